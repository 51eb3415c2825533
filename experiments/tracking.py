"""Tracks over time on the long tracking scenes (paper-panoptic's last tables): identities (IDF1,
ID switches, MOTA, by py-motmetrics) and, per filter (none, One-Euro, Butterworth), jitter, MPJPE
and PCP, for the learned pipeline and for epipolar proposals + DLT."""

from __future__ import annotations

import numpy as np

from experiments.data import pooled_tracks, stack_frames, tracking_truth, tracking_views
from experiments.fitting import combined_config
from experiments.tables import mean_sd, rounded_tree, seeds_line
from mvpose_jax.cameras import up_vector
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.inference import run_pipeline
from mvpose_jax.metrics import identity_metrics, jitter, pose_metrics
from mvpose_jax.smoothing import smooth_poses
from mvpose_jax.tracking import TrackingConfig


def tracking_rows(rig, scenes: list, matcher, estimator, fit: dict) -> dict:
    """Tracks over time on long scenes: identities (IDF1, switches, MOTA) and, per filter, jitter,
    MPJPE and PCP, for the learned pipeline and for epipolar proposals + DLT.

    Each scene is its own stream (the tracker starts afresh); scenes are pooled by keeping their
    track and person ids apart, so the pooled metrics are those of one long recording.
    """
    fps = 1.0 / float(np.median(np.diff(scenes[0].timestamps)))
    layout = scenes[0].layout
    pipelines = {
        # The learned pipeline as `infer` runs it: combined proposals, the blend.
        "learned": {
            "matcher": matcher,
            "estimator": estimator,
            "proposals": "combined",
            "combined": combined_config(fit),
            "method": "blend",
        },
        "epipolar_dlt": {"half_score_px": fit["geometric_cutoff_px"]},
    }
    filters = {
        "none": {"filter": "none", "fill_gap_s": 0.0, "outlier_m": None},
        "one_euro": {"filter": "one-euro", "fill_gap_s": 0.0, "outlier_m": None},
        "butterworth": {"filter": "butterworth"},
    }
    out = {}
    gt, gt_ids = tracking_truth(scenes)
    # A person only one camera sees cannot be placed by any multi-view method: "don't care" in
    # the identity metrics (neither missed nor a false positive when found); `identity_any_view`
    # counts them too.
    one_view = np.asarray(gt.valid) & (tracking_views(scenes) < 2)
    gt_jitter = jitter(gt.xyz, gt.keypoint_valid, gt.valid, np.where(gt.valid, gt_ids, -1))
    scoring = {"up": up_vector(rig), "person_ids": gt_ids, "layout": layout}
    # Each scene in one chunk: a scene's people go through the 3D stage in one call, not two of
    # other shapes (each new shape costs the jitted stages a compilation, most of this section's
    # time); tracking's backfill then spans the whole scene (`PipelineConfig.chunk_frames`).
    chunk_frames = max(len(rec.detections.count) for rec in scenes)
    for name, kwargs in pipelines.items():
        per_filter = {f: [] for f in filters}
        tracks, seconds, person_frames = [], 0.0, 0
        for rec in scenes:
            res = run_pipeline(
                rig,
                rec.detections,
                tracking=TrackingConfig(),
                fps=fps,
                chunk_frames=chunk_frames,
                **kwargs,
            )
            seconds += res.seconds["tracking"]
            person_frames += int(res.poses.valid.sum())
            tracks.append(res.track)
            results = PoseResults(
                res.poses,
                res.confidence,
                res.members,
                res.identity,
                res.cameras,
                layout,
                rec.timestamps,
                res.track,
            )
            for f, fk in filters.items():
                sm = smooth_poses(results, fps=fps, **fk)
                filled = np.zeros_like(sm.poses.keypoint_valid) if sm.filled is None else sm.filled
                per_filter[f].append((sm.poses, sm.track, filled))
        raw, track = pooled_tracks([p[0] for p in per_filter["none"]], tracks)
        out_poses, out_track = pooled_tracks(
            [p[0] for p in per_filter["butterworth"]], [p[1] for p in per_filter["butterworth"]]
        )
        ident = {"gt_ids": gt_ids, "layout": layout}
        row = {
            # The delivered output (`infer`'s default: tracked, Butterworth, gaps filled).
            "identity": identity_metrics(out_poses, out_track, gt, ignore=one_view, **ident),
            "identity_unfiltered": identity_metrics(raw, track, gt, ignore=one_view, **ident),
            "identity_any_view": identity_metrics(out_poses, out_track, gt, **ident),
            "tracking_ms_per_person_frame": 1000 * seconds / max(person_frames, 1),
            "gt_jitter_mm": gt_jitter,
            "scene_people": [int(r.ground_truth.valid.shape[1]) for r in scenes],
        }
        for f, parts in per_filter.items():
            poses, trk = pooled_tracks([p[0] for p in parts], [p[1] for p in parts])
            filled = stack_frames([p[2] for p in parts], fill=False)
            m = pose_metrics(poses, gt, **scoring)
            row[f] = {
                "jitter_mm": jitter(poses.xyz, poses.keypoint_valid, poses.valid, trk),
                "mpjpe_mm": m["mpjpe_mm"],
                "pcp": m["pcp"],
                "completeness": m["completeness"],
                "filled_share": float(100 * filled.sum() / max(poses.keypoint_valid.sum(), 1)),
            }
        out[name] = rounded_tree(row)
    return out


def tracking_table(runs: list[dict], split: str) -> list[str]:
    """Identities over time, and each filter's jitter and accuracy (tracking scenes)."""
    runs = [r for r in runs if "tracking" in r]  # runs saved before tracking have none
    if not runs:
        return []
    names = {
        "learned": "combined + blend (learned, infer's default)",
        "gat_mlp": "GAT + MLP",  # runs saved before the combined matcher and the blend
        "epipolar_dlt": "epipolar + DLT",
    }
    names = {k: v for k, v in names.items() if k in runs[0]["tracking"][split]}
    first = runs[0]["tracking"][split][next(iter(names))]
    people = first["scene_people"]
    lines = [
        f"### Tracks over time: panoptic5, {split} tracking scenes with {min(people)}-"
        f"{max(people)} people, 30 fps ({first['identity']['person_frames']} person-frames)",
        "",
        seeds_line(runs),
        "",
        "Identities of `infer`'s output (tracked, Butterworth, gaps up to 0.5 s filled) over the "
        'person-frames two or more cameras saw; a person only one camera saw is "don\'t care" '
        "(no multi-view method can place them: neither missed nor false when found). IDF1 "
        "unfiltered: the tracks before filtering and gap filling; IDF1 any view: every person "
        "some camera saw counted.",
        "",
        "| pipeline | IDF1 | IDF1 unfiltered | IDF1 any view | ID switches "
        "| per 1,000 person-frames | MOTA | tracks / people | tracking ms per person-frame |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key, title in names.items():
        base = ("tracking", split, key)
        lines.append(
            f"| {title} | {mean_sd(runs, (*base, 'identity', 'idf1'), 4)} "
            f"| {mean_sd(runs, (*base, 'identity_unfiltered', 'idf1'), 4)} "
            f"| {mean_sd(runs, (*base, 'identity_any_view', 'idf1'), 4)} "
            f"| {mean_sd(runs, (*base, 'identity', 'id_switches'), 1)} "
            f"| {mean_sd(runs, (*base, 'identity', 'switches_per_1000'), 2)} "
            f"| {mean_sd(runs, (*base, 'identity', 'mota'), 4)} "
            f"| {mean_sd(runs, (*base, 'identity', 'num_tracks'), 1)} / "
            f"{mean_sd(runs, (*base, 'identity', 'num_ids'), 0)} "
            f"| {mean_sd(runs, (*base, 'tracking_ms_per_person_frame'), 3)} |"
        )
    lines += [
        "",
        "Jitter: mean |second difference| of keypoints along tracks (mm per frame²); the ground "
        f"truth's own: {mean_sd(runs, ('tracking', split, next(iter(names)), 'gt_jitter_mm'), 2)}.",
        "Filters: none; One-Euro (causal, as the stream runs it); Butterworth (zero-phase, "
        "offline) with outlier rejection and gaps up to 0.5 s filled (share of keypoints filled).",
        "",
        "| pipeline | filter | jitter mm/frame² | × ground truth | MPJPE mm | PCP % "
        "| completeness % | filled % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, title in names.items():
        for f in ("none", "one_euro", "butterworth"):
            base = ("tracking", split, key, f)
            ratio = [
                r["tracking"][split][key][f]["jitter_mm"]
                / r["tracking"][split][key]["gt_jitter_mm"]
                for r in runs
            ]
            ratio_txt = f"{np.mean(ratio):.2f}" + (
                f" ± {np.std(ratio, ddof=1):.2f}" if len(ratio) > 1 else ""
            )
            lines.append(
                f"| {title} | {f} | {mean_sd(runs, (*base, 'jitter_mm'), 2)} | {ratio_txt} "
                f"| {mean_sd(runs, (*base, 'mpjpe_mm'), 1)} | {mean_sd(runs, (*base, 'pcp'), 2)} "
                f"| {mean_sd(runs, (*base, 'completeness'), 2)} "
                f"| {mean_sd(runs, (*base, 'filled_share'), 4)} |"
            )
    return lines + [""]
