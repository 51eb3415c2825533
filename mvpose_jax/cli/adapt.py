"""``mvpose-jax adapt``: a trained estimator (and matcher) fine-tuned on a recording's own
detections."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import (
    adapt_settings,
    add_adapt_arguments,
    add_proposal_arguments,
    detection_arguments,
    detections_source,
    print_adapt_report,
    print_dev_quality,
    proposal_options,
    rig_source,
)
from mvpose_jax.cli.registry import command
from mvpose_jax.jobs.adapt import MATCHER_ADAPT_STEPS, AdaptJob, adapt

#   mvpose-jax adapt --rig calib.toml --detections rec.npz --estimator est/ --out est_rec/


def _adapt_arguments(p: argparse.ArgumentParser) -> None:
    detection_arguments(p)
    p.add_argument(
        "--cameras", nargs="+", help="use only these cameras of the recording (default: all)"
    )
    p.add_argument(
        "--estimator",
        "--model",
        dest="estimator",
        required=True,
        help="folder of the trained estimator to start from (train-estimator --out, or an "
        "earlier adapt --out)",
    )
    p.add_argument(
        "--matcher",
        help="group the detections into people with this trained matcher (train-matcher --out); "
        "default: the geometric matcher (symmetric epipolar distance) on every camera",
    )
    add_proposal_arguments(p)
    p.add_argument("--out", required=True, help="the adapted model's folder (new or empty)")
    p.add_argument(
        "--matcher-out",
        help="also adapt the matcher (--matcher) to the recording first, on the combined "
        "proposals' groups as labels (no truth), and write it to this folder (new or empty; "
        "`infer --matcher` loads it); the estimator then adapts behind its proposals",
    )
    p.add_argument(
        "--matcher-max-steps",
        type=int,
        default=MATCHER_ADAPT_STEPS,
        help="--matcher-out: most steps of the matcher's adaptation (held-out frames stop it "
        "earlier); the command keeps one wall-clock budget (--max-seconds), of which the "
        "matcher takes at most half",
    )
    p.add_argument("--seed", type=int, default=0, help="batch order and augmentation")
    add_adapt_arguments(p)


@command(
    "adapt",
    "Fine-tune a trained 3D estimator on a recording's own detections (no labels: grouped by "
    "the proposals, reprojection loss, held-out frames stop it); writes a model infer loads.",
    _adapt_arguments,
)
def _adapt(args: argparse.Namespace) -> int:
    job = AdaptJob(
        rig=rig_source(args),
        detections=detections_source(args),
        estimator=args.estimator,
        out=args.out,
        matcher=args.matcher,
        proposals=proposal_options(args),
        matcher_out=args.matcher_out,
        matcher_max_steps=args.matcher_max_steps,
        seed=args.seed,
        settings=adapt_settings(args),
    )
    done = adapt(job)
    if done.matcher_report is not None:
        r = done.matcher_report
        print(
            f"adapted the matcher on {r.frames_adapt} frames ({r.pairs_adapt} pairs labelled by "
            f"the combined proposals): held-out pseudo-label loss {r.heldout_loss_before:.4f} -> "
            f"{r.heldout_loss_after:.4f} (agreement {r.heldout_accuracy_before:.3f} -> "
            f"{r.heldout_accuracy_after:.3f}), step {r.best_step} of {r.steps} ({r.stopped}), "
            f"{r.seconds:.0f} s; GAT threshold {r.threshold:g} (chosen on the held-out frames); "
            f"wrote {args.matcher_out}"
        )
    print_adapt_report(done.report)
    print(
        f"wrote {args.out} (`infer --estimator {args.out}` loads it) and its report "
        f"{done.report_path}"
    )
    print_dev_quality(done.dev_quality)
    return 0
