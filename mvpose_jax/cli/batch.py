"""``mvpose-jax batch``: many recordings over a pool of Ray workers, each as ``infer`` runs it.

Options -> one `jobs.batch.BatchConfig` -> `jobs.batch.run_batch` -> a line per recording and a
summary. Exit status 1 when any recording failed (its error in the summary and in
``OUT/batch.json``), 130 when interrupted.
"""

from __future__ import annotations

import argparse
import sys

from mvpose_jax.cli.infer import (
    add_pipeline_arguments,
    add_tracking_arguments,
    named_by_option,
    pipeline_config,
)
from mvpose_jax.cli.options import add_pool_arguments, add_rig_argument, pool_config, rig_source
from mvpose_jax.cli.registry import command
from mvpose_jax.errors import InputError


def _batch_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "source",
        help="a Pose2Sim project (session, participant or trial folder: every trial, as infer "
        "--session does), a folder of recordings (every .json, .npz and OpenPose folder in it; "
        "--rig their calibration) or a manifest file (a line per recording: RECORDING "
        "CALIBRATION [OUTPUT], tab- or space-separated, paths relative to the file)",
    )
    p.add_argument(
        "--out",
        required=True,
        help="output folder: OUT/<trial>/ per Pose2Sim trial, OUT/<recording>/ per recording "
        "(as infer writes them), and the run manifest OUT/batch.json (each recording's status, "
        "error, output); on a cluster, a path every machine sees or an fsspec URL "
        "(s3://bucket/run, gs://..., file:///shared/run: each worker uploads its results)",
    )
    add_rig_argument(p, default=None, required=False)
    p.add_argument(
        "--layout",
        default=None,
        help="keypoint layout to work in (default: the file's; coco18 for a Pose2Sim project)",
    )
    add_pipeline_arguments(p)
    add_tracking_arguments(p)
    p.add_argument(
        "--no-trc",
        action="store_true",
        help="Pose2Sim projects: no TRC files in OUT/<trial>/pose-3d/",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="skip the recordings OUT/batch.json records as done (same settings, output still "
        "there); the others continue their own unfinished infer run",
    )
    p.add_argument(
        "--keep-chunks", action="store_true", help="keep each recording's OUT/.../chunks/"
    )
    add_pool_arguments(p)


@command(
    "batch",
    "Many recordings (a Pose2Sim session, a folder, a manifest file) on a pool of Ray workers, "
    "here or on a cluster (--address): a dead worker's recording is run again, --resume skips "
    'the done ones (needs pip install "mvpose-jax[cluster]").',
    _batch_arguments,
)
def _batch(args: argparse.Namespace) -> int:
    from mvpose_jax.jobs.batch import BatchConfig, run_batch

    config = BatchConfig(
        args.source,
        args.out,
        rig=rig_source(args) if args.rig else None,
        pipeline=pipeline_config(args),
        matcher=args.matcher,
        estimator=args.estimator,
        layout=args.layout,
        fps=args.fps,
        trc=not args.no_trc,
        resume=args.resume,
        keep_chunks=args.keep_chunks,
        pool=pool_config(args),
    )

    def on_done(status) -> None:
        if status.status == "done":
            print(
                f"done {status.name}: {status.frames} frames in {status.seconds:.1f} s "
                f"(worker {status.worker})"
            )
        else:
            print(f"failed {status.name}: {status.error}", file=sys.stderr)

    try:
        res = run_batch(config, on_done=on_done)
    except InputError as e:
        raise named_by_option(e) from None
    return print_summary(res, "batch")


def print_summary(res, name: str) -> int:
    """Prints a batch's summary; returns the exit status (1 when a recording failed, 130 when
    interrupted)."""
    counts = {s: sum(r.status == s for r in res.recordings) for s in ("done", "skipped", "failed")}
    rate = res.frames / max(res.seconds, 1e-9)
    print(
        f"{len(res.recordings)} recordings: {counts['done']} done, {counts['skipped']} skipped "
        f"(done before), {counts['failed']} failed; {res.frames} frames in {res.seconds:.1f} s "
        f"({rate:.1f} frames/s) on {res.workers} workers; run manifest {res.manifest}"
    )
    for r in res.failed:
        print(f"mvpose-jax {name}: failed {r.name}: {r.error}", file=sys.stderr)
    if res.interrupted:
        print(
            f"mvpose-jax {name}: interrupted: the same command with --resume skips the "
            "recordings done",
            file=sys.stderr,
        )
        return 130
    return 1 if res.failed else 0
