"""domain-shift: models trained on the default simulator, tested on scenes they never saw.

The 5-view matcher and the estimator trained as in ``paper-panoptic`` (default simulator), tested
on validation and test scenes (the same seed streams, 1-8 people) made with detectors, people and
rigs they never saw (`mvpose_jax.synthetic.shifts.SHIFTS`: COCO-sigma heavy-tailed noise, part
mixing, occluders and the image border, another score calibration, children and poses outside
the training ranges, the floor 0.3 or 0.6 m off, calibration errors; ``none`` is the unshifted
reference). Per shift and split: per-frame ARI of the GAT (dev-chosen threshold) and the epipolar
matcher (dev-chosen cutoff); PCP, MPJPE, completeness and mAP of GAT, epipolar and true groups,
each with the MLP, DLT and robust triangulation (`shift_rows`, `tables`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments.config import SPLITS, Scale
from experiments.data import Data, make_data, make_shifted_scenes, true_members
from experiments.fitting import combined_config, fit_estimator, fit_matcher, free_compiled_programs
from experiments.records import run_record, save_partial
from experiments.tables import diff_mean_sd, has_value, mean_sd, seeds_line
from mvpose_jax.adapt import AdaptConfig, MatcherAdaptConfig, adapt_estimator, adapt_matcher
from mvpose_jax.cameras import up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.errors import InputError
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import poses_of_members
from mvpose_jax.metrics import matching_scores, mpjpe_on_reference_keypoints, pose_metrics
from mvpose_jax.skeletons import Poses3D
from mvpose_jax.synthetic import SHIFTS

SHIFT_PIPELINES = {
    # name: (grouping, 3D method)
    "combined_mlp": ("combined", "mlp"),
    "combined_robust": ("combined", "robust"),
    "combined_blend": ("combined", "blend"),
    "gat_mlp": ("gat", "mlp"),
    "gat_dlt": ("gat", "dlt"),
    "gat_robust": ("gat", "robust"),
    "epipolar_mlp": ("epipolar", "mlp"),
    "epipolar_dlt": ("epipolar", "dlt"),
    "epipolar_robust": ("epipolar", "robust"),
    "true_mlp": ("true", "mlp"),
    "true_dlt": ("true", "dlt"),
    "true_robust": ("true", "robust"),
    "gat_blend": ("gat", "blend"),
    "epipolar_blend": ("epipolar", "blend"),
    "true_blend": ("true", "blend"),
}
SHIFT_METRICS = ("pcp", "mpjpe_mm", "completeness", "map")
# After `adapt`: the MLP adapted to the split's own detections, grouped by the same proposals it
# then runs behind (no labels; issue 19 item 3).
ADAPT_PIPELINES = {
    "combined_mlp_adapted": ("combined", "mlp"),
    "combined_blend_adapted": ("combined", "blend"),
}


def shift_rows(
    data: Data,
    split: str,
    matcher,
    estimator,
    fit: dict,
    adapt: AdaptConfig | None = None,
    matcher_adapt: MatcherAdaptConfig | None = None,
) -> dict:
    """One shift, one split: per-frame ARI of every matcher, and PCP, MPJPE, completeness and
    mAP of every grouping (the combined matcher and the GAT at their dev-chosen thresholds,
    epipolar at its dev-chosen cutoff, the true groups) with every 3D method (the MLP, DLT,
    robust triangulation, the blend of robust triangulation and the MLP); each estimator
    method's MPJPE on the keypoints robust triangulation reconstructs
    (``mpjpe_on_robust_keypoints_mm``, like with like); with ``adapt``, also the estimator
    adapted to the split's own detections behind the combined proposals (`ADAPT_PIPELINES`);
    with ``matcher_adapt``, the ARI of the GAT and the combined matcher after the matcher is
    adapted to the split's own detections (`adapt.adapt_matcher`, the combined proposals as
    pseudo-labels; ``gat_adapted``, ``combined_adapted``)."""
    rig = data.rig
    det, ident, gt, ids = data.detections(split, rig.names)
    scoring = {"up": up_vector(rig), "person_ids": ids}
    count = np.asarray(det.count)
    groups = {
        "combined": run_pipeline(
            rig, det, matcher=matcher, proposals="combined", combined=combined_config(fit)
        ),
        "gat": run_pipeline(rig, det, matcher=matcher, proposals="gat", threshold=fit["threshold"]),
        "epipolar": run_pipeline(rig, det, half_score_px=fit["geometric_cutoff_px"]),
    }
    out = {"matching": {}, "pose": {}, "frames": int(len(count))}
    if matcher_adapt is not None:
        # Pseudo-labels: the combined proposals above (no truth); the adapted GAT keeps the
        # matcher's dev-chosen thresholds.
        try:
            adapted_matcher, report = adapt_matcher(
                rig,
                det,
                matcher,
                identity=groups["combined"].identity,
                config=matcher_adapt,
                progress=False,
            )
        except InputError as e:  # too few frames of cross-view pairs (tiny scales): no rows
            out["matcher_adapt"] = {"skipped": str(e)}
        else:
            groups["combined_adapted"] = run_pipeline(
                rig,
                det,
                matcher=adapted_matcher,
                proposals="combined",
                combined=combined_config(fit),
            )
            groups["gat_adapted"] = run_pipeline(
                rig, det, matcher=adapted_matcher, proposals="gat", threshold=fit["threshold"]
            )
            keys = ("steps", "best_step", "stopped", "heldout_loss_before", "heldout_loss_after")
            out["matcher_adapt"] = {k: getattr(report, k) for k in keys} | {
                "seconds": round(report.seconds, 1)
            }
    for name, res in groups.items():
        s = matching_scores(ident, res.identity, count)
        out["matching"][name] = {k: round(float(s[k]), 5) for k in ("ari", "pooled_ari")}
    members = {name: res.members for name, res in groups.items() if not name.endswith("_adapted")}
    members["true"] = true_members(ident, gt.valid.shape[1], min_views=2)
    poses = {}
    for key, (grouping, method) in SHIFT_PIPELINES.items():
        poses[key], conf = poses_of_members(
            rig, det, members[grouping], estimator=estimator, method=method
        )
        m = pose_metrics(poses[key], gt, confidence=conf, **scoring)
        out["pose"][key] = {k: round(float(m[k]), 3) for k in SHIFT_METRICS}
    for key, (grouping, method) in SHIFT_PIPELINES.items():
        if method in ("mlp", "blend"):
            out["pose"][key]["mpjpe_on_robust_keypoints_mm"] = _mpjpe_on(
                poses[key], poses[f"{grouping}_robust"], gt, scoring
            )
            # The acceptance's like with like: on the keypoints epipolar + robust triangulation
            # (the geometric pipeline) reconstructs, whatever this grouping did.
            out["pose"][key]["mpjpe_on_epipolar_robust_keypoints_mm"] = round(
                mpjpe_on_reference_keypoints(poses[key], poses["epipolar_robust"], gt), 3
            )
    adapted_of: dict = {}
    for key, (grouping, method) in ({} if adapt is None else ADAPT_PIPELINES).items():
        if grouping not in adapted_of:
            try:
                adapted, report = adapt_estimator(
                    rig, det, estimator, members=members[grouping], config=adapt, progress=False
                )
                info = {
                    k: getattr(report, k)
                    for k in (
                        "steps",
                        "best_step",
                        "stopped",
                        "heldout_px_before",
                        "heldout_px_after",
                    )
                } | {"seconds": round(report.seconds, 1)}
            except InputError as e:
                # Too few grouped people to hold frames out (tiny scales, a matcher that groups
                # nobody): the row is the unadapted estimator, and says so.
                adapted, info = estimator, {"skipped": str(e)}
            adapted_of[grouping] = adapted, info
        adapted, info = adapted_of[grouping]
        got, conf = poses_of_members(rig, det, members[grouping], estimator=adapted, method=method)
        m = pose_metrics(got, gt, confidence=conf, **scoring)
        out["pose"][key] = {k: round(float(m[k]), 3) for k in SHIFT_METRICS} | {"adapt": info}
        out["pose"][key]["mpjpe_on_robust_keypoints_mm"] = _mpjpe_on(
            got, poses[f"{grouping}_robust"], gt, scoring
        )
        out["pose"][key]["mpjpe_on_epipolar_robust_keypoints_mm"] = round(
            mpjpe_on_reference_keypoints(got, poses["epipolar_robust"], gt), 3
        )
    return out


def run(
    sc: Scale, seeds: list[int], data_seed: int, out: Path, progress: bool
) -> tuple[list[dict], list[str]]:
    """Models trained on the default simulator (scale ``sc``, each training seed), tested on the
    scenes of ``data_seed`` made with every shift of ``sc.shifts`` (None: all).

    Returns: (one record per training seed, the lines of tables.md after its head).
    """
    rig = load_rig("panoptic5")
    names = [n for n in SHIFTS if sc.shifts is None or n in sc.shifts]
    shifted = {name: make_shifted_scenes(rig, sc, data_seed, SHIFTS[name]) for name in names}
    runs = []
    for seed in seeds:
        free_compiled_programs()  # the last seed's evaluation programs
        data = make_data(rig, {}, sc, seed, progress)
        print(f"== seed {seed}: matcher, 5 views", flush=True)
        matcher, fit = fit_matcher(data, sc, rig.names, seed, progress)
        print(f"== seed {seed}: estimator, 5 views", flush=True)
        est, est_fit = fit_estimator(data, sc, rig.names, rig.names, seed, progress)
        res = run_record(seed, data_seed, sc) | {
            "training": {"matcher-5": fit, "estimator": est_fit},
            "shifts": {},
        }
        for name in names:
            print(f"== seed {seed}: shift {name}", flush=True)
            scenes = Data(rig, [], [], shifted[name])
            res["shifts"][name] = {
                split: shift_rows(
                    scenes,
                    split,
                    matcher,
                    est,
                    fit,
                    adapt=sc.adapt,
                    matcher_adapt=None if sc.adapt is None else sc.matcher_adapt,
                )
                for split in SPLITS
            }
        runs.append(res)
        save_partial(runs, out)
    return runs, tables(runs)


SHIFT_PIPELINE_NAMES = {
    "combined_mlp": "combined + MLP",
    "combined_robust": "combined + robust triangulation",
    "gat_mlp": "GAT + MLP",
    "gat_dlt": "GAT + DLT",
    "gat_robust": "GAT + robust triangulation",
    "epipolar_mlp": "epipolar + MLP",
    "epipolar_dlt": "epipolar + DLT",
    "epipolar_robust": "epipolar + robust triangulation",
    "true_mlp": "true groups + MLP",
    "true_dlt": "true groups + DLT",
    "true_robust": "true groups + robust triangulation",
    "gat_blend": "GAT + MLP/robust blend",
    "epipolar_blend": "epipolar + MLP/robust blend",
    "true_blend": "true groups + MLP/robust blend",
    "combined_blend": "combined + MLP/robust blend (learned, the default)",
    "combined_mlp_adapted": "combined + MLP after adapt",
    "combined_blend_adapted": "combined + blend after adapt",
}


def tables(runs: list[dict]) -> list[str]:
    """Per split (test first): a summary against the acceptance margins, then per shift the
    matching and every pipeline's PCP, MPJPE, completeness and mAP."""
    lines = []
    # The shifts every run tested (`--shifts` may have chosen some).
    names = [n for n in runs[0]["shifts"] if all(n in r["shifts"] for r in runs)]
    # Runs from before `adapt` have no adapted rows: their tables keep the old columns.
    present = runs[0]["shifts"][names[0]]
    adapted = all(
        "combined_blend_adapted" in r["shifts"][n][s]["pose"]
        for r in runs
        for n in names
        for s in present
    )
    for split in (s for s in ("test", "validation") if s in present):
        role = (
            "the reported results; read only for these tables"
            if split == "test"
            else "where settings are chosen"
        )
        lines += [
            f"## {split.capitalize()} scenes ({role})",
            "",
            f"### Summary: panoptic5, {split} scenes with 1-8 people, per shift",
            "",
            seeds_line(runs) + " The learned proposals are the combined matcher's (GAT and "
            "epipolar geometry, `proposals.propose_combined`), the learned 3D stage the blend "
            "(robust triangulation wherever it reconstructs a keypoint, the MLP elsewhere); ARI: "
            "mean of per-frame scores. Acceptance: Δ ARI = combined − epipolar ≥ −0.002; the "
            "combined proposals cost at most 0.5 PCP points against the same 3D stage on the "
            "true groups (Δ true, for the MLP, robust triangulation and the blend, each ≥ −0.5); "
            "Δ PCP = learned pipeline − epipolar + robust triangulation ≥ +1 point (≥ +2 after "
            "adapt: the estimator fine-tuned without labels on the split's own detections grouped "
            "by the combined proposals).",
            "",
            "| shift | combined ARI | GAT ARI | epipolar ARI | Δ ARI | Δ true MLP "
            "| Δ true robust | Δ true blend | combined + MLP PCP | combined + blend PCP "
            "| epipolar + robust PCP | Δ PCP MLP | Δ PCP blend"
            + (" | combined + blend after adapt PCP | Δ PCP after adapt |" if adapted else " |"),
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"
            + ("---|---|" if adapted else ""),
        ]
        for name in names:
            base = ("shifts", name, split)
            ari = (*base, "matching")
            pcp = {k: (*base, "pose", k, "pcp") for k in {**SHIFT_PIPELINES, **ADAPT_PIPELINES}}
            row = (
                f"| {name} "
                f"| {mean_sd(runs, (*ari, 'combined', 'ari'), 4)} "
                f"| {mean_sd(runs, (*ari, 'gat', 'ari'), 4)} "
                f"| {mean_sd(runs, (*ari, 'epipolar', 'ari'), 4)} "
                f"| {diff_mean_sd(runs, (*ari, 'combined', 'ari'), (*ari, 'epipolar', 'ari'), 4)} "
                f"| {diff_mean_sd(runs, pcp['combined_mlp'], pcp['true_mlp'], 2)} "
                f"| {diff_mean_sd(runs, pcp['combined_robust'], pcp['true_robust'], 2)} "
                f"| {diff_mean_sd(runs, pcp['combined_blend'], pcp['true_blend'], 2)} "
                f"| {mean_sd(runs, pcp['combined_mlp'], 2)} "
                f"| {mean_sd(runs, pcp['combined_blend'], 2)} "
                f"| {mean_sd(runs, pcp['epipolar_robust'], 2)} "
                f"| {diff_mean_sd(runs, pcp['combined_mlp'], pcp['epipolar_robust'], 2)} "
                f"| {diff_mean_sd(runs, pcp['combined_blend'], pcp['epipolar_robust'], 2)} |"
            )
            if adapted:
                row += (
                    f" {mean_sd(runs, pcp['combined_blend_adapted'], 2)} "
                    f"| {diff_mean_sd(runs, pcp['combined_blend_adapted'], pcp['epipolar_robust'], 2)} |"
                )
            lines.append(row)
        lines += _matcher_adapt_table(runs, names, split)
        lines += [
            "",
            "| shift | what |",
            "|---|---|",
        ]
        lines += [
            f"| {name} | {SHIFTS[name].description if name in SHIFTS else ''} |" for name in names
        ]
        lines += [
            "",
            f"### Every pipeline per shift ({split} scenes)",
            "",
            "PCP over the 10 limbs (%, every person counted), MPJPE (mm, over the keypoints a "
            "method produced), completeness (%), mAP; MPJPE on the keypoints robust "
            "triangulation reconstructs behind the same grouping, and on those epipolar + "
            "robust triangulation reconstructs (mm; the MLP and the blend only, like with like: "
            "acceptance ≤ 1.05 × the epipolar + robust triangulation row's MPJPE).",
            "",
            "| shift | pipeline | PCP | MPJPE mm | complete % | mAP | MPJPE on robust's mm "
            "| MPJPE on epipolar + robust's mm |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name in names:
            for key, label in SHIFT_PIPELINE_NAMES.items():
                if key in ADAPT_PIPELINES and not adapted:
                    continue
                base = ("shifts", name, split, "pose", key)
                cells = " | ".join(
                    mean_sd(runs, (*base, k), 1 if k == "mpjpe_mm" else 2) for k in SHIFT_METRICS
                )
                learned = {**SHIFT_PIPELINES, **ADAPT_PIPELINES}[key][1] in ("mlp", "blend")
                like = mean_sd(runs, (*base, "mpjpe_on_robust_keypoints_mm"), 1) if learned else ""
                # Runs from before this column have no value: left empty.
                geo = (*base, "mpjpe_on_epipolar_robust_keypoints_mm")
                has_geo = learned and all(has_value(r, geo) for r in runs)
                like_geo = mean_sd(runs, geo, 1) if has_geo else ""
                lines.append(f"| {name} | {label} | {cells} | {like} | {like_geo} |")
        lines.append("")
    return lines


def _matcher_adapt_table(runs: list[dict], names: list[str], split: str) -> list[str]:
    """Per-frame ARI before and after the matcher is adapted to the split (`shift_rows`'
    ``matcher_adapt``), where every run has it."""
    if not all(
        has_value(r, ("shifts", n, split, "matching", "gat_adapted")) for r in runs for n in names
    ):
        return []
    lines = [
        "",
        f"Matcher adapted to each shift's own {split} detections (`adapt.adapt_matcher`; "
        "pseudo-labels: the combined proposals, no truth; the matcher's dev-chosen thresholds "
        "kept), per-frame ARI:",
        "",
        "| shift | GAT | GAT adapted | combined | combined adapted | Δ ARI adapted − epipolar |",
        "|---|---|---|---|---|---|",
    ]
    for name in names:
        ari = ("shifts", name, split, "matching")
        lines.append(
            f"| {name} | {mean_sd(runs, (*ari, 'gat', 'ari'), 4)} "
            f"| {mean_sd(runs, (*ari, 'gat_adapted', 'ari'), 4)} "
            f"| {mean_sd(runs, (*ari, 'combined', 'ari'), 4)} "
            f"| {mean_sd(runs, (*ari, 'combined_adapted', 'ari'), 4)} "
            f"| {diff_mean_sd(runs, (*ari, 'combined_adapted', 'ari'), (*ari, 'epipolar', 'ari'), 4)} |"
        )
    return lines


def _mpjpe_on(poses: Poses3D, tri: Poses3D, gt: Poses3D, scoring: dict) -> float:
    """MPJPE (mm) of ``poses`` on the keypoints triangulation ``tri`` reconstructs (like with
    like: the keypoints only a network gives are left out)."""
    restricted = Poses3D(
        poses.xyz, poses.valid & tri.valid, tri.keypoint_valid & poses.valid[..., None]
    )
    return round(float(pose_metrics(restricted, gt, **scoring)["mpjpe_mm"]), 3)
