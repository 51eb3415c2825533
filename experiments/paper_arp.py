"""paper-arp: the paper's Tables 4 and 7 on the ``arplab6`` rig.

Matchers for the robot's 2 cameras and all 6; estimators M_1/6, M_2/6, M_6/6, M_2/2 (inference
cameras: the robot's), with the reprojection error per camera (mean / median) of each model's
people, on the true skeleton groups (the 3D stage alone) and grouped by the 6-view proposals (the
whole pipeline); plus their MPJPE against the synthetic ground truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments.config import SPLITS, Scale
from experiments.data import Data, make_data, make_scenes, true_members
from experiments.figures import training_curves
from experiments.fitting import fit_estimator, fit_matcher, free_compiled_programs
from experiments.matching import matching_rows, matching_table
from experiments.paper import PAPER_TABLE4, PAPER_TABLE7, ROBOT
from experiments.records import run_record, save_partial
from experiments.tables import mean_sd, seeds_line
from mvpose_jax.cameras import up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import estimate_grouped, group_people
from mvpose_jax.metrics import pose_metrics, reprojection_errors


def run(
    sc: Scale, seeds: list[int], data_seed: int, out: Path, progress: bool
) -> tuple[list[dict], list[str]]:
    """The experiment at scale ``sc`` for each training seed on the scenes of ``data_seed``.

    Returns: (one record per training seed, the lines of tables.md after its head).
    """
    rig = load_rig("arplab6")
    scenes = make_scenes(rig, sc, data_seed)
    runs = []
    models = {
        "M_1/6": (rig.names, ROBOT[:1]),
        "M_2/6": (rig.names, ROBOT),
        "M_6/6": (rig.names, rig.names),
        "M_2/2": (ROBOT, ROBOT),
    }
    for i, seed in enumerate(seeds):
        free_compiled_programs()  # the last seed's evaluation programs
        data = make_data(rig, scenes, sc, seed, progress)
        res = run_record(seed, data_seed, sc) | {
            "matching": {s: {} for s in SPLITS},
            "training": {},
        }
        matchers = {}
        for n, cams in ((2, ROBOT), (6, rig.names)):
            print(f"== seed {seed}: matcher, {n} views", flush=True)
            matchers[n], fit = fit_matcher(data, sc, cams, seed, progress)
            res["training"][f"matcher-{n}"] = fit
            for split in SPLITS:
                res["matching"][split][str(n)] = matching_rows(data, split, matchers[n], cams, fit)
        estimators = {}
        for name, (train_cams, infer_cams) in models.items():
            print(f"== seed {seed}: estimator {name}", flush=True)
            estimators[name], res["training"][f"estimator {name}"] = fit_estimator(
                data, sc, train_cams, infer_cams, seed, progress
            )
        print(f"== seed {seed}: evaluating", flush=True)
        res["camera_subsets"] = arp_rows(data, "test", matchers[6], estimators, "true")
        res["camera_subsets_proposals"] = arp_rows(
            data,
            "test",
            matchers[6],
            estimators,
            "proposals",
            res["training"]["matcher-6"]["threshold"],
        )
        if i == 0:
            res["figures"] = [training_curves(res["training"], out / "figures")]
        runs.append(res)
        save_partial(runs, out)
    return runs, tables(runs)


def tables(runs: list[dict]) -> list[str]:
    """Tables 4 and 7 (test scenes), then matching on validation scenes."""
    lines = ["## Test scenes (the reported results; read only for these tables)", ""]
    lines += matching_table(
        runs, "test", PAPER_TABLE4, "Matching (Table 4): arplab6, test scenes with 1-8 people"
    )
    lines += arp_table(runs, "camera_subsets", "true skeleton groups (the 3D stage alone)")
    lines += arp_table(
        runs,
        "camera_subsets_proposals",
        "grouped by the 6-view GAT proposals (whole pipeline)",
        paper=False,
    )
    lines += ["## Validation scenes (where settings are chosen)", ""]
    lines += matching_table(
        runs, "validation", PAPER_TABLE4, "Matching: arplab6, validation scenes with 1-8 people"
    )
    return lines


def arp_rows(
    data: Data,
    split: str,
    matcher6,
    estimators: dict,
    grouping: str = "true",
    threshold: float = 0.5,
) -> dict:
    """Table 7: each model's people reprojected into every camera.

    grouping: "true" (the true skeleton groups, so that only the 3D stage is measured) or
    "proposals" (grouped by the 6-view matcher, the whole pipeline).
    """
    rig = data.rig
    det, ident, gt, ids = data.detections(split, rig.names)
    if grouping == "true":
        members = true_members(ident, gt.valid.shape[1], min_views=1)
    else:
        members = run_pipeline(
            rig,
            det,
            matcher=matcher6,
            estimator=estimators["M_6/6"],
            proposals="gat",
            threshold=threshold,
        ).members
    p_xy, p_sc = group_people(det.xy, det.score, members)
    out = {}
    for name, est in estimators.items():
        idx = [rig.names.index(c) for c in est.rig_infer.names]
        poses, conf = estimate_grouped(est, p_xy[:, :, idx], p_sc[:, :, idx], min_views=1)
        v = poses.valid
        errors = reprojection_errors(rig, poses.xyz[v], poses.keypoint_valid[v], p_xy[v], p_sc[v])
        m = pose_metrics(poses, gt, confidence=conf, up=up_vector(rig), person_ids=ids)
        out[name] = {
            "people": int(v.sum()),
            "reprojection": errors,
            "mpjpe_mm": round(m["mpjpe_mm"], 3),
            "pcp": round(m["pcp"], 3),
        }
    return out


def arp_table(runs: list[dict], key: str, grouping: str, paper: bool = True) -> list[str]:
    """Table 7 from the runs' ``key`` rows (`arp_rows`), with the paper's beside it (``paper``)."""
    first = runs[0][key]
    cams = list(next(iter(first.values()))["reprojection"])
    lines = [
        f"### Camera subsets (Table 7): reprojection error per camera, px, mean / median; {grouping}; test scenes",
        "",
        seeds_line(runs),
        "",
        "| model | people | " + " | ".join(cams) + " | MPJPE mm | PCP |",
        "|---|---|" + "---|" * len(cams) + "---|---|",
    ]
    for name in first:
        cells = [
            f"{mean_sd(runs, (key, name, 'reprojection', c, 'mean'), 1)} / {mean_sd(runs, (key, name, 'reprojection', c, 'median'), 1)}"
            for c in cams
        ]
        lines.append(
            f"| {name} | {mean_sd(runs, (key, name, 'people'), 0)} | "
            + " | ".join(cells)
            + f" | {mean_sd(runs, (key, name, 'mpjpe_mm'), 1)} | {mean_sd(runs, (key, name, 'pcp'), 1)} |"
        )
    if paper:
        lines += [
            "",
            "Paper (ARP Laboratory, cameras W0-W3 walls, R0-R1 robot; reference numbers, not ours):",
            "",
            "| model | W0 | W1 | W2 | W3 | R0 | R1 |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, v in PAPER_TABLE7.items():
            lines.append(f"| {name} | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in v) + " |")
    wall = [c for c in cams if c not in ROBOT]
    lines.append("")
    for stat in ("median", "mean"):
        r26 = [np.mean([r[key]["M_2/6"]["reprojection"][c][stat] for c in wall]) for r in runs]
        r22 = [np.mean([r[key]["M_2/2"]["reprojection"][c][stat] for c in wall]) for r in runs]
        ratio = np.array(r22) / np.array(r26)
        lines += [
            f"Wall cameras, mean of {stat}s: M_2/6 {np.mean(r26):.1f} px, M_2/2 {np.mean(r22):.1f} px "
            f"({ratio.mean():.2f}x; per seed {', '.join(f'{x:.2f}' for x in ratio)}).",
            "",
        ]
    return lines
