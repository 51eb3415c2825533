"""``mvpose-jax train-matcher`` and ``train-estimator``: model folders from single-person
recordings (no labels)."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import add_training_arguments, print_dev_quality, training_run
from mvpose_jax.cli.registry import command
from mvpose_jax.jobs.train import (
    EstimatorJob,
    MatcherJob,
    TemporalJob,
    train_estimator_job,
    train_matcher_job,
    train_temporal_job,
)


def _train_matcher_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p)
    p.add_argument(
        "--cameras", nargs="+", help="inference cameras C_i (default: every camera of the rig)"
    )
    p.add_argument("--quick", action="store_true", help="small network and short epochs")
    p.add_argument("--max-epochs", type=int, help="override the epoch limit")
    p.add_argument("--learning-rate", type=float, help="override Adam's step size (paper 1e-4)")
    p.add_argument(
        "--max-people", type=int, help="most recordings composed into one frame (default 8)"
    )
    p.add_argument(
        "--keypoint-dropout",
        type=float,
        help="missing-keypoint augmentation: largest per-skeleton drop rate (default 0, the paper; "
        "python -m experiments.run uses 0.5)",
    )
    p.add_argument(
        "--start",
        metavar="MODEL",
        help="fine-tune this rig-agnostic matcher instead of training a new one: a model folder, "
        "or 'pretrained' (the one shipped in the package, for any rig); its network replaces "
        "--quick's",
    )


@command(
    "train-matcher",
    "Train the skeleton-matching GAT from single-person recordings (no labels needed).",
    _train_matcher_arguments,
)
def _train_matcher(args: argparse.Namespace) -> int:
    job = MatcherJob(
        run=training_run(args),
        cameras=tuple(args.cameras) if args.cameras else None,
        quick=args.quick,
        max_epochs=args.max_epochs,
        learning_rate=args.learning_rate,
        max_people=args.max_people,
        keypoint_dropout=args.keypoint_dropout,
        start=args.start,
    )
    done = train_matcher_job(job)
    print(
        f"best validation loss {done.best_val_loss:.5f} after {done.steps} steps ({done.seconds:.0f} s); "
        f"checkpoints in {args.out}"
    )
    if done.proposals is not None:
        threshold, ari, combined, combined_ari = done.proposals
        print(
            f"proposal threshold {threshold} (ARI {ari[threshold]:.4f} on multi-person frames composed from "
            f"--dev; 0.5: {ari[0.5]:.4f}); combined matcher: threshold {combined.threshold}, "
            f"epipolar cutoff {combined.epipolar_cutoff_px:g} px (ARI "
            f"{combined_ari[combined.threshold]:.4f}); used by "
            f"`infer --matcher {args.out}`"
        )
    return 0


def _train_estimator_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(
        p, dev_help="validation recordings (default: the last 10%% of --train's frames)"
    )
    p.add_argument(
        "--train-cameras", nargs="+", help="training cameras C_t (default: every camera of the rig)"
    )
    p.add_argument(
        "--infer-cameras", nargs="+", help="inference cameras C_i, a subset of C_t (default: C_t)"
    )
    p.add_argument(
        "--paper-size",
        action="store_true",
        help="the paper's widths (3072 ... 1024); default: quick",
    )
    p.add_argument(
        "--output",
        choices=("absolute", "anchored", "residual"),
        default="residual",
        help="what the MLP predicts: absolute = the paper's; residual = offsets from the "
        "triangulated initial estimate (default; see models.MLPConfig)",
    )
    p.add_argument(
        "--loss-power",
        type=float,
        default=1.0,
        help="per-sample loss e^power (paper: 2; 1 resists gross detector errors)",
    )
    p.add_argument(
        "--augment", type=int, default=4, help="view-subset samples per seed sample (paper: 4)"
    )
    p.add_argument("--steps", type=int, default=4000, help="training steps")
    p.add_argument("--batch-size", type=int, default=256, help="people per training step")
    p.add_argument("--learning-rate", type=float, default=1e-3, help="Adam's initial step size")
    p.add_argument("--constant-lr", action="store_true", help="no cosine decay (the paper's)")
    p.add_argument(
        "--patience", type=int, default=20, help="validations without improvement before stopping"
    )
    p.add_argument(
        "--start",
        metavar="MODEL",
        help="fine-tune this estimator instead of training a new one: a model folder, or "
        "'pretrained' (the rig-agnostic estimator shipped in the package, for any rig); its "
        "network replaces --paper-size and --output, and a rig-agnostic one trains on every "
        "camera of the rig",
    )


@command(
    "train-estimator",
    "Train the 3D estimator from single-person recordings with the reprojection loss (no 3D labels).",
    _train_estimator_arguments,
)
def _train_estimator(args: argparse.Namespace) -> int:
    job = EstimatorJob(
        run=training_run(args),
        train_cameras=tuple(args.train_cameras) if args.train_cameras else None,
        infer_cameras=tuple(args.infer_cameras) if args.infer_cameras else None,
        paper_size=args.paper_size,
        output=args.output,
        loss_power=args.loss_power,
        augment=args.augment,
        steps=args.steps,
        batch_size=args.batch_size,
        learning_rate=args.learning_rate,
        constant_lr=args.constant_lr,
        patience=args.patience,
        start=args.start,
    )
    done = train_estimator_job(job)
    print(
        f"{done.people} training people; best validation reprojection error "
        f"{done.best_px_per_keypoint:.2f} px per keypoint after {done.steps} steps "
        f"({done.seconds:.0f} s); checkpoints in {args.out}"
    )
    print_dev_quality(done.dev_quality)
    return 0


def _train_temporal_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(
        p, dev_help="validation recordings (default: the last 10%% of --train's windows)"
    )
    p.add_argument("--steps", type=int, default=1500, help="training steps (default 1500)")
    p.add_argument(
        "--learning-rate", type=float, default=1e-3, help="Adam's step size (default 1e-3)"
    )
    p.add_argument("--window", type=int, default=32, help="frames per window (default 32)")
    p.add_argument("--start", metavar="MODEL", help="a temporal model folder to fine-tune")
    p.add_argument(
        "--multi-person",
        action="store_true",
        help="the recordings hold several people (e.g. your own recording, to fine-tune on): "
        "the geometric pipeline tracks them and the model trains on its tracks",
    )


@command(
    "train-temporal",
    "Train the learned temporal stage from recordings (no 3D labels); `infer --temporal`.",
    _train_temporal_arguments,
)
def _train_temporal(args: argparse.Namespace) -> int:
    job = TemporalJob(
        run=training_run(args),
        steps=args.steps,
        learning_rate=args.learning_rate,
        window=args.window,
        start=args.start,
        multi_person=args.multi_person,
    )
    done = train_temporal_job(job)
    print(
        f"{done.train_windows} training and {done.dev_windows} dev windows; dev loss "
        f"{done.initial_dev_loss:.2f} -> {done.dev_loss:.2f} (step {done.best_step}, "
        f"{done.seconds:.0f} s); model in {args.out}, used by `infer --temporal {args.out}`"
    )
    return 0
