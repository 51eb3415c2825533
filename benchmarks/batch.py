"""The ``batch`` group: many recordings on a local Ray, 1 and 2 workers (`jobs.batch.run_batch`).

What ``mvpose-jax batch`` runs, on this machine: ``recordings`` synthetic panoptic5 recordings
(5 cameras, 4 people, ``frames`` each, `.npz`) through the geometric pipeline of ``infer``
(`jobs.infer.INFER_PIPELINE` without models: epipolar proposals, DLT, tracking, the Butterworth
filter), each written to its own output folder by the worker that ran it.

- Start-up: a first batch on fresh workers (as many as the machine's CPUs, at most 2) measures
  ``worker_start_s`` (Ray's actor process started and JAX imported, from the pool's start:
  `BatchResult.startup_s`) and ``first_recording_extra_s`` (a worker's first recording less the
  median of its later ones: the XLA compiles; no models to load here).
- Throughput: the same recordings with 1 and then 2 workers, warm (the start-up batch's
  workers, kept by the job between batches of one driver), alternated `REPEATS` times, the
  fastest batch of each: ``recordings_per_s`` and ``frames_per_s`` over its wall time, and
  their ratio (2 workers / 1).

One Ray for the group (``ray.init(num_cpus=min(2, CPUs))``), stopped at its end.
"""

from __future__ import annotations

import os
import statistics
import tempfile
from pathlib import Path

# tier -> (recordings, frames per recording)
SIZES = {"full": (16, 200), "quick": (8, 60), "smoke": (2, 4)}
# Timed batches per worker count, alternated; the fastest counts: a worker compiles the shapes of
# the recordings it has not met yet (the start-up batch split them between the workers).
REPEATS = {"full": 3, "quick": 3, "smoke": 1}
PEOPLE = 4


def batch_group(tier: str) -> dict:
    """The group's record (the module docstring)."""
    import ray

    from benchmarks import scenes
    from mvpose_jax.data import save_recording
    from mvpose_jax.jobs.batch import BatchConfig, PoolConfig, run_batch
    from mvpose_jax.jobs.common import RigSource

    recordings, frames = SIZES[tier]
    cpus = max(1, min(2, os.cpu_count() or 1))
    with tempfile.TemporaryDirectory(prefix="mvpose-bench-batch-") as tmp:
        folder = Path(tmp) / "recordings"
        folder.mkdir()
        for i in range(recordings):
            rig, rec = scenes.recording(5, PEOPLE, frames, seed=100 + i)
            save_recording(rec, folder / f"rec_{i:03d}.npz")
        rig_file = Path(tmp) / "rig.json"
        from mvpose_jax.data.calibration import save_rig

        save_rig(rig, rig_file)

        def batch(name: str, workers: int):
            config = BatchConfig(
                str(folder),
                str(Path(tmp) / name),
                rig=RigSource(str(rig_file)),
                pool=PoolConfig(workers=workers, keep_workers=True),
                progress=False,
            )
            res = run_batch(config)
            bad = [r for r in res.recordings if r.status != "done"]
            if bad:
                raise RuntimeError(f"batch {name}: {bad[0].name} {bad[0].status}: {bad[0].error}")
            return res

        ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
        try:
            start = batch("start", cpus)
            runs: dict[int, list] = {}
            for i in range(REPEATS[tier]):
                for w in sorted({1, cpus}):
                    runs.setdefault(w, []).append(batch(f"workers_{w}_{i}", w))
            rows = [_row(min(r, key=lambda res: res.seconds), frames) for r in runs.values()]
        finally:
            ray.shutdown()
    by_worker: dict[str, list[float]] = {}
    for r in start.recordings:  # in the order each worker ran them (the batch's order)
        by_worker.setdefault(r.worker, []).append(r.seconds)
    extra = [runs[0] - statistics.median(runs[1:]) for runs in by_worker.values() if len(runs) > 1]
    ratio = rows[-1]["frames_per_s"] / rows[0]["frames_per_s"] if len(rows) > 1 else None
    return {
        "recordings": recordings,
        "frames_per_recording": frames,
        "views": 5,
        "people": PEOPLE,
        "pipeline": "infer's geometric default (epipolar, DLT, tracking, Butterworth), no models",
        "ray_cpus": cpus,
        "worker_start_s": start.startup_s,
        "first_recording_extra_s": statistics.median(extra) if extra else None,
        "start_batch_seconds": start.seconds,
        "rows": rows,
        "ratio_2_to_1": ratio,
        "repeats": REPEATS[tier],
    }


def _row(res, frames: int) -> dict:
    n = len(res.recordings)
    return {
        "workers": res.workers,
        "seconds": res.seconds,
        "recordings_per_s": n / res.seconds,
        "frames_per_s": n * frames / res.seconds,
    }


def markdown(result: dict) -> list[str]:
    """The group's table (lines of Markdown)."""
    lines = [
        "",
        f"## Many recordings on Ray (`batch`: {result['recordings']} recordings of "
        f"{result['frames_per_recording']} frames, {result['views']} views, {result['people']} "
        f"people; {result['pipeline']}; local Ray of {result['ray_cpus']} CPUs, warm workers)",
        "",
        "| workers | seconds | recordings/s | frames/s |",
        "|---|---|---|---|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['workers']} | {r['seconds']:.2f} | {r['recordings_per_s']:.2f} | "
            f"{r['frames_per_s']:.1f} |"
        )
    ratio = result["ratio_2_to_1"]
    start = result["worker_start_s"]
    extra = result["first_recording_extra_s"]
    lines += [
        "",
        f"2 workers / 1: {'-' if ratio is None else f'{ratio:.2f}'}x. Per-worker start-up: "
        f"{'-' if start is None else f'{start:.1f}'} s to a worker with JAX imported (Ray's "
        f"process and imports), then {'-' if extra is None else f'{extra:.1f}'} s more on its "
        "first recording (XLA compiles).",
    ]
    return lines
