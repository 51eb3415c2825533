"""The ``mvpose-jax`` command line: one entry point, one subcommand per job.

Each subcommand parses its options and calls the library; nothing here computes.
Bad input ends with a one-line error naming the file, frame, camera and field (exit status 2).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence

from mvpose_jax.errors import InputError, MvposeError

# name -> (help, add_arguments(parser), run(args) -> exit status)
_COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {}


def command(name: str, help: str, arguments: Callable[[argparse.ArgumentParser], None]):
    """Registers the decorated ``run(args) -> exit status`` as subcommand ``name``."""

    def register(run):
        _COMMANDS[name] = (help, arguments, run)
        return run

    return register


def add_rig_argument(p: argparse.ArgumentParser, default: str | None = "panoptic5") -> None:
    """The ``--rig`` option every subcommand that needs cameras shares."""
    p.add_argument(
        "--rig", default=default, required=default is None,
        help="preset name (panoptic5, arplab6) or calibration file (.json native or CMU Panoptic, "
        ".toml anipose/Pose2Sim)",
    )  # fmt: skip
    p.add_argument(
        "--translation-scale", type=float, default=1.0,
        help="TOML calibrations only: metres per translation unit (0.001 for millimetres)",
    )  # fmt: skip


@command("rig", "Show a rig (preset or calibration file): cameras, centres, image sizes, up.", add_rig_argument)
def _rig(args: argparse.Namespace) -> int:
    import numpy as np

    from mvpose_jax.cameras import camera_centres, rig_centre_and_radius, up_vector
    from mvpose_jax.data.calibration import load_rig

    rig = load_rig(args.rig, translation_scale=args.translation_scale)
    centres = np.asarray(camera_centres(rig), np.float64)
    centre, radius = rig_centre_and_radius(rig)
    print(f"{rig.num_cameras} cameras; up {np.round(up_vector(rig), 3).tolist()}"
          f"{' (inferred)' if rig.up is None else ''}; centre {np.round(np.asarray(centre, np.float64), 3).tolist()} m,"
          f" radius {float(radius):.3f} m")
    for c, name in enumerate(rig.names):
        w, h = np.asarray(rig.size[c]).astype(int)
        print(f"  {name:>12s}  {w}x{h}  f={float(rig.K[c, 0, 0]):.1f}px  centre {np.round(centres[c], 3).tolist()}")
    return 0


def _generate_arguments(p: argparse.ArgumentParser) -> None:
    from mvpose_jax.data.synthetic.cli import add_generate_arguments

    add_rig_argument(p)
    add_generate_arguments(p)


@command(
    "generate",
    "Generate a synthetic recording (or single-person training recordings) on any rig.",
    _generate_arguments,
)
def _generate(args: argparse.Namespace) -> int:
    from mvpose_jax.data.synthetic.cli import run_generate

    return run_generate(args)


# --------------------------------------------------------------------------- train-matcher


def _recordings_in(path: str, layout: str | None) -> list:
    """Every recording in a file or (recursively) a folder (.npz and .json, any readable format)."""
    from pathlib import Path

    from mvpose_jax.data import load_recording
    from mvpose_jax.errors import InputError

    root = Path(path)
    if root.is_dir():
        files = sorted(p for p in root.rglob("*") if p.suffix.lower() in (".npz", ".json"))
    elif root.exists():
        files = [root]
    else:
        raise InputError("no such file or folder", file=root)
    if not files:
        raise InputError("no recordings (.npz or .json) here", file=root)
    return [load_recording(f, layout=layout) for f in files]


def add_training_arguments(p: argparse.ArgumentParser, *, dev_help: str | None = None) -> None:
    """Options every training command shares: rig, data, output folder, layout and seed."""
    add_rig_argument(p, default=None)
    p.add_argument("--train", required=True, help="single-person recordings: a file or a folder of them")
    p.add_argument("--dev", required=dev_help is None,
                   help=dev_help or "single-person validation recordings: a file or folder")  # fmt: skip
    p.add_argument("--out", required=True, help="folder for the best and latest checkpoints")
    p.add_argument("--layout", default=None, help="keypoint layout to convert the recordings to")
    p.add_argument("--seed", type=int, default=0)


def _train_matcher_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p)
    p.add_argument("--cameras", nargs="+", help="inference cameras C_i (default: every camera of the rig)")
    p.add_argument("--quick", action="store_true", help="small network and short epochs")
    p.add_argument("--max-epochs", type=int, help="override the epoch limit")
    p.add_argument("--learning-rate", type=float, help="override Adam's step size (paper 1e-4)")
    p.add_argument("--max-people", type=int, help="most recordings composed into one frame (default 8)")


@command(
    "train-matcher",
    "Train the skeleton-matching GAT from single-person recordings (no labels needed).",
    _train_matcher_arguments,
)
def _train_matcher(args: argparse.Namespace) -> int:
    import dataclasses

    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.train import MatcherConfig, train_matcher

    rig = load_rig(args.rig, translation_scale=args.translation_scale)
    config = MatcherConfig.quick() if args.quick else MatcherConfig()
    train = dataclasses.replace(
        config.train, seed=args.seed,
        **{k: v for k, v in (("max_epochs", args.max_epochs), ("learning_rate", args.learning_rate)) if v is not None},
    )  # fmt: skip
    config = dataclasses.replace(
        config, train=train, cameras=tuple(args.cameras) if args.cameras else None,
        **({"max_people": args.max_people} if args.max_people else {}),
    )  # fmt: skip
    train_recs = _recordings_in(args.train, args.layout)
    dev_recs = _recordings_in(args.dev, args.layout)
    _, fit = train_matcher(rig, train_recs, dev_recs, config, checkpoint_dir=args.out)
    print(f"best validation loss {fit.best_val_loss:.5f} after {fit.steps} steps ({fit.seconds:.0f} s); "
          f"checkpoints in {args.out}")  # fmt: skip
    return 0


def _train_estimator_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p, dev_help="validation recordings (default: the last 10%% of --train's frames)")
    p.add_argument("--train-cameras", nargs="+", help="training cameras C_t (default: every camera of the rig)")
    p.add_argument("--infer-cameras", nargs="+", help="inference cameras C_i, a subset of C_t (default: C_t)")
    p.add_argument("--paper-size", action="store_true", help="the paper's widths (3072 ... 1024); default: quick")
    p.add_argument("--output", choices=("absolute", "anchored", "residual"), default="residual",
                   help="what the MLP predicts: absolute = the paper's; residual = offsets from the "
                   "triangulated initial estimate (default; see models.MLPConfig)")  # fmt: skip
    p.add_argument("--loss-power", type=float, default=1.0,
                   help="per-sample loss e^power (paper: 2; 1 resists gross detector errors)")  # fmt: skip
    p.add_argument("--augment", type=int, default=4, help="view-subset samples per seed sample (paper: 4)")
    p.add_argument("--steps", type=int, default=4000, help="training steps")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--learning-rate", type=float, default=1e-3, help="Adam's initial step size")
    p.add_argument("--constant-lr", action="store_true", help="no cosine decay (the paper's)")
    p.add_argument("--patience", type=int, default=20, help="validations without improvement before stopping")
    p.add_argument("--resume", action="store_true",
                   help="continue from the latest checkpoint in --out (same settings; --steps may grow)")  # fmt: skip


@command(
    "train-estimator",
    "Train the 3D estimator from single-person recordings with the reprojection loss (no 3D labels).",
    _train_estimator_arguments,
)
def _train_estimator(args: argparse.Namespace) -> int:
    import numpy as np

    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.features import main_skeletons
    from mvpose_jax.models import MLPConfig
    from mvpose_jax.train import EstimatorConfig, TrainConfig, train_estimator

    rig = load_rig(args.rig, translation_scale=args.translation_scale)
    train_cams = tuple(args.train_cameras or rig.names)
    infer_cams = tuple(args.infer_cameras or train_cams)
    for c in train_cams:
        rig.camera_index(c)  # unknown names fail here, naming the camera

    def samples(recordings):
        xy, score = [], []
        for rec in recordings:
            missing = [c for c in train_cams if c not in rec.cameras]
            if missing:
                raise InputError(f"recording lacks training cameras {missing}", field="cameras")
            idx = [rec.cameras.index(c) for c in train_cams]
            m_xy, m_score = main_skeletons(np.asarray(rec.detections.xy)[:, idx], np.asarray(rec.detections.score)[:, idx])
            xy.append(m_xy)
            score.append(m_score)
        return np.concatenate(xy), np.concatenate(score)

    xy, score = samples(_recordings_in(args.train, args.layout))
    if args.dev:
        dev_xy, dev_score = samples(_recordings_in(args.dev, args.layout))
    else:
        n = max(1, len(xy) // 10)
        xy, score, dev_xy, dev_score = xy[:-n], score[:-n], xy[-n:], score[-n:]
    mlp = MLPConfig() if args.paper_size else MLPConfig.quick()
    config = EstimatorConfig(
        train_cameras=train_cams, infer_cameras=infer_cams,
        mlp=MLPConfig(widths=mlp.widths, output=args.output), num_augment=args.augment,
        loss_power=args.loss_power,
        train=TrainConfig(learning_rate=args.learning_rate, batch_size=args.batch_size,
                          max_steps=args.steps, patience=args.patience, seed=args.seed,
                          final_lr_fraction=1.0 if args.constant_lr else 0.01),
    )  # fmt: skip
    _, fit = train_estimator(rig.select(list(train_cams)), xy, score, dev_xy, dev_score, config,
                             checkpoint_dir=args.out, resume=args.resume)  # fmt: skip
    best = min(fit.history, key=lambda h: h["val_loss"]) if fit.history else {}
    print(f"{len(xy)} training people; best validation reprojection error "
          f"{best.get('val_px_per_keypoint', float('nan')):.2f} px per keypoint after {fit.steps} steps "
          f"({fit.seconds:.0f} s); checkpoints in {args.out}")  # fmt: skip
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mvpose-jax", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_, add, _) in _COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        add(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _COMMANDS[args.command][2](args) or 0
    except MvposeError as e:
        print(f"mvpose-jax {args.command}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader went away (`mvpose-jax rig | head`): not our error; silence the final flush.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
