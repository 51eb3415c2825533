"""The experiments' figures: 3D skeletons of sample frames and the training curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvpose_jax.metrics import match_people
from mvpose_jax.render import curves_figure, save_figure, skeleton_figure
from mvpose_jax.skeletons import Poses3D, evaluation_keypoints


def sample_figures(samples: dict, rig, layout: str, out: Path, count: int = 2) -> list[str]:
    """3D skeletons of sample frames (D-detected): ground truth, ours and triangulation side by side.

    Picks the frame with the most people where triangulation is incomplete for someone (the
    paper's Figure 7) and the frame with the most people where it is complete (Figure 6)."""
    gt = samples["detected"]["gt"]
    source = "pipeline"
    ours, tri = samples["detected"][source]
    if (
        not ours.poses.valid.any()
    ):  # a matcher that proposes nobody (e.g. smoke runs): show the stage alone
        source = "true groupings"
        ours, tri = samples["detected"][source]
    people = ours.poses.valid.sum(-1)
    incomplete = (tri.valid[..., None] & ~tri.keypoint_valid).any(-1).any(-1) | (
        ours.poses.valid & ~tri.valid
    ).any(-1)
    picks = []
    for want in (True, False):
        cand = np.nonzero((incomplete == want) & (people > 0))[0]
        if len(cand):
            picks.append(int(cand[np.argmax(people[cand])]))
    written = []
    for f in picks[:count]:
        g_list = np.flatnonzero(gt.valid[f])
        panels = {
            "ground truth": (gt.xyz[f][g_list], gt.keypoint_valid[f][g_list]),
            "ours": _in_gt_order(ours.poses, gt, f, g_list, layout),
            "triangulation": _in_gt_order(tri, gt, f, g_list, layout),
        }
        fig = skeleton_figure(
            panels, layout, rig=rig, title=f"test frame {f} (D-detected, {source})"
        )
        written.append(str(save_figure(fig, out / f"frame_{f:05d}.png")))
    return written


def _in_gt_order(pred: Poses3D, gt: Poses3D, f: int, g_list: np.ndarray, layout: str):
    """Frame f's predicted people reordered so that the one assigned to ground-truth person
    ``g_list[i]`` (minimum-total-error assignment) comes i-th, and so gets that person's colour;
    unassigned predictions follow."""
    one = lambda p: Poses3D(*(np.asarray(a)[f : f + 1] for a in p))  # noqa: E731
    p_idx, g_idx = match_people(one(pred), one(gt), evaluation_keypoints(layout))[0]
    K = pred.xyz.shape[2]
    order = [int(p_idx[g_idx == g][0]) if (g_idx == g).any() else -1 for g in g_list]
    order += [int(p) for p in np.flatnonzero(pred.valid[f]) if p not in set(p_idx.tolist())]
    if not order:
        return np.zeros((0, K, 3), np.float32), np.zeros((0, K), bool)
    xyz = np.stack([pred.xyz[f, p] if p >= 0 else np.zeros((K, 3), np.float32) for p in order])
    kv = np.stack(
        [
            pred.keypoint_valid[f, p] & pred.valid[f, p] if p >= 0 else np.zeros(K, bool)
            for p in order
        ]
    )
    return xyz, kv


def training_curves(training: dict, folder: Path) -> str:
    """The training curves of every model of a run (its ``training`` record) as one figure."""
    fig = curves_figure({k: v["history"] for k, v in training.items() if v["history"]})
    return str(save_figure(fig, folder / "training_curves.png"))
