"""One 3D estimator for any rig: ``python -m experiments.pretrain --out DIR [--scale quick]``.

Pretrains the rig-agnostic estimator (`models.ViewPooledMLP`, `pretraining.pretrain_estimator`)
without labels on single-person recordings of random rigs of the families in
`synthetic.rigs.PRETRAIN_FAMILIES`, then compares it on rigs it never saw, against an estimator
trained on each rig with the same number of steps (the recipe of every other experiment, the
paper's per-camera network) and against itself fine-tuned on the rig for a tenth of them:

* the paper's two rigs (``panoptic5``, ``arplab6``);
* one rig of each family held out of pretraining (`synthetic.rigs.HELD_OUT_FAMILIES`).

Every rig's multi-person scenes (1-8 people, the default detector) come from the validation and
test seed streams; the table reports the test scenes, the 3D stage on the true groupings of people
seen by 2+ views (the estimator alone, ``mlp``, and the default ``blend``), beside robust
triangulation. Nothing is chosen here: the recipe's settings are `PRETRAIN_SCALES`' (the learning
rate was picked on the dev rigs' reprojection error, see docs/pretrained.md).

Writes ``DIR/pretrain.md``, ``DIR/pretrain.json`` and the model folder ``DIR/models/pretrained``
(what ``mvpose-jax infer --estimator DIR/models/pretrained`` and the package's shipped weights
are).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Iterator
from pathlib import Path

from experiments.config import SCALES, SPLITS, Scale, estimator_config, seed_stream
from experiments.data import make_data, make_scenes, true_members
from experiments.fitting import fit_estimator
from experiments.real_detectors import DETECTORS, training_detectors
from experiments.records import report_json
from experiments.tables import diff_mean_sd, mean_sd, rounded, seeds_line
from mvpose_jax.cameras import Rig, up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.estimator_training import train_estimator
from mvpose_jax.features import single_person_samples
from mvpose_jax.lifting import poses_of_members
from mvpose_jax.metrics import pose_metrics
from mvpose_jax.models import MLPConfig
from mvpose_jax.pretraining import RigPeople, pretrain_estimator
from mvpose_jax.progress import progress_bar
from mvpose_jax.synthetic import DetectorConfig, SyntheticConfig, generate_single_person_recordings
from mvpose_jax.synthetic.rigs import HELD_OUT_FAMILIES, PRETRAIN_FAMILIES, random_rig
from mvpose_jax.trained import EstimatorConfig, load_estimator


@dataclasses.dataclass(frozen=True)
class PretrainScale:
    """How much pretraining, and the per-rig comparison's scale.

    Attributes:
      train_rigs, dev_rigs: random rigs of the pretraining families (in turn).
      recordings_per_rig, frames: single-person recordings per rig, frames each.
      estimator: the rig-agnostic estimator and its training (steps, batch, rate).
      rig_scale: the `experiments.config.SCALES` entry of the per-rig comparison (its training
        recordings and scenes); its estimator trains for the same steps as pretraining.
      finetune_fraction: fine-tuning on a rig takes this fraction of the steps.
    """

    train_rigs: int
    dev_rigs: int
    recordings_per_rig: int
    frames: int
    estimator: EstimatorConfig
    rig_scale: str
    finetune_fraction: float = 0.1


def pooled_config(steps: int, batch: int = 256, lr: float = 3e-4, widths=None) -> EstimatorConfig:
    """Our estimator recipe (`experiments.config.estimator_config`) for the rig-agnostic network,
    at step size ``lr``, validated every 5 epochs."""
    mlp = MLPConfig.pooled() if widths is None else MLPConfig(**widths)
    config = estimator_config(mlp, steps, batch)
    return dataclasses.replace(
        config, train=dataclasses.replace(config.train, learning_rate=lr, eval_every=5)
    )


PRETRAIN_SCALES = {
    "smoke": PretrainScale(
        train_rigs=5,
        dev_rigs=2,
        recordings_per_rig=2,
        frames=10,
        estimator=pooled_config(
            steps=6,
            batch=32,
            widths=dict(widths=(32,), output="residual", views="pooled", view_widths=(32,)),
        ),
        rig_scale="smoke",
        finetune_fraction=0.5,
    ),
    "quick": PretrainScale(
        train_rigs=1500,
        dev_rigs=40,
        recordings_per_rig=2,
        frames=20,
        estimator=pooled_config(steps=3000),
        rig_scale="quick",
    ),
}

EVAL_RIG_SEED = 35
# Fine-tuning's candidate step sizes (Adam, cosine decay over its steps), one chosen per rig on
# the rig's validation scenes.
FINETUNE_RATES = (1e-4, 3e-5)  # the held-out families' rigs: fixed, whatever the training seed


def random_rig_recordings(
    n: int,
    at: list[int],
    recordings_per_rig: int,
    frames: int,
    detectors: tuple[DetectorConfig, ...],
    progress,
    desc: str,
) -> Iterator[tuple[Rig, list]]:
    """``n`` random rigs of the pretraining families, in turn, each with its single-person
    recordings: rig ``i`` is drawn at seed ``[*at, i]`` (z-up, its own floor; drawing a rig,
    with its capture area, is most of the time) and its recordings at ``[*at, i, 1]``, from
    detector ``i mod len(detectors)``. Yields (rig, recordings) one rig at a time."""
    for i in progress_bar(range(n), desc=desc, unit="rig", disable=not progress):
        family = PRETRAIN_FAMILIES[i % len(PRETRAIN_FAMILIES)]
        rig, floor = random_rig(family, [*at, i])
        config = SyntheticConfig(detector=detectors[i % len(detectors)]).with_scene(
            up=(0.0, 0.0, 1.0), floor_height=floor
        )
        recs = generate_single_person_recordings(
            rig,
            num_recordings=recordings_per_rig,
            num_frames=frames,
            config=config,
            seed=[*at, i, 1],
        )
        yield rig, recs


def rig_people(
    n: int,
    sc: PretrainScale,
    stream: str,
    seed: int,
    progress,
    detectors: tuple[DetectorConfig, ...] = (DetectorConfig(),),
) -> list[RigPeople]:
    """`random_rig_recordings` of seed stream ``stream`` as `RigPeople` (each rig's recordings
    turned into people as they are made)."""
    rigs = random_rig_recordings(
        n,
        seed_stream(stream, seed),
        sc.recordings_per_rig,
        sc.frames,
        detectors,
        progress,
        f"{stream} rigs",
    )
    return [RigPeople(rig, *single_person_samples(recs)) for rig, recs in rigs]


def evaluation_rigs() -> dict[str, tuple[Rig, float | None]]:
    """The paper's two rigs (floor guessed from the cameras) and one rig of each held-out
    family (z-up, floor given)."""
    rigs: dict[str, tuple[Rig, float | None]] = {
        name: (load_rig(name), None) for name in ("panoptic5", "arplab6")
    }
    for j, family in enumerate(HELD_OUT_FAMILIES):
        rigs[family] = random_rig(family, [EVAL_RIG_SEED, j], name=family)
    return rigs


def evaluation_data(rigs, rig_sc: Scale, scenes_seed: int, seed: int, progress: bool):
    """Each evaluation rig (`evaluation_rigs`; all of them, or those named in ``rigs``) with its
    recordings and multi-person scenes at the per-rig scale ``rig_sc``: yields (name, rig, data)."""
    for name, (rig, floor) in evaluation_rigs().items():
        if rigs is not None and name not in rigs:
            continue
        print(f"== {name}: {rig.num_cameras} cameras", flush=True)
        synth = up = None
        if floor is not None:
            up = (0.0, 0.0, 1.0)
            synth = SyntheticConfig().with_scene(up=up, floor_height=floor)
        scenes = make_scenes(rig, rig_sc, scenes_seed, config=synth)
        yield name, rig, make_data(rig, scenes, rig_sc, seed, progress, floor_height=floor, up=up)


def finetune_config(config, steps: int, learning_rate: float):
    """``config`` (a model's training config: ``.train`` a `TrainConfig`) with fine-tuning's
    budget and step size."""
    train = dataclasses.replace(config.train, max_steps=steps, learning_rate=learning_rate)
    return dataclasses.replace(config, train=train)


def stage_rows(data, split: str, estimators: dict) -> dict:
    """The 3D stage on a split's true groupings (people in 2+ views): robust triangulation, and
    each estimator alone (``mlp``) and in the blend."""
    rig = data.rig
    det, ident, gt, ids = data.detections(split, rig.names)
    groups = true_members(ident, gt.valid.shape[1], min_views=2)
    scoring = {"up": up_vector(rig), "person_ids": ids}
    keep = ("pcp", "mpjpe_mm")

    def score(poses, conf):
        m = pose_metrics(poses, gt, confidence=conf, **scoring)
        return {k: m[k] for k in keep}

    rows = {"robust triangulation": score(*poses_of_members(rig, det, groups, method="robust"))}
    for name, est in estimators.items():
        for method in ("mlp", "blend"):
            rows[f"{name}, {method}"] = score(
                *poses_of_members(rig, det, groups, estimator=est, method=method)
            )
    return rows


def run(
    sc: PretrainScale,
    seed: int,
    scenes_seed: int,
    out: Path,
    progress: bool,
    rigs: tuple[str, ...] | None = None,
    detectors: tuple[str, ...] = ("default",),
) -> dict:
    """Pretrains on seed ``seed`` with the simulated ``detectors`` (names of
    `real_detectors.DETECTORS`, taken in turn by the rigs) and compares on the evaluation rigs
    (`evaluation_rigs`; all of them, or those named in ``rigs``); returns the report."""
    t0 = time.perf_counter()
    configs, detector_record = training_detectors(detectors)
    train = rig_people(sc.train_rigs, sc, "train", seed, progress, configs)
    dev = rig_people(sc.dev_rigs, sc, "dev", seed, progress, configs)
    data_seconds = time.perf_counter() - t0
    config = dataclasses.replace(
        sc.estimator, train=dataclasses.replace(sc.estimator.train, seed=seed)
    )
    folder = out / "models" / "pretrained"
    t0 = time.perf_counter()
    _, fit = pretrain_estimator(train, dev, config, checkpoint_dir=folder, progress=progress)
    pretrain_seconds = time.perf_counter() - t0
    steps = config.train.max_steps
    rig_sc = SCALES[sc.rig_scale]
    rig_sc = dataclasses.replace(
        rig_sc,
        estimator=dataclasses.replace(
            rig_sc.estimator,
            train=dataclasses.replace(rig_sc.estimator.train, max_steps=steps),
        ),
    )
    finetune_steps = max(1, round(steps * sc.finetune_fraction))
    report = {
        "seed": seed,
        "scenes_seed": scenes_seed,
        "pretraining": {
            "families": list(PRETRAIN_FAMILIES),
            "rigs": {"train": sc.train_rigs, "dev": sc.dev_rigs},
            "detectors": detector_record,
            "people": {"train": sum(len(p.xy) for p in train), "dev": sum(len(p.xy) for p in dev)},
            "steps": fit.steps,
            "data_seconds": round(data_seconds, 1),
            "train_seconds": round(pretrain_seconds, 1),
            "best_val_loss": fit.best_val_loss,
            "history": fit.history,
        },
        "finetune_steps": finetune_steps,
        "rig_steps": steps,
        "rigs": {},
    }
    save(report, out)  # the pretraining's record, also when no rig is compared
    for name, rig, data in evaluation_data(rigs, rig_sc, scenes_seed, seed, progress):
        per_rig, _ = fit_estimator(data, rig_sc, rig.names, rig.names, seed, progress)
        pretrained = load_estimator(folder, rig)
        xy, score = single_person_samples(data.train, rig.names)
        dev_xy, dev_score = single_person_samples(data.dev, rig.names)
        # Fine-tuning's step size, chosen per rig on its validation scenes (the blend's PCP,
        # then the estimator's alone): a pretrained network is already near a good minimum.
        candidates = {}
        for lr in FINETUNE_RATES:
            tune = finetune_config(config, finetune_steps, lr)
            candidates[lr], _ = train_estimator(
                rig, xy, score, dev_xy, dev_score, tune, progress=progress, start=pretrained
            )
        estimators = {"per-rig": per_rig, "pretrained": pretrained}
        rows = {
            split: stage_rows(
                data, split, estimators | {f"fine-tuned {lr:g}": e for lr, e in candidates.items()}
            )
            for split in SPLITS
        }
        val = rows["validation"]
        chosen = max(
            FINETUNE_RATES,
            key=lambda lr: (
                val[f"fine-tuned {lr:g}, blend"]["pcp"],
                val[f"fine-tuned {lr:g}, mlp"]["pcp"],
            ),
        )
        for r in rows.values():
            for method in ("mlp", "blend"):
                r[f"fine-tuned, {method}"] = r[f"fine-tuned {chosen:g}, {method}"]
        report["rigs"][name] = {
            "cameras": rig.num_cameras,
            "held_out_family": name in HELD_OUT_FAMILIES,
            "finetune_learning_rate": chosen,
            **{split: rounded(r) for split, r in rows.items()},
        }
        save(report, out)
    return report


def table(report: dict, split: str = "test") -> list[str]:
    """PCP and MPJPE per evaluation rig and 3D stage."""
    rigs = report["rigs"]
    if not rigs:
        return ["(no evaluation rig: pretraining only, `--rigs none`)"]
    rows = next(iter(rigs.values()))[split]
    head = "| 3D stage (true groupings) | " + " | ".join(
        f"{r} ({v['cameras']} cams{', held-out family' if v['held_out_family'] else ''})"
        for r, v in rigs.items()
    )
    lines = [head + " |", "|---" * (len(rigs) + 1) + "|"]
    for row in [r for r in rows if not r.startswith("fine-tuned ")]:
        cells = [
            f"{v[split][row]['pcp']:.1f} / {v[split][row]['mpjpe_mm']:.1f}" for v in rigs.values()
        ]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return lines


def seeds_table(reports: list[dict], split: str = "test") -> list[str]:
    """Avg PCP per evaluation rig and 3D stage over training seeds (mean ± sd), with each
    pretrained row's difference from the per-rig row of the same seed."""
    rigs = list(reports[0]["rigs"])
    head = "| 3D stage (true groupings), avg PCP % | " + " | ".join(rigs) + " |"
    lines = [seeds_line(reports), "", head, "|---" * (len(rigs) + 1) + "|"]
    rows = [r for r in reports[0]["rigs"][rigs[0]][split] if not r.startswith("fine-tuned ")]
    for row in rows:
        cells = [mean_sd(reports, ("rigs", rig, split, row, "pcp"), 1) for rig in rigs]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
        who, _, method = row.partition(", ")
        if who in ("pretrained", "fine-tuned"):
            diffs = [
                diff_mean_sd(
                    reports,
                    ("rigs", rig, split, row, "pcp"),
                    ("rigs", rig, split, f"per-rig, {method}", "pcp"),
                    1,
                )
                for rig in rigs
            ]
            lines.append(f"| ... minus per-rig, {method} | " + " | ".join(diffs) + " |")
    return lines


def save(report: dict, out: Path) -> None:
    p = report["pretraining"]
    lines = [
        "# One 3D estimator for any rig",
        "",
        f"Pretrained on {p['rigs']['train']} random rigs of the families "
        f"{', '.join(p['families'])} ({p['people']['train']} people, {p['steps']} steps, "
        f"{p['train_seconds']} s; data {p['data_seconds']} s), training seed {report['seed']}, "
        f"scenes seed {report['scenes_seed']}. Per-rig estimators: {report['rig_steps']} steps on "
        f"the rig; fine-tuned: the pretrained one, {report['finetune_steps']} more steps on the "
        "rig's recordings at the step size chosen on its validation scenes (of "
        f"{', '.join(f'{lr:g}' for lr in FINETUNE_RATES)}). Cells: avg PCP % / MPJPE mm, test "
        "scenes (1-8 people).",
        "",
        *table(report, "test"),
        "",
        "Validation scenes:",
        "",
        *table(report, "validation"),
        "",
    ]
    atomic_write_text(out / "pretrain.md", "\n".join(lines))
    atomic_write_text(out / "pretrain.json", report_json(report))


def ship(models: Path, report: dict) -> Path:
    """Writes the pretrained estimator into the package (`ship_model`)."""
    return ship_model(models, "estimator", report, "pretrain")


def ship_model(models: Path, kind: str, report: dict, experiment: str) -> Path:
    """Writes a pretrained ``kind`` ("estimator" or "matcher") model folder's parameters (no
    optimiser state), config, chosen proposal settings (a matcher's) and report as the
    package's shipped model (`trained.pretrained_folder`), replacing the one there; returns its
    folder. ``experiment``: the module that made it (for the report's command)."""
    import shutil

    import jax
    from flax import nnx

    import mvpose_jax
    from mvpose_jax.models import estimator_model, matcher_model
    from mvpose_jax.trained import (
        ModelFolder,
        estimator_config_from_dict,
        matcher_config_from_dict,
    )

    source = ModelFolder(models)
    config = source.read_config("best")
    K = config["num_keypoints"]
    if kind == "estimator":
        model = estimator_model(0, K, estimator_config_from_dict(config).mlp, rngs=nnx.Rngs(0))
    else:
        model = matcher_model(0, K, matcher_config_from_dict(config).gat, rngs=nnx.Rngs(0))
    _, params, _ = nnx.split(model, nnx.Param, ...)
    params = source.restore_params(jax.eval_shape(lambda: params))
    target = Path(mvpose_jax.__file__).resolve().parent / "pretrained" / kind
    fresh = target.with_name(f".{kind}.new")
    shutil.rmtree(fresh, ignore_errors=True)
    p = report["pretraining"]
    with ModelFolder.create(fresh) as folder:
        folder.save_params(params, p["steps"], config, p["best_val_loss"])
        folder.copy_proposal_settings(source)
        folder.write_pretrain_report(
            {
                "command": f"python -m experiments.{experiment} --scale "
                f"{report['scale']} --seed {report['seed']} --ship",
                **{k: v for k, v in report.items() if k != "pretraining"},
                "pretraining": {k: v for k, v in p.items() if k != "history"},
            }
        )
    if target.exists():
        old = target.with_name(f".{kind}.old")
        shutil.rmtree(old, ignore_errors=True)
        target.rename(old)
        fresh.rename(target)
        shutil.rmtree(old)
    else:
        fresh.rename(target)
    return target


def combine(paths: list[Path], out: Path) -> list[str]:
    """``DIR/pretrain_seeds.md`` from the ``pretrain.json`` of several training seeds' runs."""
    return combine_seeds(
        paths, out, "pretrain", "# One 3D estimator for any rig, over training seeds", seeds_table
    )


def combine_seeds(paths: list[Path], out: Path, name: str, title: str, seeds_table, note=()):
    """``OUT/NAME_seeds.md`` from the ``NAME.json`` reports of several training seeds' runs
    (``seeds_table(reports, split)``'s lines for the test then the validation scenes, after
    ``title`` and the lines ``note``); returns its lines."""
    reports = [json.loads((p / f"{name}.json").read_text()) for p in paths]
    if len({r["scenes_seed"] for r in reports}) != 1:
        raise SystemExit("the runs were evaluated on different scenes (--scenes-seed)")
    lines = [
        title,
        "",
        *note,
        *seeds_table(reports, "test"),
        "",
        "Validation scenes:",
        "",
        *seeds_table(reports, "validation"),
        "",
    ]
    atomic_write_text(out / f"{name}_seeds.md", "\n".join(lines))
    return lines


def main(argv=None) -> None:
    experiment_main(
        argv,
        description=__doc__.split("\n\n")[0],
        scales=PRETRAIN_SCALES,
        run=run,
        table=table,
        combine=combine,
        ship=lambda out, report: ship(out / "models" / "pretrained", report),
        kind="estimator",
        markdown="pretrain.md",
    )


def experiment_main(argv, *, description, scales, run, table, combine, ship, kind, markdown):
    """The command line of a pretraining experiment (this one's, `experiments.pretrain_matcher`'s):
    run one training seed (and ``--ship`` its model), or ``--combine`` several seeds' runs."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--out", required=True, type=Path, help="folder for the tables and models")
    p.add_argument("--scale", default="quick", choices=sorted(scales))
    p.add_argument("--seed", type=int, default=0, help="training seed")
    p.add_argument("--scenes-seed", type=int, default=0, help="seed of the evaluation scenes")
    p.add_argument(
        "--rigs",
        nargs="+",
        choices=("panoptic5", "arplab6", *HELD_OUT_FAMILIES, "none"),
        help="compare on these evaluation rigs only (default: all; none: pretrain only)",
    )
    p.add_argument(
        "--detectors",
        nargs="+",
        choices=DETECTORS,
        default=["default"],
        help="simulated detectors of the pretraining recordings, taken in turn by the rigs: the "
        "simulator's default, or the detectors fitted without labels to ../shared/real/'s MVOR "
        "days and Pose2Sim demo trial (experiments.real_detectors)",
    )
    p.add_argument(
        "--ship",
        action="store_true",
        help=f"also write the pretrained {kind} into the package (mvpose_jax/pretrained/{kind}: "
        f"what `infer --{kind} pretrained` loads)",
    )
    p.add_argument(
        "--combine",
        nargs="+",
        type=Path,
        metavar="RUN",
        help="instead of running: the mean and spread over the given runs' folders (one "
        "training seed each), into OUT",
    )
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.combine:
        print("\n".join(combine(args.combine, args.out)))
        return
    t0 = time.perf_counter()
    report = run(
        scales[args.scale],
        args.seed,
        args.scenes_seed,
        args.out,
        not args.no_progress,
        tuple(r for r in args.rigs if r != "none") if args.rigs else None,
        tuple(args.detectors),
    )
    report["scale"] = args.scale
    print("\n".join(table(report)))
    if args.ship:
        print(f"shipped: {ship(args.out, report)}")
    print(f"{args.out / markdown} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
