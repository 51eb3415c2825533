"""The 3D estimator on its own (true proposals), as the paper's Tables 6 and 7 measure it.

    python -m experiments.estimator [--only panoptic|arp] [--steps N] [--paper-size] [--out DIR]

* ``panoptic``: the ``panoptic5`` rig, 5 training = inference views. Trained on synthetic
  single-person recordings (detector model on, no 3D anywhere in training), evaluated on held-out
  multi-person recordings (1-8 people) grouped by their true identities, for the D-detected,
  D-projected and D-average variants, against triangulation (the paper's pairwise centroid and our
  weighted DLT) on the same groups.
* ``arp``: the ``arplab6`` rig, models M_1/6, M_2/6, M_6/6 and M_2/2 (M_i/t: t training cameras,
  i inference cameras, the robot's for i < 6); reprojection error of each model's poses into every
  camera, mean and median (Table 7; no ground truth needed).

Writes ``metrics.json`` and ``tables.md`` to ``results/estimator/`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.synthetic import detection_variants, generate_recording, generate_single_person_recordings
from mvpose_jax.features import main_skeletons, people_from_identity
from mvpose_jax.inference import estimate_grouped, predict_people, triangulate_grouped
from mvpose_jax.metrics import pose_metrics, reprojection_errors
from mvpose_jax.models import MLPConfig
from mvpose_jax.train import EstimatorConfig, TrainConfig, train_estimator

PAPER_TABLE6 = {  # CMU Panoptic, D-detected (the paper's Table 6)
    "ours": {"mpjpe_mm": 26.06, "map": 89.25, "mean_recall": 92.63},
    "triangulation": {"mpjpe_mm": 22.63, "map": 76.99, "mean_recall": 85.10},
}


@dataclasses.dataclass(frozen=True)
class Setup:
    """Data and training budget of the experiment."""

    train_recordings: int = 60
    train_frames: int = 300
    test_scenes: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8)  # people per test recording
    test_frames: int = 60
    steps: int = 4000
    batch_size: int = 256
    learning_rate: float = 1e-3
    final_lr_fraction: float = 0.01
    mlp: MLPConfig = dataclasses.replace(MLPConfig.quick(), output="residual")
    loss_power: float = 1.0
    seed: int = 0


def single_person_samples(rig, setup: Setup, seed: int):
    """Main skeletons of single-person recordings: (N, C, K, 2), (N, C, K); no 3D is kept."""
    recs = generate_single_person_recordings(
        rig, num_recordings=setup.train_recordings, num_frames=setup.train_frames, seed=seed, progress=True
    )
    ms = [main_skeletons(np.asarray(r.detections.xy), np.asarray(r.detections.score)) for r in recs]
    return np.concatenate([m[0] for m in ms]), np.concatenate([m[1] for m in ms])


def test_people(rig, setup: Setup, seed: int, variant: str = "detected"):
    """Held-out multi-person recordings grouped by true identity (true proposals)."""
    out = []
    for i, n in enumerate(setup.test_scenes):
        rec = generate_recording(rig, num_people=n, num_frames=setup.test_frames, seed=seed + 1000 * i)
        v = detection_variants(rec)[variant]
        G = rec.ground_truth.valid.shape[1]
        xy, sc = people_from_identity(np.asarray(v.detections.xy), np.asarray(v.detections.score),
                                      np.asarray(rec.identity), G)  # fmt: skip
        out.append((xy, sc, rec.ground_truth))
    return out


def _train(rig, setup: Setup, xy, score, train_cams, infer_cams):
    n_dev = max(1, len(xy) // 10)
    cfg = EstimatorConfig(
        train_cameras=tuple(train_cams), infer_cameras=tuple(infer_cams), mlp=setup.mlp,
        loss_power=setup.loss_power,
        train=TrainConfig(learning_rate=setup.learning_rate, batch_size=setup.batch_size,
                          max_steps=setup.steps, patience=1000, seed=setup.seed,
                          final_lr_fraction=setup.final_lr_fraction),
    )  # fmt: skip
    cam_idx = [rig.names.index(c) for c in train_cams]
    return train_estimator(rig, xy[n_dev:][:, cam_idx], score[n_dev:][:, cam_idx],
                           xy[:n_dev][:, cam_idx], score[:n_dev][:, cam_idx], cfg)  # fmt: skip


def _concat_poses(parts):
    """Stacks per-scene Poses3D of different G by padding the person axis."""
    G = max(p.valid.shape[1] for p in parts)
    pad = lambda a: np.pad(a, [(0, 0), (0, G - a.shape[1])] + [(0, 0)] * (a.ndim - 2))  # noqa: E731
    return type(parts[0])(*(np.concatenate([pad(np.asarray(x)) for x in field]) for field in zip(*parts)))


def _pad_conf(parts):
    G = max(c.shape[1] for c in parts)
    return np.concatenate([np.pad(c, [(0, 0), (0, G - c.shape[1])]) for c in parts])


def panoptic(setup: Setup) -> dict:
    rig = load_rig("panoptic5")
    xy, score = single_person_samples(rig, setup, seed=setup.seed)
    t0 = time.perf_counter()
    est, fit = _train(rig, setup, xy, score, rig.names, rig.names)
    train_s = time.perf_counter() - t0
    results = {"train_seconds": train_s, "train_samples": int(len(xy)), "steps": fit.steps,
               "history": fit.history, "variants": {}}  # fmt: skip
    for variant in ("detected", "projected", "average"):
        groups = test_people(rig, setup, seed=setup.seed + 1, variant=variant)
        rows = {}
        for name in ("ours", "centroid", "dlt"):
            poses, confs, gts = [], [], []
            for xy_g, sc_g, gt in groups:
                if name == "ours":
                    p, c = estimate_grouped(est, xy_g, sc_g)
                else:
                    p, c = triangulate_grouped(rig, xy_g, sc_g, name)
                poses.append(p)
                confs.append(c)
                gts.append(gt)
            pred, gt, conf = _concat_poses(poses), _concat_poses(gts), _pad_conf(confs)
            rows[name] = pose_metrics(pred, gt, confidence=conf)
            if name == "ours":
                ours = pred
            else:
                # Ours on exactly the keypoints this triangulation reconstructed.
                restricted = type(ours)(ours.xyz, ours.valid & pred.valid, pred.keypoint_valid & ours.valid[..., None])
                rows[f"ours_on_{name}_keypoints"] = pose_metrics(restricted, gt, confidence=conf)
        results["variants"][variant] = rows
    return results


def arp(setup: Setup) -> dict:
    rig = load_rig("arplab6")
    robot = ("orinbot_l", "orinbot_r")
    models = {
        "M_1/6": (rig.names, robot[:1]),
        "M_2/6": (rig.names, robot),
        "M_6/6": (rig.names, rig.names),
        "M_2/2": (robot, robot),
    }
    xy, score = single_person_samples(rig, setup, seed=setup.seed + 7)
    groups = test_people(rig, setup, seed=setup.seed + 8)
    results = {}
    for name, (train_cams, infer_cams) in models.items():
        t0 = time.perf_counter()
        est, fit = _train(rig, setup, xy, score, train_cams, infer_cams)
        infer_idx = [rig.names.index(c) for c in infer_cams]
        xyz, kv, det_xy, det_sc = [], [], [], []
        for xy_g, sc_g, _ in groups:
            F, G = sc_g.shape[:2]
            flat_xy, flat_sc = xy_g.reshape((F * G,) + xy_g.shape[2:]), sc_g.reshape((F * G,) + sc_g.shape[2:])
            # People the inference cameras see at all (a robot sees few of them).
            seen = (flat_sc[:, infer_idx] > 0).any(-1).sum(-1) >= 1
            out = predict_people(est, flat_xy[seen][:, infer_idx], flat_sc[seen][:, infer_idx])
            xyz.append(out)
            kv.append(np.ones(out.shape[:2], bool))
            det_xy.append(flat_xy[seen])
            det_sc.append(flat_sc[seen])
        errors = reprojection_errors(rig, np.concatenate(xyz), np.concatenate(kv),
                                     np.concatenate(det_xy), np.concatenate(det_sc))  # fmt: skip
        results[name] = {"train_seconds": time.perf_counter() - t0, "people": int(sum(len(x) for x in xyz)),
                         "reprojection": errors}  # fmt: skip
    return results


def tables(res: dict) -> str:
    lines = []
    if "panoptic" in res:
        p = res["panoptic"]
        lines += [
            "## panoptic5, 5 views, true proposals (Table 6)",
            "",
            f"Estimator trained {p['steps']} steps on {p['train_samples']} single-person frames in "
            f"{p['train_seconds']:.0f} s (CPU).",
            "",
            "AP and recall count a pose missing a keypoint as wrong (metrics.pose_metrics); MPJPE is",
            "over the keypoints a method produced. centroid = the paper's pairwise-centroid",
            "triangulation, dlt = score-weighted DLT, on the same true person groupings.",
            "",
            "| variant | method | MPJPE (mm) | mAP | mR | PCP | completeness (%) |",
            "|---|---|---|---|---|---|---|",
        ]
        for variant, rows in p["variants"].items():
            for name, m in rows.items():
                if name.startswith("ours_on_"):  # only its MPJPE compares like with like
                    method = name.removeprefix("ours_on_").removesuffix("_keypoints")
                    lines.append(f"| D-{variant} | ours, on the keypoints {method} reconstructs | "
                                 f"{m['mpjpe_mm']:.2f} | | | | |")  # fmt: skip
                    continue
                lines.append(f"| D-{variant} | {name} | {m['mpjpe_mm']:.2f} | {m['map']:.2f} | "
                             f"{m['mean_recall']:.2f} | {m['pcp']:.2f} | {m['completeness']:.2f} |")  # fmt: skip
        lines += ["", "Paper (CMU Panoptic, D-detected): ours 26.06 mm / mAP 89.25 / mR 92.63; "
                  "triangulation 22.63 / 76.99 / 85.10 (reference numbers, not ours).", ""]  # fmt: skip
    if "arp" in res:
        a = res["arp"]
        cams = list(next(iter(a.values()))["reprojection"])
        lines += ["## arplab6, camera subsets (Table 7): reprojection error, px, mean / median", "",
                  "| model | " + " | ".join(cams) + " |", "|---|" + "---|" * len(cams)]  # fmt: skip
        for name, m in a.items():
            cells = [f"{m['reprojection'][c]['mean']:.1f} / {m['reprojection'][c]['median']:.1f}" for c in cams]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.estimator", description=__doc__.splitlines()[0])
    ap.add_argument("--tables-from", type=Path, help="only rewrite tables.md from this metrics.json")
    ap.add_argument("--only", choices=("panoptic", "arp"), default=None)
    ap.add_argument("--steps", type=int, default=Setup.steps, help="training steps per model")
    ap.add_argument("--paper-size", action="store_true", help="the paper's MLP widths")
    ap.add_argument("--output", choices=("absolute", "anchored", "residual"), default="residual",
                    help="MLP output mode (absolute = the paper's)")  # fmt: skip
    ap.add_argument("--loss-power", type=float, default=1.0, help="per-sample loss e^power; 2 = the paper's e^2")
    ap.add_argument("--out", type=Path, default=Path("results/estimator"))
    args = ap.parse_args(argv)
    if args.tables_from:
        text = tables(json.loads(args.tables_from.read_text()))
        atomic_write_text(args.tables_from.with_name("tables.md"), text)
        print(text)
        return 0
    mlp = MLPConfig(output=args.output) if args.paper_size else dataclasses.replace(MLPConfig.quick(), output=args.output)
    setup = Setup(steps=args.steps, mlp=mlp, loss_power=args.loss_power)
    res = {"setup": json.loads(json.dumps(dataclasses.asdict(setup)))}
    args.out.mkdir(parents=True, exist_ok=True)
    for part, run in (("panoptic", panoptic), ("arp", arp)):
        if args.only in (None, part):
            res[part] = run(setup)
            # Written after each part, so a long run leaves what it has finished.
            atomic_write_text(args.out / "metrics.json", json.dumps(res, indent=1) + "\n")
            atomic_write_text(args.out / "tables.md", tables(res))
    print(tables(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
