"""One skeleton matcher for any rig: ``python -m experiments.pretrain_matcher --out DIR
[--scale quick] [--ship]``.

Pretrains the rig-agnostic matcher (`models.RigAgnosticGAT`, `pretraining.pretrain_matcher`)
without labels on single-person recordings of random rigs of the families in
`synthetic.rigs.PRETRAIN_FAMILIES` (the paper's composed frames, each of one rig), chooses its
proposal threshold once on frames composed on the dev rigs (what a user with no recording of
their own gets), then compares it on rigs it never saw (`experiments.pretrain.evaluation_rigs`:
the paper's two rigs and one rig of each held-out family) against:

* the paper's GAT trained on the rig for the same number of steps (the recipe of every other
  experiment, `experiments.fitting.fit_matcher`, its threshold chosen on the rig's dev
  recordings);
* itself with its threshold chosen on the rig's dev recordings instead (no training);
* itself fine-tuned on the rig for a tenth of the steps (step size chosen on the validation
  scenes);
* the epipolar matcher (its cutoff chosen on the rig's dev recordings).

Per split (1-8 people, the default detector): the per-frame adjusted Rand index of the
detections' grouping, the people per frame against the truth, and avg PCP / MPJPE of robust
triangulation on each matcher's proposals (the 3D stage is the same for all, so that the
difference is the matcher's).

Writes ``DIR/pretrain_matcher.md``, ``.json`` and the model folder ``DIR/models/matcher``
(what ``mvpose-jax infer --matcher DIR/models/matcher`` and the package's shipped weights are).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from experiments.config import SCALES, SPLITS, matcher_config, seed_stream
from experiments.fitting import choose_settings_on_dev, fit_matcher, free_compiled_programs
from experiments.pretrain import (
    combine_seeds,
    evaluation_data,
    experiment_main,
    finetune_config,
    random_rig_recordings,
    ship_model,
)
from experiments.real_detectors import training_detectors
from experiments.records import report_json
from experiments.tables import mean_sd, rounded_tree, seeds_line
from mvpose_jax.cameras import up_vector
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.inference import run_pipeline
from mvpose_jax.matcher_settings import choose_matcher_threshold
from mvpose_jax.matcher_training import train_matcher
from mvpose_jax.metrics import matching_scores, pose_metrics
from mvpose_jax.models import GATConfig
from mvpose_jax.pretraining import pretrain_matcher, rig_pool
from mvpose_jax.synthetic import DetectorConfig
from mvpose_jax.synthetic.rigs import HELD_OUT_FAMILIES, PRETRAIN_FAMILIES
from mvpose_jax.trained import (
    MatcherConfig,
    load_matcher,
    rig_agnostic_matcher,
    write_proposal_threshold,
)

# Seeds the matcher's pretraining rigs apart from the estimator's (`experiments.pretrain`).
MATCHER_RIGS = 7


@dataclasses.dataclass(frozen=True)
class MatcherPretrainScale:
    """How much pretraining, and the per-rig comparison's scale.

    Attributes:
      train_rigs, dev_rigs: random rigs of the pretraining families (in turn).
      recordings_per_rig, frames: single-person recordings per rig (at least the most people
        composed into a frame, 8), frames each.
      matcher: the rig-agnostic matcher and its training (steps, graphs per step, rate).
      threshold_frames: frames composed per dev rig to choose the shipped threshold on.
      rig_scale: the `experiments.config.SCALES` entry of the per-rig comparison (its
        recordings, scenes and matcher recipe); its matcher trains for the same steps.
      finetune_fraction: fine-tuning on a rig takes this fraction of the steps.
    """

    train_rigs: int
    dev_rigs: int
    recordings_per_rig: int
    frames: int
    matcher: MatcherConfig
    threshold_frames: int
    rig_scale: str
    finetune_fraction: float = 0.1


def pooled_matcher_config(
    steps: int, gat: GATConfig = GATConfig.pooled(), lr: float = 1e-3, dev: int = 300
) -> MatcherConfig:
    """Our matcher recipe (`experiments.config.matcher_config`: Adam with cosine decay,
    missing-keypoint augmentation) for the rig-agnostic network, ``steps`` steps."""
    config = matcher_config(gat, lr=lr, samples_per_epoch=300, eval_every=5, dev=dev)
    return dataclasses.replace(
        config, train=dataclasses.replace(config.train, max_steps=steps, max_epochs=10**6)
    )


MATCHER_PRETRAIN_SCALES = {
    "smoke": MatcherPretrainScale(
        train_rigs=5,
        dev_rigs=2,
        recordings_per_rig=3,
        frames=4,
        matcher=pooled_matcher_config(
            4, GATConfig(widths=(8, 1), heads=(2, 1), views="pooled", encoder_widths=(16,)), dev=4
        ),
        threshold_frames=8,
        rig_scale="smoke",
        finetune_fraction=0.5,
    ),
    "quick": MatcherPretrainScale(
        train_rigs=500,
        dev_rigs=20,
        recordings_per_rig=8,
        frames=6,
        matcher=pooled_matcher_config(3000),
        threshold_frames=128,
        rig_scale="quick",
    ),
}
# Fine-tuning's candidate step sizes, one chosen per rig on its validation scenes.
FINETUNE_RATES = (3e-4, 1e-4)


def rig_recordings(
    n: int,
    sc: MatcherPretrainScale,
    stream: str,
    seed: int,
    progress,
    detectors: tuple[DetectorConfig, ...] = (DetectorConfig(),),
):
    """`pretrain.random_rig_recordings` of seed stream ``stream`` (the matcher's own rigs):
    [(rig, recordings)]."""
    at = [*seed_stream(stream, seed), MATCHER_RIGS]
    return list(
        random_rig_recordings(
            n, at, sc.recordings_per_rig, sc.frames, detectors, progress, f"{stream} rigs"
        )
    )


def shipped_threshold(parts, config: MatcherConfig, dev, num_frames: int, seed: int):
    """The proposal threshold of the best per-frame ARI on frames composed on the dev rigs
    (`matcher_settings.choose_matcher_threshold` per rig; each rig's frames weigh alike):
    (threshold, {threshold: mean ARI}, [(cameras, {threshold: ARI}) per dev rig])."""
    graphdef, rest, params = parts
    totals: dict[float, float] = {}
    per_rig = []
    for rig, recs in dev:
        matcher = rig_agnostic_matcher(graphdef, rest, params, config, rig)
        _, ari, _ = choose_matcher_threshold(matcher, recs, num_samples=num_frames, seed=seed)
        per_rig.append((rig.num_cameras, ari))
        for th, a in ari.items():
            totals[th] = totals.get(th, 0.0) + a / len(dev)
    best = max(totals, key=lambda th: (round(totals[th], 6), th == 0.5))
    return best, totals, per_rig


# Camera-count groups of the dev rigs, for the question whether one threshold fits every rig.
CAMERA_GROUPS = ((2, 3), (4, 6), (7, 10))


def threshold_by_cameras(per_rig) -> dict:
    """{"2-3 cameras": {"rigs": n, "best": threshold, "ari": {threshold: mean ARI}}} of the dev
    rigs in each `CAMERA_GROUPS` group (`shipped_threshold`'s ``per_rig``)."""
    out = {}
    for lo, hi in CAMERA_GROUPS:
        curves = [ari for cams, ari in per_rig if lo <= cams <= hi]
        if not curves:
            continue
        mean = {th: float(np.mean([c[th] for c in curves])) for th in curves[0]}
        out[f"{lo}-{hi} cameras"] = {
            "rigs": len(curves),
            "best": max(mean, key=lambda th: round(mean[th], 6)),
            "ari": {str(th): round(v, 5) for th, v in mean.items()},
        }
    return out


def matcher_rows(data, split: str, matchers: dict, cutoff_px: float) -> dict:
    """ARI, people per frame and PCP / MPJPE (robust triangulation of the proposals) on a
    split's scenes for each ``name: (matcher, threshold)`` and the epipolar matcher."""
    rig = data.rig
    det, ident, gt, ids = data.detections(split, rig.names)
    scoring = {"up": up_vector(rig), "person_ids": ids}
    runs = {
        name: dict(matcher=m, proposals="gat", threshold=th) for name, (m, th) in matchers.items()
    }
    runs["epipolar"] = dict(half_score_px=cutoff_px)
    true_people = float(np.mean(gt.valid.sum(-1)))
    out = {}
    for name, kwargs in runs.items():
        res = run_pipeline(rig, det, method="robust", **kwargs)
        s = matching_scores(ident, res.identity, np.asarray(det.count))
        m = pose_metrics(res.poses, gt, confidence=res.confidence, **scoring)
        out[name] = {
            "ari": float(s["ari"]),
            "people_per_frame": float(np.mean(res.poses.valid.sum(-1))),
            "pcp": m["pcp"],
            "mpjpe_mm": m["mpjpe_mm"],
        }
    out["true_people_per_frame"] = true_people
    return out


def run(
    sc: MatcherPretrainScale,
    seed: int,
    scenes_seed: int,
    out: Path,
    progress: bool,
    rigs,
    detectors: tuple[str, ...] = ("default",),
):
    """Pretrains on seed ``seed`` with the simulated ``detectors`` (`experiments.pretrain.run`)
    and compares on the evaluation rigs; returns the report."""
    t0 = time.perf_counter()
    configs, detector_record = training_detectors(detectors)
    train = rig_recordings(sc.train_rigs, sc, "train", seed, progress, configs)
    dev = rig_recordings(sc.dev_rigs, sc, "dev", seed, progress, configs)
    train_pools = [rig_pool(rig, recs) for rig, recs in train]
    dev_pools = [rig_pool(rig, recs) for rig, recs in dev]
    data_seconds = time.perf_counter() - t0
    config = dataclasses.replace(sc.matcher, train=dataclasses.replace(sc.matcher.train, seed=seed))
    folder = out / "models" / "matcher"
    t0 = time.perf_counter()
    parts, fit = pretrain_matcher(
        train_pools, dev_pools, config, checkpoint_dir=folder, progress=progress
    )
    pretrain_seconds = time.perf_counter() - t0
    del train, train_pools
    free_compiled_programs()
    threshold, ari_dev, ari_dev_rigs = shipped_threshold(
        parts, config, dev, sc.threshold_frames, seed
    )
    write_proposal_threshold(folder, threshold, ari_dev, sc.threshold_frames * len(dev))
    steps = config.train.max_steps
    rig_sc = SCALES[sc.rig_scale]
    rig_sc = dataclasses.replace(rig_sc, matcher_steps=dict.fromkeys(range(1, 13), steps))
    finetune_steps = max(1, round(steps * sc.finetune_fraction))
    report = {
        "seed": seed,
        "scenes_seed": scenes_seed,
        "pretraining": {
            "families": list(PRETRAIN_FAMILIES),
            "rigs": {"train": sc.train_rigs, "dev": sc.dev_rigs},
            "detectors": detector_record,
            "frames": {
                "train": sc.train_rigs * sc.recordings_per_rig * sc.frames,
                "dev": sc.dev_rigs * sc.recordings_per_rig * sc.frames,
            },
            "steps": fit.steps,
            "data_seconds": round(data_seconds, 1),
            "train_seconds": round(pretrain_seconds, 1),
            "best_val_loss": fit.best_val_loss,
            "threshold": threshold,
            "dev_ari_by_threshold": {str(k): round(v, 5) for k, v in ari_dev.items()},
            "dev_ari_by_cameras": threshold_by_cameras(ari_dev_rigs),
            "history": fit.history,
        },
        "finetune_steps": finetune_steps,
        "rig_steps": steps,
        "rigs": {},
    }
    save(report, out)  # the pretraining's record, also when no rig is compared
    for name, rig, data in evaluation_data(rigs, rig_sc, scenes_seed, seed, progress):
        per_rig, per_rig_fit = fit_matcher(data, rig_sc, rig.names, seed, progress)
        pretrained = load_matcher(folder, rig)
        own = choose_settings_on_dev(pretrained, data, rig_sc.threshold_frames, seed)
        tuned = {}
        for lr in FINETUNE_RATES:
            tune = finetune_config(config, finetune_steps, lr)
            m, _ = train_matcher(
                rig, data.train, data.dev, tune, progress=progress, start=pretrained
            )
            free_compiled_programs()
            tuned[lr] = (m, choose_settings_on_dev(m, data, rig_sc.threshold_frames, seed))
        matchers = {
            "per-rig GAT": (per_rig, per_rig_fit["threshold"]),
            "pretrained": (pretrained, threshold),
            "pretrained, rig's threshold": (pretrained, own["threshold"]),
            **{f"fine-tuned {lr:g}": (m, f["threshold"]) for lr, (m, f) in tuned.items()},
        }
        rows = {
            split: matcher_rows(data, split, matchers, per_rig_fit["geometric_cutoff_px"])
            for split in SPLITS
        }
        val = rows["validation"]
        chosen = max(
            FINETUNE_RATES,
            key=lambda lr: (val[f"fine-tuned {lr:g}"]["ari"], val[f"fine-tuned {lr:g}"]["pcp"]),
        )
        for r in rows.values():
            r["fine-tuned"] = r[f"fine-tuned {chosen:g}"]
        report["rigs"][name] = {
            "cameras": rig.num_cameras,
            "held_out_family": name in HELD_OUT_FAMILIES,
            "thresholds": {
                "per-rig GAT": per_rig_fit["threshold"],
                "pretrained": threshold,
                "pretrained, rig's threshold": own["threshold"],
                "fine-tuned": tuned[chosen][1]["threshold"],
            },
            "epipolar_cutoff_px": per_rig_fit["geometric_cutoff_px"],
            "finetune_learning_rate": chosen,
            "per_rig_train_seconds": per_rig_fit["train_seconds"],
            **{split: rounded_tree(r) for split, r in rows.items()},
        }
        save(report, out)
        free_compiled_programs()
    return report


ROWS = ("per-rig GAT", "pretrained", "pretrained, rig's threshold", "fine-tuned", "epipolar")


def table(report: dict, split: str = "test") -> list[str]:
    """ARI, people per frame and PCP / MPJPE per evaluation rig and matcher."""
    rigs = report["rigs"]
    if not rigs:
        return ["(no evaluation rig: pretraining only, `--rigs none`)"]
    head = "| matcher | " + " | ".join(
        f"{r} ({v['cameras']} cams{', held out' if v['held_out_family'] else ''})"
        for r, v in rigs.items()
    )
    lines = [head + " |", "|---" * (len(rigs) + 1) + "|"]
    for row in ROWS:
        cells = []
        for v in rigs.values():
            c = v[split][row]
            cells.append(
                f"{c['ari']:.4f} · {c['people_per_frame']:.2f} · {c['pcp']:.1f} / "
                f"{c['mpjpe_mm']:.1f}"
            )
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    truth = " | ".join(f"{v[split]['true_people_per_frame']:.2f}" for v in rigs.values())
    lines.append(f"| (true people per frame) | {truth} |")
    return lines


def seeds_table(reports: list[dict], split: str = "test") -> list[str]:
    """ARI and PCP per evaluation rig and matcher over training seeds (mean ± sd)."""
    rigs = list(reports[0]["rigs"])
    lines = [seeds_line(reports), "", "| matcher | " + " | ".join(rigs) + " |"]
    lines.append("|---" * (len(rigs) + 1) + "|")
    for row in ROWS:
        cells = [
            f"{mean_sd(reports, ('rigs', r, split, row, 'ari'), 4)} · "
            f"{mean_sd(reports, ('rigs', r, split, row, 'pcp'), 1)}"
            for r in rigs
        ]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return lines


def cameras_table(pretraining: dict) -> list[str]:
    """The dev rigs' ARI by threshold, per camera-count group (`threshold_by_cameras`)."""
    groups = pretraining.get("dev_ari_by_cameras")
    if not groups:
        return []
    ths = list(pretraining["dev_ari_by_threshold"])
    lines = [
        "Dev rigs' per-frame ARI by threshold, per camera count (does one threshold fit every "
        "rig?):",
        "",
        "| dev rigs | best | " + " | ".join(ths) + " |",
        "|---" * (len(ths) + 2) + "|",
    ]
    for name, g in groups.items():
        cells = " | ".join(f"{g['ari'][th]:.4f}" for th in ths)
        lines.append(f"| {name} ({g['rigs']}) | {g['best']:g} | {cells} |")
    all_cells = " | ".join(f"{pretraining['dev_ari_by_threshold'][th]:.4f}" for th in ths)
    lines += [
        f"| all ({pretraining['rigs']['dev']}) | {pretraining['threshold']:g} | {all_cells} |",
        "",
    ]
    return lines


def save(report: dict, out: Path) -> None:
    p = report["pretraining"]
    lines = [
        "# One skeleton matcher for any rig",
        "",
        f"Pretrained on {p['rigs']['train']} random rigs of the families "
        f"{', '.join(p['families'])} ({p['frames']['train']} single-person frames, {p['steps']} "
        f"steps, {p['train_seconds']} s; data {p['data_seconds']} s), training seed "
        f"{report['seed']}, scenes seed {report['scenes_seed']}; shipped threshold "
        f"{p['threshold']} (chosen on frames composed on {p['rigs']['dev']} dev rigs). Per-rig "
        f"GAT: the paper's network, {report['rig_steps']} steps on the rig; fine-tuned: "
        f"{report['finetune_steps']} more steps on the rig's recordings. Cells: ARI · people "
        "per frame · avg PCP % / MPJPE mm (robust triangulation of the proposals), test scenes "
        "(1-8 people).",
        "",
        *table(report, "test"),
        "",
        "Validation scenes:",
        "",
        *table(report, "validation"),
        "",
        *cameras_table(p),
    ]
    atomic_write_text(out / "pretrain_matcher.md", "\n".join(lines))
    atomic_write_text(out / "pretrain_matcher.json", report_json(report))


def combine(paths: list[Path], out: Path) -> list[str]:
    """``DIR/pretrain_matcher_seeds.md`` from several training seeds' runs."""
    return combine_seeds(
        paths,
        out,
        "pretrain_matcher",
        "# One skeleton matcher for any rig, over training seeds",
        seeds_table,
        note=("Cells: ARI · avg PCP %.", ""),
    )


def main(argv=None) -> None:
    experiment_main(
        argv,
        description=__doc__.split("\n\n")[0],
        scales=MATCHER_PRETRAIN_SCALES,
        run=run,
        table=table,
        combine=combine,
        ship=lambda out, report: ship_model(
            out / "models" / "matcher", "matcher", report, "pretrain_matcher"
        ),
        kind="matcher",
        markdown="pretrain_matcher.md",
    )


if __name__ == "__main__":
    main()
