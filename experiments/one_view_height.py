"""People one camera sees, placed at a standing person's shoulder height: ``python -m
experiments.one_view_height --out DIR`` (issue 37 item 5; MVOR days 1-2, evaluation only).

A person one view alone sees is lifted by the estimator, whose depth comes from the body's size
in the image (docs/real.md, "People one camera sees": 265 mm median joint error). MVOR's floor is
measured from the people (`floor.estimate_floor_from_detections`), and an upright adult's
mid-shoulder stands about `floor.STANDING_SHOULDER_HEIGHT_M` above it. This checks whether that
prior places them better: each one-view person whose lifted torso is within ``max_tilt`` degrees
of up is moved along its camera's ray through its lifted mid-shoulder until that mid-shoulder is
at the standing height (a translation: the body keeps its size), where the move keeps it within
``MOVE_FACTORS`` of its depth.

Rows: the shipped rig-agnostic estimator (`trained.PRETRAINED`, no training) in the blend with
``min_views`` 1, on the true groups and on the epipolar grouping; with ``--models DIR``
(``experiments.real``'s models folder, its MVOR pair trained there where missing) also the
``infer`` default with that pair (the combined matcher's proposals, the blend), as ``infer
--min-views 1`` runs it; each as lifted and moved at each tilt limit; scored by the MVOR protocol (`mvor_protocol.evaluate`) overall and on the one-view
people (`real.error_by_views`). Diagnostics on the true groups' one-view people with both
shoulders in the truth and the result: the truth's shoulder height above the measured floor by
views, the angle between the camera's rays to the true and to the lifted mid-shoulder, their
depths, the rays' elevation and the lifted mid-shoulder's height.

Writes ``DIR/one_view_height.md`` and ``DIR/one_view_height.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from experiments.mvor import DEFAULT_ROOT, JOINTS, load_mvor, poses_to_joints, true_identity
from experiments.mvor_protocol import evaluate
from experiments.real import error_by_views, model_settings, pipeline_result
from experiments.real_models import synthetic_models
from experiments.records import report_json
from mvpose_jax.cameras import camera_centres
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.floor import STANDING_SHOULDER_HEIGHT_M, estimate_floor_from_detections
from mvpose_jax.lifting import members_from_identity
from mvpose_jax.skeletons import get_layout
from mvpose_jax.trained import PRETRAINED, load_estimator

SPLIT = "MVOR days 1-2, all frames (evaluation only; nothing is chosen here)"
MAX_TILTS_DEG = (20.0, 30.0, 45.0)
DIAGNOSED_TILT_DEG = 30.0
# A move that would scale the depth by less than 0.3 or more than 3 is left undone.
MOVE_FACTORS = (0.3, 3.0)
GROUPINGS = ("true", "epipolar")


def one_view_people(result: PoseResults) -> list[tuple[int, int, int]]:
    """(frame, group, camera) of each person the result built from one view alone."""
    members = np.asarray(result.members)
    one = np.asarray(result.poses.valid) & ((members >= 0).sum(-1) == 1)
    f, g = np.nonzero(one)
    cameras = np.argmax(members[f, g] >= 0, axis=-1)
    return list(zip(f.tolist(), g.tolist(), cameras.tolist(), strict=True))


def moved_to_standing_height(
    result: PoseResults,
    centres: np.ndarray,
    up: np.ndarray,
    floor_height: float,
    layout: str,
    max_tilt_deg: float,
) -> tuple[np.ndarray, int]:
    """The result's xyz (F, G, K, 3) with its upright one-view people moved along their camera's
    ray to a standing mid-shoulder height, and how many were moved. ``centres`` (C, 3) metres;
    ``up`` (3,) unit."""
    lay = get_layout(layout)
    rs, ls, rh, lh = (lay.index(n) for n in ("r_shoulder", "l_shoulder", "r_hip", "l_hip"))
    xyz = np.asarray(result.poses.xyz, np.float64)
    ok = np.asarray(result.poses.keypoint_valid)
    out, moved = xyz.copy(), 0
    for f, g, camera in one_view_people(result):
        k = ok[f, g]
        if not (k[rs] and k[ls] and k[rh] and k[lh]):
            continue
        shoulders = xyz[f, g, [rs, ls]].mean(0)
        torso = shoulders - xyz[f, g, [rh, lh]].mean(0)
        cos_tilt = torso @ up / max(np.linalg.norm(torso), 1e-9)
        if cos_tilt < np.cos(np.radians(max_tilt_deg)):
            continue
        centre = centres[camera]
        ray = shoulders - centre
        if abs(ray @ up) < 1e-6:
            continue
        t = (floor_height + STANDING_SHOULDER_HEIGHT_M - centre @ up) / (ray @ up)
        if not MOVE_FACTORS[0] < t < MOVE_FACTORS[1]:
            continue
        out[f, g] += (t - 1.0) * ray
        moved += 1
    return out, moved


def scores(result: PoseResults, xyz: np.ndarray, data) -> dict:
    """The MVOR protocol's overall numbers and the one-view people's, with ``xyz`` as the poses."""
    poses = result.poses._replace(xyz=xyz)
    overall = evaluate(poses_to_joints(poses, data.layout), data)["overall"]
    by_views = error_by_views(dataclasses.replace(result, poses=poses), data)
    return {
        "missed": overall["missed"],
        "people": overall["people"],
        "mpjpe_mm": overall["mpjpe_mm"],
        "pck3d_150": overall["pck3d_150"],
        "one_view": by_views["1"],
    }


def diagnostics(
    result: PoseResults, moved: np.ndarray, data, members, centres, up, floor_height
) -> dict:
    """Where the true groups' one-view people are, and where the estimator puts them (as lifted,
    and ``moved`` (F, G, K, 3), its xyz after a move)."""
    gt_xyz, gt_ok = np.asarray(data.gt.xyz), np.asarray(data.gt.keypoint_valid)
    gt_valid = np.asarray(data.gt.valid)
    ls, rs = JOINTS.index("l_shoulder"), JOINTS.index("r_shoulder")
    lay = get_layout(data.layout)
    prs, pls = lay.index("r_shoulder"), lay.index("l_shoulder")
    true_views = (members >= 0).sum(-1)  # (F, H)
    pct = (10, 25, 50, 75, 90)
    out = {"percentiles": list(pct), "truth_shoulder_height_m": {}}
    both = gt_valid & gt_ok[..., ls] & gt_ok[..., rs]
    for key, sel in (("0", true_views == 0), ("1", true_views == 1), ("2+", true_views >= 2)):
        h = gt_xyz[both & sel][:, [ls, rs]].mean(1) @ up - floor_height
        out["truth_shoulder_height_m"][key] = {"n": len(h), "values": _pct(h, pct)}
    xyz, ok = np.asarray(result.poses.xyz), np.asarray(result.poses.keypoint_valid)
    angle, depth_ratio, elevation, height, error, error_moved = [], [], [], [], [], []
    for f, g, camera in one_view_people(result):
        # True groups: group g is true person g.
        if not (both[f, g] and ok[f, g, prs] and ok[f, g, pls]):
            continue
        centre = centres[camera]
        lifted = xyz[f, g, [prs, pls]].mean(0) - centre
        truth = gt_xyz[f, g, [ls, rs]].mean(0) - centre
        cos = lifted @ truth / np.linalg.norm(lifted) / np.linalg.norm(truth)
        angle.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        depth_ratio.append(np.linalg.norm(lifted) / np.linalg.norm(truth))
        elevation.append(np.degrees(np.arcsin(-(lifted @ up) / np.linalg.norm(lifted))))
        height.append((centre + lifted) @ up - floor_height)
        error.append(np.linalg.norm(lifted - truth))
        error_moved.append(np.linalg.norm(moved[f, g, [prs, pls]].mean(0) - centre - truth))
    out["one_view_people"] = len(angle)
    out["ray_angle_lifted_vs_truth_deg"] = _pct(angle, pct)
    out["depth_lifted_over_truth"] = _pct(depth_ratio, pct)
    out["ray_below_horizontal_deg"] = _pct(elevation, pct)
    out["lifted_shoulder_height_m"] = _pct(height, pct)
    out["shoulder_error_m"] = _pct(error, pct)
    out["shoulder_error_moved_m"] = _pct(error_moved, pct)
    return out


def _pct(values, pct) -> list[float]:
    return [round(float(v), 3) for v in np.percentile(values, pct)] if len(values) else []


def run(data, models_dir: Path | None = None) -> dict:
    """The report; ``models_dir``: `experiments.real`'s models folder for the ``infer`` default's
    rows (None: the shipped estimator's rows alone)."""
    identity = true_identity(data)
    members = members_from_identity(identity, data.gt.valid.shape[1])
    floor = estimate_floor_from_detections(data.rig, data.detections, layout=data.layout)
    up = np.asarray(floor.up, np.float64)
    centres = np.asarray(camera_centres(data.rig), np.float64)
    shipped = {"method": "blend", "estimator": load_estimator(PRETRAINED, data.rig)}
    variants = [(g, g, shipped) for g in GROUPINGS]
    if models_dir is not None:
        models = synthetic_models(data.rig, floor, models_dir / "mvor-synthetic", smoke=False)
        variants.append(("infer default", "combined", model_settings("combined", "blend", models)))
    rows, diag = {}, None
    for label, grouping, settings in variants:
        settings = settings | {"min_views": 1}
        result = pipeline_result(data, grouping, settings, identity, members)
        xyz = np.asarray(result.poses.xyz, np.float64)
        rows[f"{label}, as lifted"] = scores(result, xyz, data) | {"moved": 0}
        for tilt in MAX_TILTS_DEG:
            moved, n = moved_to_standing_height(
                result, centres, up, floor.height, data.layout, tilt
            )
            rows[f"{label}, moved (torso within {tilt:g} deg)"] = scores(result, moved, data) | {
                "moved": n
            }
            if grouping == "true" and tilt == DIAGNOSED_TILT_DEG:
                diag = diagnostics(result, moved, data, members, centres, up, floor.height)
    return {
        "split": SPLIT,
        "estimator": PRETRAINED,
        "models": None if models_dir is None else str(models_dir / "mvor-synthetic"),
        "floor": {"height_m": floor.height, "basis": floor.basis, "spread_m": floor.spread},
        "standing_shoulder_height_m": STANDING_SHOULDER_HEIGHT_M,
        "rows": rows,
        "diagnostics": diag,
    }


def markdown(report: dict) -> str:
    fl = report["floor"]
    lines = [
        "# One-view people at a standing shoulder height (MVOR days 1-2)",
        "",
        f"Split: {report['split']}. Blend, min_views 1; the true and epipolar rows with the "
        f"shipped estimator, the `infer` default's with the rig's pair ({report['models']}). Floor {fl['height_m']:.3f} m ({fl['basis']}); standing mid-shoulder "
        f"{report['standing_shoulder_height_m']:.2f} m above it.",
        "",
        "| row | moved | missed / people | MPJPE mm | PCK3D@150 % | one view: built / matched "
        "| MPJPE mm | PCK3D@150 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in report["rows"].items():
        one = r["one_view"]
        lines.append(
            f"| {name} | {r['moved']} | {r['missed']} / {r['people']} | {r['mpjpe_mm']:.1f} "
            f"| {r['pck3d_150']:.1f} | {one['predicted']} / {one['matched']} "
            f"| {one['mpjpe_mm']:.1f} | {one['pck3d_150']:.1f} |"
        )
    d = report["diagnostics"]
    pct = "/".join(str(p) for p in d["percentiles"])
    lines += ["", f"Diagnostics, true groups (percentiles {pct}):", ""]
    for key, h in d["truth_shoulder_height_m"].items():
        lines.append(
            f"- truth's shoulder height above the floor, people {key} views see "
            f"(n = {h['n']}): {h['values']} m"
        )
    lines += [
        f"- one-view people with both shoulders: {d['one_view_people']}",
        f"- angle between the camera's rays to the lifted and the true mid-shoulder: "
        f"{d['ray_angle_lifted_vs_truth_deg']} deg",
        f"- lifted depth / true depth: {d['depth_lifted_over_truth']}",
        f"- the ray below the horizontal: {d['ray_below_horizontal_deg']} deg",
        f"- the lifted mid-shoulder's height above the floor: {d['lifted_shoulder_height_m']} m",
        f"- the mid-shoulder's distance to the truth, as lifted: {d['shoulder_error_m']} m; moved "
        f"(torso within {DIAGNOSED_TILT_DEG:g} deg): {d['shoulder_error_moved_m']} m",
        "",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for the report")
    p.add_argument("--data", type=Path, default=DEFAULT_ROOT, help="MVOR days 1-2")
    p.add_argument(
        "--models",
        type=Path,
        help="experiments.real's models folder: adds the infer default's rows with its MVOR pair "
        "(trained there where missing)",
    )
    args = p.parse_args(argv)
    start = time.perf_counter()
    report = run(load_mvor(args.data), args.models)
    report["seconds"] = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    text = markdown(report)
    atomic_write_text(args.out / "one_view_height.json", report_json(report))
    atomic_write_text(args.out / "one_view_height.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
