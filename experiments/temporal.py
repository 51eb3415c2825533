"""The learned temporal stage against the Butterworth filter (issue 37, item 2):
``python -m experiments.temporal --out DIR [--scale quick|smoke]``.

**Synthetic** (panoptic5, the "occluders" shift: furniture hides keypoints from some cameras,
5 % of the image border lost; training recordings made with the same simulator, as a user gets
them from `generate --detector-like`): a temporal model per variant (`VARIANTS`) is trained on
single-person recordings, the variant and whether the filter runs after it are chosen on the
validation scenes, and the test scenes give the table. The 3D stage runs on the true groupings
and true tracks (every row sees the same people): robust triangulation, the blend (the shipped
rig-agnostic estimator), the blend + Butterworth (`infer`'s default filter: outliers, gaps up to
0.5 s, 2 Hz), and the temporal stage alone, in the blend, and in the blend + Butterworth. MPJPE is
split by how many views detected the keypoint (0, 1, 2+).

**Real** (Pose2Sim demo's two-person trial, no labels): each camera in turn is held out. The
people and tracks are the geometric pipeline's (all cameras); the 3D of each row is computed from
the other cameras only (the temporal model fine-tuned on those cameras' windows of the recording
itself, after synthetic training on the rig with the detector fitted to the recording) and
projected into the held-out camera, where its skeletons are the reference: the share of its
visible keypoints within 20 and 50 px, split by how many of the OTHER cameras saw the keypoint.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from experiments import pose2sim_demo as demo
from experiments.config import seed_stream
from experiments.records import report_json
from mvpose_jax.cameras import Rig, project_points, up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.pose2sim import find_trials
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.detector_fit import fit_detector
from mvpose_jax.floor import estimate_floor_from_detections
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import (
    group_people,
    members_from_identity,
    predict_people,
    triangulate_people,
)
from mvpose_jax.metrics import pose_metrics
from mvpose_jax.skeletons import Poses3D, get_layout
from mvpose_jax.smoothing import smooth_poses
from mvpose_jax.synthetic import (
    SHIFTS,
    SyntheticConfig,
    generate_recording,
    generate_single_person_recordings,
)
from mvpose_jax.temporal import TemporalConfig, for_rig, refine_tracks, save_temporal
from mvpose_jax.temporal_training import (
    TemporalTrainConfig,
    fit_temporal,
    windows_of_recordings,
    windows_of_tracks,
)
from mvpose_jax.tracking import TrackingConfig
from mvpose_jax.trained import PRETRAINED, load_estimator

RIG = "panoptic5"
SHIFT = "occluders"
LAYOUT = "coco18"
SEED = 0
# (bone_weight, symmetry_weight): the reprojection alone, and with the body's constancy.
VARIANTS = {"reprojection": (0.0, 0.0), "bones 0.1": (0.1, 0.1), "bones 1": (1.0, 1.0)}
# The real part alone (--parts real) uses the library default (TemporalTrainConfig's weights).
DEFAULT_VARIANT = "bones 0.1"


@dataclasses.dataclass(frozen=True)
class TemporalScale:
    train_recordings: int
    train_frames: int
    dev_recordings: int
    people: tuple[int, ...]
    scene_frames: int
    steps: int
    finetune_steps: int
    demo_frames: int | None
    eval_every: int
    extra_seeds: tuple[int, ...]


SCALES = {
    "quick": TemporalScale(60, 160, 10, (2, 4), 300, 1500, 300, None, 100, (1, 2)),
    "smoke": TemporalScale(3, 40, 1, (2,), 40, 3, 2, 40, 1, (1,)),
}


def _people_views(score: np.ndarray) -> np.ndarray:
    """(F, G, K) how many views detected each keypoint of each grouped person."""
    return (score > 0).sum(axis=2)


def _by_views(err: np.ndarray, views: np.ndarray, where: np.ndarray) -> dict:
    out = {}
    for name, sel in (("0", views == 0), ("1", views == 1), ("2+", views >= 2)):
        m = where & sel
        out[name] = {
            "mpjpe_mm": float(err[m].mean() * 1000) if m.any() else None,
            "n": int(m.sum()),
        }
    return out


def _results(xyz, kv, valid, members, identity, cameras, timestamps, track) -> PoseResults:
    poses = Poses3D(xyz.astype(np.float32), valid, kv & valid[..., None])
    conf = valid.astype(np.float32)
    return PoseResults(poses, conf, members, identity, cameras, LAYOUT, timestamps, track)


def _butterworth(results: PoseResults, fps: float) -> np.ndarray:
    return np.asarray(smooth_poses(results, fps=fps, filter="butterworth").poses.xyz, np.float64)


def _scene_rows(rig, rec, estimator, models: dict, fps: float) -> dict:
    """Every row's 3D for one scene (true groupings and tracks): {row: (xyz, keypoint_valid)},
    with the people and their views."""
    G = rec.ground_truth.valid.shape[1]
    members = members_from_identity(np.asarray(rec.identity), G)
    xy, score = group_people(rec.detections.xy, rec.detections.score, members)
    valid = (score > 0).any(-1).sum(-1) >= 2  # proposals need two views
    F = len(valid)
    track = np.where(valid, np.arange(G)[None], -1)
    flat = valid.reshape(-1)
    xyf, scf = xy.reshape(F * G, *xy.shape[2:]), score.reshape(F * G, *score.shape[2:])
    K = score.shape[-1]
    rows = {}
    tri = np.zeros((F * G, K, 3))
    tri_ok = np.zeros((F * G, K), bool)
    t, ok = triangulate_people(rig, xyf[flat], scf[flat], method="robust")
    tri[flat], tri_ok[flat] = t, ok
    rows["robust triangulation"] = (tri.reshape(F, G, K, 3), tri_ok.reshape(F, G, K))
    blend = np.zeros((F * G, K, 3))
    blend[flat] = predict_people(estimator, xyf[flat], scf[flat], method="blend", layout=LAYOUT)
    every = np.broadcast_to(valid[..., None], (F, G, K))
    rows["blend"] = (blend.reshape(F, G, K, 3), every)
    timestamps = np.arange(F) / fps
    res = lambda x: _results(  # noqa: E731
        x, every, valid, members, rec.identity, tuple(rig.names), timestamps, track
    )
    rows["blend + Butterworth"] = (_butterworth(res(rows["blend"][0]), fps), every)
    for name, model in models.items():
        alone, _ = refine_tracks(model, rig, xy, score, track, valid, method="alone")
        tblend, _ = refine_tracks(model, rig, xy, score, track, valid, method="blend")
        rows[f"temporal ({name}), alone"] = (alone, every)
        rows[f"temporal ({name}), blend"] = (tblend, every)
        rows[f"temporal ({name}), blend + Butterworth"] = (_butterworth(res(tblend), fps), every)
    return {"rows": rows, "valid": valid, "views": _people_views(score)}


def _score_split(rig, scenes, estimator, models, fps) -> dict:
    """Per row: PCP and MPJPE over the split's scenes, and MPJPE by views."""
    per_row: dict = {}
    for rec in scenes:
        out = _scene_rows(rig, rec, estimator, models, fps)
        gt = rec.ground_truth
        gt_xyz = np.asarray(gt.xyz, np.float64)
        # Ground truth: the people the rows have (two or more views), so every row is scored on
        # the same people; the 3D stage, not the grouping, is compared.
        gt_valid = np.asarray(gt.valid, bool) & out["valid"]
        gt_poses = Poses3D(gt_xyz, gt_valid, np.asarray(gt.keypoint_valid, bool))
        for row, (xyz, kv) in out["rows"].items():
            pred = Poses3D(xyz, out["valid"], kv & out["valid"][..., None])
            m = pose_metrics(pred, gt_poses, layout=LAYOUT, up=up_vector(rig))
            err = np.linalg.norm(xyz - gt_xyz, axis=-1)
            where = kv & gt_valid[..., None] & np.asarray(gt.keypoint_valid, bool)
            r = per_row.setdefault(row, {"pcp": [], "err": [], "views": [], "where": []})
            r["pcp"].append((m["pcp"], int(gt_valid.sum())))
            r["err"].append(err[where])
            r["views"].append(out["views"][where])
    table = {}
    for row, r in per_row.items():
        w = np.array([n for _, n in r["pcp"]], float)
        err, views = np.concatenate(r["err"]), np.concatenate(r["views"])
        table[row] = {
            "pcp": float(np.sum([p * n for p, n in r["pcp"]]) / max(w.sum(), 1)),
            "mpjpe_mm": float(err.mean() * 1000),
            "by_views": _by_views(err, views, np.ones_like(err, bool)),
        }
    return table


def _training_windows(rig, config: SyntheticConfig, sc: TemporalScale, progress: bool):
    """(training, dev) windows of single-person recordings of ``rig`` made with ``config``."""
    recs = generate_single_person_recordings(
        rig,
        num_recordings=sc.train_recordings + sc.dev_recordings,
        num_frames=sc.train_frames,
        config=config,
        seed=seed_stream("train", SEED),
        progress=progress,
    )
    window = TemporalConfig().window
    return (
        windows_of_recordings(recs[: sc.train_recordings], window),
        windows_of_recordings(recs[sc.train_recordings :], window),
    )


def synthetic_part(sc: TemporalScale, out: Path, progress: bool) -> dict:
    rig = load_rig(RIG)
    shift = SHIFTS[SHIFT]
    _, config = shift.apply(rig, SyntheticConfig(), seed=0)
    fps = config.motion.fps
    t0 = time.time()
    train_w, dev_w = _training_windows(rig, config, sc, progress)
    scenes = {
        split: [
            generate_recording(
                rig,
                num_people=n,
                num_frames=sc.scene_frames,
                config=config,
                seed=seed_stream(split, SEED, n),
            )
            for n in sc.people
        ]
        for split in ("validation", "test")
    }
    data_s = time.time() - t0
    estimator = load_estimator(PRETRAINED, rig)

    def train(bone: float, sym: float, seed: int, name: str):
        t1 = time.time()
        tc = TemporalTrainConfig(
            steps=sc.steps,
            bone_weight=bone,
            symmetry_weight=sym,
            eval_every=sc.eval_every,
            seed=seed,
        )
        model, record = fit_temporal(rig, train_w, dev_w, config=tc, progress=progress)
        record["seconds"] = time.time() - t1
        save_temporal(out / "models" / f"{name}-seed{seed}", model, record)
        return model, record

    models, records = {}, {}
    for name, (bone, sym) in VARIANTS.items():
        models[name], records[name] = train(bone, sym, SEED, name)
    tables = {
        split: _score_split(rig, scenes[split], estimator, models, fps)
        for split in ("validation", "test")
    }
    # Chosen on validation: the variant and row with the lowest MPJPE among the temporal rows.
    temporal_rows = [r for r in tables["validation"] if r.startswith("temporal")]
    chosen = min(temporal_rows, key=lambda r: tables["validation"][r]["mpjpe_mm"])
    variant = next(v for v in VARIANTS if chosen.startswith(f"temporal ({v})"))
    # The chosen variant over more training seeds: the test table's spread.
    seeds = {SEED: tables["test"]}
    for seed in sc.extra_seeds:
        model, _ = train(*VARIANTS[variant], seed, variant)
        seeds[seed] = _score_split(rig, scenes["test"], estimator, {variant: model}, fps)
    spread = {}
    for row in tables["test"]:
        if row.startswith("temporal") and not row.startswith(f"temporal ({variant})"):
            continue
        values = [t[row] for t in seeds.values()]
        spread[row] = {key: _mean_sd([v[key] for v in values]) for key in ("pcp", "mpjpe_mm")} | {
            f"mpjpe_mm_{k}_views": _mean_sd([v["by_views"][k]["mpjpe_mm"] for v in values])
            for k in ("0", "1", "2+")
        }
    return {
        "rig": RIG,
        "shift": SHIFT,
        "split_tables": {"validation": "choice", "test": "report"},
        "tables": tables,
        "chosen_on_validation": chosen,
        "chosen_variant": variant,
        "chosen_weights": VARIANTS[variant],
        "test_over_seeds": {"seeds": sorted(seeds), "rows": spread},
        "training": {
            k: {kk: v[kk] for kk in ("dev_loss", "best_step", "initial_dev_loss", "seconds")}
            | {"train_windows": v["train_windows"], "dev_windows": v["dev_windows"]}
            for k, v in records.items()
        },
        "data_seconds": data_s,
        "fps": fps,
    }


def _mean_sd(values) -> dict | None:
    v = [x for x in values if x is not None]
    if not v:
        return None
    return {"mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0}


def _bone_sd_cm(xyz: np.ndarray, valid: np.ndarray, track: np.ndarray) -> float:
    """The mean over tracks and bones of each bone's length's standard deviation over the
    track's frames, cm (a rigid body's is 0)."""
    bones = np.asarray(get_layout(LAYOUT).bones)
    length = np.linalg.norm(xyz[..., bones[:, 0], :] - xyz[..., bones[:, 1], :], axis=-1)
    sds = [
        length[(track == t) & valid].std(axis=0).mean()
        for t in np.unique(track[valid])
        if ((track == t) & valid).sum() >= 2
    ]
    return float(np.mean(sds) * 100) if sds else float("nan")


def _held_out_errors(rig_c: Rig, xyz: np.ndarray, have: np.ndarray, xy_c, score_c) -> np.ndarray:
    """Pixel distance in the held-out camera (NaN where not comparable)."""
    px = np.asarray(project_points(rig_c, xyz))[0]  # (F, G, K, 2)
    d = np.linalg.norm(px - xy_c, axis=-1)
    return np.where(have & (score_c > 0), d, np.nan)


def real_part(
    sc: TemporalScale, out: Path, progress: bool, data_root: Path, weights: tuple[float, float]
) -> dict:
    trial = {t.name: t for t in find_trials(data_root, pose_folders=("pose",)).trials}[
        demo.MULTI_TRIAL
    ]
    rig, det = demo.raw_detections(trial, sc.demo_frames)
    fps = float(trial.fps) if getattr(trial, "fps", None) else 30.0
    floor = estimate_floor_from_detections(rig, det, layout=LAYOUT)
    fitted = fit_detector(rig, det, layout=LAYOUT)
    config = dataclasses.replace(SyntheticConfig(), detector=fitted.config).with_scene(
        floor_height=floor.height, up=floor.measured_up
    )
    window = TemporalConfig().window
    train, dev = _training_windows(rig, config, sc, progress)
    tc = TemporalTrainConfig(
        steps=sc.steps, eval_every=sc.eval_every, bone_weight=weights[0], symmetry_weight=weights[1]
    )
    base, base_record = fit_temporal(rig, train, dev, config=tc, progress=progress)
    # The people and tracks: the geometric pipeline on every camera.
    res = run_pipeline(rig, det, method="robust", tracking=TrackingConfig(), fps=fps)
    xy, score = group_people(det.xy, det.score, res.members)
    valid = np.asarray(res.poses.valid, bool)
    F, G, C, K = score.shape
    estimator_all = load_estimator(PRETRAINED, rig)
    table: dict = {}
    bones_sd: dict = {}
    finetune = {}
    for c, cam in enumerate(rig.names):
        keep = [i for i in range(C) if i != c]
        sub = rig.select([rig.names[i] for i in keep])
        xs, ss = xy[:, :, keep], score[:, :, keep]
        people = valid & ((ss > 0).any(-1).sum(-1) >= 2)
        track = np.where(people, res.track, -1)
        # Fine-tuned on this recording without camera c: its windows split in time, the last
        # fifth of the frames as the fine-tuning's dev windows.
        cut = int(F * 0.8)
        ft_train = windows_of_tracks(xs[:cut], ss[:cut], track[:cut], people[:cut], window)
        ft_dev = windows_of_tracks(xs[cut:], ss[cut:], track[cut:], people[cut:], window)
        model = for_rig(base, sub)
        if len(ft_train.present) and len(ft_dev.present):
            ftc = dataclasses.replace(
                tc, steps=sc.finetune_steps, learning_rate=1e-4, eval_every=sc.eval_every
            )
            model, rec = fit_temporal(sub, ft_train, ft_dev, config=ftc, start=model)
            finetune[cam] = {k: rec[k] for k in ("dev_loss", "best_step", "initial_dev_loss")}
        est = load_estimator(PRETRAINED, sub) if estimator_all is not None else None
        flat = people.reshape(-1)
        xyf, scf = xs.reshape(F * G, C - 1, K, 2), ss.reshape(F * G, C - 1, K)
        blend = np.zeros((F * G, K, 3))
        if flat.any():
            blend[flat] = predict_people(est, xyf[flat], scf[flat], method="blend", layout=LAYOUT)
        blend = blend.reshape(F, G, K, 3)
        every = np.broadcast_to(people[..., None], (F, G, K))
        members = np.where(people[..., None], res.members[:, :, keep], -1)
        stamps = np.arange(F) / fps
        mk = lambda x: _results(  # noqa: E731
            x, every, people, members, res.identity[:, keep], tuple(sub.names), stamps, track
        )
        tblend, _ = refine_tracks(model, sub, xs, ss, track, people, method="blend")
        synthetic_only, _ = refine_tracks(
            for_rig(base, sub), sub, xs, ss, track, people, method="blend"
        )
        rows = {
            "blend": blend,
            "blend + Butterworth": _butterworth(mk(blend), fps),
            "temporal (synthetic only), blend + Butterworth": _butterworth(mk(synthetic_only), fps),
            "temporal, blend": tblend,
            "temporal, blend + Butterworth": _butterworth(mk(tblend), fps),
        }
        views = (ss > 0).sum(2)  # (F, G, K) other cameras that saw it
        rig_c = rig.select([cam])
        for row, xyz in rows.items():
            d = _held_out_errors(rig_c, xyz, every, xy[:, :, c], score[:, :, c])
            r = table.setdefault(row, {"0": [], "1": [], "2+": []})
            bones_sd.setdefault(row, []).append(_bone_sd_cm(xyz, people, track))
            for name, sel in (("0", views == 0), ("1", views == 1), ("2+", views >= 2)):
                r[name].append(d[sel & np.isfinite(d)])
    summary = {}
    for row, parts in table.items():
        summary[row] = {"bone_sd_cm": float(np.mean(bones_sd[row]))}
        for name, ds in parts.items():
            d = np.concatenate(ds)
            summary[row][name] = {
                "n": int(len(d)),
                "median_px": float(np.median(d)) if len(d) else None,
                "within_20px": float((d <= 20).mean() * 100) if len(d) else None,
                "within_50px": float((d <= 50).mean() * 100) if len(d) else None,
            }
    return {
        "trial": demo.MULTI_TRIAL,
        "frames": F,
        "split": demo.SPLIT,
        "held_out": summary,
        "base_training": {k: base_record[k] for k in ("dev_loss", "best_step", "initial_dev_loss")},
        "finetune": finetune,
        "detector_fit": "fit_detector on the trial's own detections",
    }


def _markdown(report: dict) -> str:
    lines = []
    syn = report.get("synthetic")
    if syn:
        lines.append(
            f"## Synthetic: {syn['rig']}, shift {syn['shift']}, true groupings and tracks\n"
        )
        lines.append(f"Chosen on validation: **{syn['chosen_on_validation']}**.\n")
        for split in ("validation", "test"):
            lines.append(f"### {split} scenes\n")
            lines.append("| 3D stage | PCP % | MPJPE mm | MPJPE, 0 views | 1 view | 2+ views |")
            lines.append("|---|---|---|---|---|---|")
            for row, v in syn["tables"][split].items():
                bv = v["by_views"]
                cell = lambda k: "-" if bv[k]["mpjpe_mm"] is None else f"{bv[k]['mpjpe_mm']:.1f}"  # noqa: E731
                lines.append(
                    f"| {row} | {v['pcp']:.1f} | {v['mpjpe_mm']:.1f} | {cell('0')} | "
                    f"{cell('1')} | {cell('2+')} |"
                )
            n = syn["tables"][split]["blend"]["by_views"]
            lines.append(
                f"\nKeypoints: {n['0']['n']} seen by no view, {n['1']['n']} by one, "
                f"{n['2+']['n']} by two or more.\n"
            )
        over = syn.get("test_over_seeds")
        if over:
            lines.append(
                f"### test scenes, training seeds {over['seeds']} (mean ± sd; the temporal rows "
                f"of {syn['chosen_variant']})\n"
            )
            lines.append("| 3D stage | PCP % | MPJPE mm | MPJPE, 0 views | 1 view | 2+ views |")
            lines.append("|---|---|---|---|---|---|")
            ms = lambda v: "-" if v is None else f"{v['mean']:.1f} ± {v['sd']:.1f}"  # noqa: E731
            for row, v in over["rows"].items():
                lines.append(
                    f"| {row} | {ms(v['pcp'])} | {ms(v['mpjpe_mm'])} | {ms(v['mpjpe_mm_0_views'])}"
                    f" | {ms(v['mpjpe_mm_1_views'])} | {ms(v['mpjpe_mm_2+_views'])} |"
                )
            lines.append("")
    real = report.get("real")
    if real:
        lines.append(f"## Real: {real['trial']} ({real['frames']} frames), each camera held out\n")
        lines.append(
            "| 3D stage | 0 other views: within 20 px / median | 1 other view | 2+ other views "
            "| bone length sd, cm |"
        )
        lines.append("|---|---|---|---|---|")
        for row, v in real["held_out"].items():
            cells = []
            for k in ("0", "1", "2+"):
                c = v[k]
                cells.append(
                    "-"
                    if c["median_px"] is None
                    else f"{c['within_20px']:.1f} % / {c['median_px']:.1f} px (n={c['n']})"
                )
            lines.append(f"| {row} | " + " | ".join(cells) + f" | {v['bone_sd_cm']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--scale", choices=sorted(SCALES), default="quick")
    ap.add_argument("--parts", default="synthetic,real", help="synthetic, real or both")
    ap.add_argument("--data", type=Path, default=demo.DEFAULT_DATA, help="the Pose2Sim demo")
    ap.add_argument("--progress", action="store_true")
    args = ap.parse_args(argv)
    sc = SCALES[args.scale]
    args.out.mkdir(parents=True, exist_ok=True)
    report: dict = {"command": "python -m experiments.temporal " + " ".join(argv or [])}
    t0 = time.time()
    parts = set(args.parts.split(","))
    if "synthetic" in parts:
        report["synthetic"] = synthetic_part(sc, args.out, args.progress)
    if "real" in parts:
        if args.data.is_dir():
            weights = (
                report["synthetic"]["chosen_weights"]
                if "synthetic" in report
                else VARIANTS[DEFAULT_VARIANT]
            )
            report["real"] = real_part(sc, args.out, args.progress, args.data, weights)
        else:
            report["real_missing"] = f"no Pose2Sim demo at {args.data}"
    report["seconds"] = time.time() - t0
    atomic_write_text(args.out / "temporal.json", report_json(report))
    atomic_write_text(args.out / "temporal.md", _markdown(report))
    print(_markdown(report))


if __name__ == "__main__":
    main()
