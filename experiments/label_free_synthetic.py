"""Does the label-free score rank results as the labelled one does? ``python -m
experiments.label_free_synthetic --out DIR``.

On synthetic scenes with the simulator's realistic detector noise (its default detector, and the
named shifts "coco-sigmas" and "part-mixing" of `synthetic.SHIFTS`), pipeline variants without
models (epipolar proposals with DLT, centroid and robust triangulation; robust with tighter and
looser thresholds, other proposal cut-offs, three views; tracked with the One-Euro filter) and
corrupted results (10 % of the keypoints moved 5 cm, the wrists dropped, a fifth of the keypoints
dropped) are scored twice: by `label_free.label_free_score` (no labels) and by
`metrics.pose_metrics` against the synthetic truth (PCP, MPJPE). Each label-free number is
correlated with PCP and with MPJPE over the variants (Spearman, scipy), each oriented so that
higher is better. Writes ``DIR/label_free_synthetic.md``, ``DIR/label_free_synthetic.json`` and
the report of the robust variant on the first scene (``DIR/report/``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from experiments.real import corrupted
from mvpose_jax.cameras import up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.data.recording import recording_fps
from mvpose_jax.inference import run_pipeline
from mvpose_jax.label_free import (
    label_free_score,
    reference_reprojection,
    write_label_free_report,
)
from mvpose_jax.metrics import match_people, pose_metrics
from mvpose_jax.smoothing import OneEuroConfig
from mvpose_jax.synthetic import SHIFTS, SyntheticConfig, generate_recording
from mvpose_jax.tracking import TrackingConfig

LAYOUT = "coco18"
SCENES = (
    ("default", 4),
    ("coco-sigmas", 5),
    ("part-mixing", 6),
    ("occluders", 7),
)  # (shift, people)

# name -> run_pipeline settings (no models).
PIPELINES = {
    "dlt": {"method": "dlt"},
    "centroid": {"method": "centroid"},
    "robust": {"method": "robust"},
    "robust outlier 10 px": {"method": "robust", "outlier_px": 10.0},
    "robust outlier 80 px": {"method": "robust", "outlier_px": 80.0, "view_outlier_px": 80.0},
    "robust half-score 10 px": {"method": "robust", "half_score_px": 10.0},
    "robust half-score 90 px": {"method": "robust", "half_score_px": 90.0},
    "robust 3 views": {"method": "robust", "min_views": 3},
    "dlt 3 views": {"method": "dlt", "min_views": 3},
    "robust tracked one-euro": {"method": "robust", "tracked": True},
}
# name -> (the pipeline it corrupts, how).
CORRUPTED = {
    "robust, 10% keypoints moved 5 cm": ("robust", "move"),
    "robust, wrists dropped": ("robust", "wrists"),
    "robust, 20% keypoints dropped": ("robust", "drop"),
}
PCK_MM = (50, 100)  # PCK3D radii, mm (every true keypoint counted: a missed one is wrong)
ALL_SKELETONS = "share of all skeletons' keypoints within 20 px"
# The label-free numbers correlated, each as (label, path in the report dict, sign: + higher
# is better, - lower is better).
LABEL_FREE = (
    ("share within 20 px (misses count)", ("result", "overall", "share_within_px", "20"), 1),
    ("share within 10 px (misses count)", ("result", "overall", "share_within_px", "10"), 1),
    (ALL_SKELETONS, ("share_of_all_within_px", "20"), 1),
    ("share within 20 px of produced only (misses skipped)", ("produced_share_20",), 1),
    ("median px (produced)", ("result", "overall", "median_px"), -1),
    ("coverage", ("result", "overall", "coverage"), 1),
    ("leave-one-out median px (the grouping)", ("leave_one_out", "overall", "median_px"), -1),
    ("leave-one-out share within 20 px", ("leave_one_out", "overall", "share_within_px", "20"), 1),
    ("people count |result - median of views|", ("people_count", "mean_abs_diff_median"), -1),
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--rig", default="panoptic5")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=80, help="frames per scene")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rig = load_rig(args.rig)
    up = up_vector(rig)

    rows: dict[str, list[dict]] = {n: [] for n in (*PIPELINES, *CORRUPTED)}
    floors = []
    for i, (shift, people) in enumerate(SCENES):
        config = SyntheticConfig()
        if shift != "default":
            config = SHIFTS[shift].config(config)
        rec = generate_recording(
            rig, num_people=people, num_frames=args.frames, config=config, seed=[args.seed, 36, i]
        )
        fps = recording_fps(rec.timestamps)
        gt = _seen_truth(rec)
        floor = reference_reprojection(
            rec.ground_truth.xyz,
            rec.ground_truth.keypoint_valid,
            rig,
            rec.detections,
            rec.identity,
            cameras=rec.cameras,
            layout=LAYOUT,
        )
        floors.append({"scene": shift, "people": people, **_agreement_dict(floor.overall)})
        results = {}
        for name, settings in PIPELINES.items():
            settings = dict(settings)
            if settings.pop("tracked", False):
                settings.update(tracking=TrackingConfig(), one_euro=OneEuroConfig())
            res = run_pipeline(rig, rec.detections, fps=fps, layout=LAYOUT, **settings)
            results[name] = PoseResults(
                res.poses,
                res.confidence,
                res.members,
                res.identity,
                res.cameras,
                LAYOUT,
                rec.timestamps,
                res.track,
            )
        rng = np.random.default_rng([args.seed, 36, i, 1])
        for name, (base, how) in CORRUPTED.items():
            results[name] = corrupted(results[base], how, rng)
        for name, result in results.items():
            report = label_free_score(result, rig, rec.detections, layout=LAYOUT, noise_floor=floor)
            if i == 0 and name == "robust":
                write_label_free_report(report, out / "report")
            m = pose_metrics(result.poses, gt, layout=LAYOUT, up=up)
            d = report.to_dict()
            ov = d["result"]["overall"]
            d["produced_share_20"] = (
                ov["share_within_px"]["20"] / ov["coverage"] if ov["coverage"] else None
            )
            row = {"scene": shift, "pcp": m["pcp"], "mpjpe_mm": m["mpjpe_mm"]}
            row.update({f"pck3d_{mm}": _pck3d(result.poses, gt, mm) for mm in PCK_MM})
            row.update({label: _get(d, path) for label, path, _ in LABEL_FREE})
            if d["jitter_m_s2"] is not None:
                row["jitter_m_s2"] = d["jitter_m_s2"]
                row["bone_cv"] = d["bone_spread"]["median_cv"]
            rows[name].append(row)
        print(f"scene {shift} ({people} people): {time.perf_counter() - t0:.0f} s", flush=True)

    means = {
        name: {
            k: float(np.nanmean([r[k] for r in per_scene if r.get(k) is not None]))
            for k in per_scene[0]
            if k != "scene"
        }
        for name, per_scene in rows.items()
    }
    names = list(means)
    correlations = {}
    for label, _, sign in LABEL_FREE:
        lf = [sign * means[n][label] for n in names]
        correlations[label] = {
            "pcp": _spearman(lf, [means[n]["pcp"] for n in names]),
            "mpjpe": _spearman(lf, [-means[n]["mpjpe_mm"] for n in names]),
            **{
                f"pck3d_{mm}": _spearman(lf, [means[n][f"pck3d_{mm}"] for n in names])
                for mm in PCK_MM
            },
            "pcp_per_scene_mean": float(
                np.nanmean(
                    [
                        _spearman(
                            [sign * rows[n][i][label] for n in names],
                            [rows[n][i]["pcp"] for n in names],
                        )
                        for i in range(len(SCENES))
                    ]
                )
            ),
            "same_winner_as_pcp": names[int(np.nanargmax(lf))]
            == names[int(np.argmax([means[n]["pcp"] for n in names]))],
        }
    seconds = time.perf_counter() - t0
    record = {
        "args": vars(args),
        "scenes": [{"shift": s, "people": n} for s, n in SCENES],
        "noise_floor": floors,
        "variants": means,
        "per_scene": rows,
        "spearman": correlations,
        "seconds": seconds,
    }
    atomic_write_text(
        out / "label_free_synthetic.json",
        json.dumps(_nan_as_null(record), indent=1, allow_nan=False) + "\n",
    )
    text = "\n".join(_markdown(args, floors, means, correlations, seconds)) + "\n"
    atomic_write_text(out / "label_free_synthetic.md", text)
    print(text)
    return 0


def _seen_truth(rec):
    """The ground truth of the people some camera detected (a person nobody saw cannot be
    placed)."""
    ident = np.asarray(rec.identity)
    G = rec.ground_truth.valid.shape[1]
    seen = (ident[:, :, :, None] == np.arange(G)).any(axis=(1, 2))
    return rec.ground_truth._replace(valid=np.asarray(rec.ground_truth.valid) & seen)


def _pck3d(pred, gt, radius_mm: float) -> float:
    """Percent of the true keypoints (of the people some camera saw) that the prediction matched
    to their person (`metrics.match_people`) puts within ``radius_mm``; a person or keypoint not
    produced counts as wrong (the MVOR protocol's PCK3D)."""
    K = np.shape(gt.keypoint_valid)[-1]
    matches = match_people(pred, gt, np.arange(K))
    kv = np.asarray(gt.keypoint_valid) & np.asarray(gt.valid)[..., None]
    hit = 0
    for f, (pi, gi) in enumerate(matches):
        d = np.linalg.norm(np.asarray(pred.xyz)[f, pi] - np.asarray(gt.xyz)[f, gi], axis=-1)
        ok = np.asarray(pred.keypoint_valid)[f, pi] & kv[f, gi] & (d * 1000 <= radius_mm)
        hit += int(ok.sum())
    return 100.0 * hit / max(int(kv.sum()), 1)


def _agreement_dict(a) -> dict:
    return {
        "median_px": a.median_px,
        "share_within_10_px": a.share_within_px["10"],
        "share_within_20_px": a.share_within_px["20"],
    }


def _nan_as_null(value):
    if isinstance(value, dict):
        return {k: _nan_as_null(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nan_as_null(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _get(d: dict, path: tuple[str, ...]):
    for key in path:
        d = d[key]
    return d


def _spearman(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:  # a constant has no rank
        return float("nan")
    return float(spearmanr(a[ok], b[ok]).statistic)


def _markdown(args, floors, means, correlations, seconds) -> list[str]:
    lines = [
        f"# Label-free score against the labelled one ({args.rig}, {args.frames} frames per "
        f"scene, seed {args.seed})",
        "",
        "Scenes: "
        + ", ".join(f"{f['scene']} ({f['people']} people)" for f in floors)
        + ". Numbers are means over the scenes.",
        "",
        "Noise floor (the detections' own spread around the truth, `reference_reprojection`): "
        + "; ".join(
            f"{f['scene']}: median {f['median_px']:.1f} px, "
            f"{100 * f['share_within_20_px']:.1f} % within 20 px"
            for f in floors
        ),
        "",
        "| variant | PCP % | PCK3D@50 % | PCK3D@100 % | MPJPE mm | all skeletons ≤20 px % "
        "| share ≤20 px % | share ≤10 px % | median px | coverage % | LOO median px |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, m in sorted(means.items(), key=lambda kv: -kv[1]["pcp"]):
        lines.append(
            f"| {name} | {m['pcp']:.2f} | {m['pck3d_50']:.2f} | {m['pck3d_100']:.2f} "
            f"| {m['mpjpe_mm']:.1f} "
            f"| {100 * m[ALL_SKELETONS]:.2f} "
            f"| {100 * m['share within 20 px (misses count)']:.2f} "
            f"| {100 * m['share within 10 px (misses count)']:.2f} "
            f"| {m['median px (produced)']:.2f} | {100 * m['coverage']:.2f} "
            f"| {m['leave-one-out median px (the grouping)']:.2f} |"
        )
    lines += [
        "",
        "Spearman correlation over the variants (each label-free number oriented higher = "
        "better; MPJPE negated):",
        "",
        "| label-free number | vs PCP | vs PCP, per scene (mean) | vs PCK3D@50 | vs PCK3D@100 "
        "| vs MPJPE | same winner as PCP |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, c in correlations.items():
        lines.append(
            f"| {label} | {c['pcp']:.3f} | {c['pcp_per_scene_mean']:.3f} | {c['pck3d_50']:.3f} "
            f"| {c['pck3d_100']:.3f} | {c['mpjpe']:.3f} | "
            f"{'yes' if c['same_winner_as_pcp'] else 'no'} |"
        )
    lines += [
        "",
        "Blind spots: a keypoint fewer than two other views show has no leave-one-out check; the "
        "result's own projection is still compared where the result has it and a second camera "
        "shows it (a keypoint one camera alone shows is unverifiable: scored as not produced), "
        "and a keypoint the result lacks is a miss wherever the camera shows it. The result's "
        "projection is not "
        "held out (a method may have used the camera), so differences below the noise floor "
        "measure agreement with the detector, not with the truth.",
        "",
        f"({seconds:.0f} s)",
    ]
    return lines


if __name__ == "__main__":
    raise SystemExit(main())
