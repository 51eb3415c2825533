"""Proposals: skeletons grouped into people from scored cross-view pairs, and their settings.

`propose_people` is the paper's proposal step (DESIGN.md §1.2): pairs above a threshold, best
first, joined by a union-find that never puts two skeletons of one camera in one person. Its
settings are chosen here by one rule for every matcher: the best per-frame adjusted Rand index
on labelled frames (in practice, frames composed from held-out single-person recordings):
`choose_proposal_threshold` for the GAT, `choose_geometric_cutoff` for the epipolar matcher. The
chosen GAT threshold travels beside the checkpoint (`write_proposal_threshold`,
`read_proposal_threshold`). Host-side numpy; no model here.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.errors import InputError
from mvpose_jax.metrics import matching_scores


class Proposals(NamedTuple):
    """People proposed in F frames of C views (P skeletons per view, padded)."""

    identity: (
        np.ndarray
    )  # (F, C, P) int32: the person (0.. within its frame) of each skeleton, -1 none
    people: list[
        np.ndarray
    ]  # per frame (num_people, C) int32: each person's skeleton per view, -1 none


def propose_people(
    rows: np.ndarray,
    scores: np.ndarray,
    count: np.ndarray,
    *,
    num_skeletons: int | None = None,
    threshold: float = 0.5,
    min_views: int = 2,
) -> Proposals:
    """Groups skeletons into people from scored cross-view pairs (DESIGN.md §1.2).

    Pairs scoring above ``threshold`` are taken best first; each joins its two skeletons' groups
    unless the joined group would hold two skeletons of one camera. A person is a group of at
    least ``min_views`` skeletons. With a single camera every skeleton is its own person.

    Args:
      rows: (M, 5) int ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]``.
      scores: (M,) pair scores.
      count: (F, C) skeletons per view.
      num_skeletons: P, the padded skeleton axis of the output (default ``count.max()``).
    Returns:
      `Proposals`.
    """
    count = np.asarray(count)
    F, C = count.shape
    P = max(1, int(count.max(initial=0)) if num_skeletons is None else num_skeletons)
    if C > 62:
        raise InputError("proposals support at most 62 cameras", field="cameras")
    ok = np.arange(P)[None, None] < count[..., None]  # (F, C, P)
    n = F * C * P
    rows = np.asarray(rows, np.int64).reshape(-1, 5)
    scores = np.asarray(scores).reshape(-1)
    if C == 1:
        parent = np.arange(n)
    else:
        keep = scores > threshold
        rows, scores = rows[keep], scores[keep]
        order = np.argsort(-scores, kind="stable")
        a = ((rows[order, 0] * C + rows[order, 1]) * P + rows[order, 2]).tolist()
        b = ((rows[order, 0] * C + rows[order, 3]) * P + rows[order, 4]).tolist()
        parent = union_find_exclusive(n, a, b, np.tile(np.repeat(np.arange(C), P), F))
    return _proposals_from_roots(parent.reshape(F, C, P), ok, 1 if C == 1 else min_views)


def union_find_exclusive(
    num_items: int, a: list[int], b: list[int], group: np.ndarray
) -> np.ndarray:
    """Greedy union-find that never joins two items of the same group (camera).

    Args:
      num_items: items 0..n-1.
      a, b: the pairs to join, in order (best first).
      group: (n,) int in 0..62, the camera of each item.
    Returns:
      (n,) the root of every item's set.
    """
    parent = list(range(num_items))
    cams = [1 << int(g) for g in np.asarray(group).tolist()]  # camera bitmask of each root

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:  # path compression
            parent[x], x = root, parent[x]
        return root

    for x, y in zip(a, b, strict=True):
        rx, ry = find(x), find(y)
        if rx == ry or cams[rx] & cams[ry]:
            continue
        if rx > ry:
            rx, ry = ry, rx
        parent[ry] = rx
        cams[rx] |= cams[ry]
    return np.array([find(x) for x in range(num_items)], np.int64)


def _proposals_from_roots(root: np.ndarray, ok: np.ndarray, min_views: int) -> Proposals:
    F, C, P = ok.shape
    flat_root = np.where(ok, root, -1).reshape(-1)
    size = np.bincount(flat_root[flat_root >= 0], minlength=F * C * P)
    person = ok.reshape(-1) & (size[np.maximum(flat_root, 0)] >= min_views)
    identity = np.full(F * C * P, -1, np.int64)
    frame = np.arange(F * C * P) // (C * P)
    # Number each frame's people 0.. in the order of their first skeleton (camera, then index).
    key = frame[person] * (F * C * P) + flat_root[person]
    uniq, inverse = np.unique(key, return_inverse=True)
    first_of_frame = np.searchsorted(uniq // (F * C * P), np.arange(F))
    identity[person] = inverse - first_of_frame[frame[person]]
    identity = identity.reshape(F, C, P).astype(np.int32)
    num = np.bincount(uniq // (F * C * P), minlength=F)
    table = np.full((F, max(1, int(num.max(initial=0))), C), -1, np.int32)
    f_i, c_i, p_i = np.nonzero(identity >= 0)
    table[f_i, identity[f_i, c_i, p_i], c_i] = p_i
    return Proposals(identity, [table[f, : num[f]] for f in range(F)])


PROPOSAL_THRESHOLDS = (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def choose_proposal_threshold(
    rows: np.ndarray,
    scores: np.ndarray,
    identity: np.ndarray,
    count: np.ndarray,
    *,
    thresholds: tuple[float, ...] = PROPOSAL_THRESHOLDS,
    min_views: int = 2,
) -> tuple[float, dict[float, float]]:
    """The proposal threshold with the best (per-frame) adjusted Rand index on labelled frames.

    Meant for frames composed from held-out single-person recordings
    (`inference.composed_match_table`): the proposal step's exclusivity (one skeleton per camera
    per person) already rejects most wrong pairs, so the best threshold is often well below the
    paper's 0.5, and the network's scores, fitted to 0/1 labels, need not be calibrated for it.
    Ties go to the threshold nearest 0.5.

    Args:
      rows (M, 5), scores (M,): scored pairs; identity (F, C, P): true person of each skeleton
        (-1 false detection); count (F, C).
    Returns:
      (the threshold, {threshold: ARI}).
    """
    ari = _ari_by_threshold(rows, scores, identity, count, thresholds, min_views)
    best = max(ari, key=lambda th: (round(ari[th], 6), -abs(th - 0.5)))
    return best, ari


GEOMETRIC_CUTOFFS_PX = (
    4.0,
    6.0,
    8.0,
    10.0,
    12.0,
    15.0,
    20.0,
    25.0,
    30.0,
    40.0,
    50.0,
    60.0,
    80.0,
    100.0,
)


def choose_geometric_cutoff(
    rows: np.ndarray,
    distances_px: np.ndarray,
    identity: np.ndarray,
    count: np.ndarray,
    *,
    cutoffs_px: tuple[float, ...] = GEOMETRIC_CUTOFFS_PX,
    prefer_px: float = 30.0,
    min_views: int = 2,
) -> tuple[float, dict[float, float]]:
    """The epipolar matcher's setting, chosen by the GAT threshold's rule (best per-frame ARI).

    The epipolar matcher's score ``2^(-d / half_score_px)`` orders pairs by their distance d
    whatever ``half_score_px``, so with the proposal threshold it has one effective setting: the
    distance under which a pair may join (``half_score_px`` at threshold 0.5). Ties go to the
    cutoff nearest ``prefer_px`` (the pipeline's default).

    Args:
      rows (M, 5), distances_px (M,): `inference.epipolar_match_distances` of composed frames;
        identity (F, C, P), count (F, C): their truth.
    Returns:
      (the cutoff in pixels, {cutoff: ARI}).
    """
    d = np.asarray(distances_px, np.float64)
    # score > threshold  <=>  -d > -cutoff  <=>  d < cutoff; best first = nearest first.
    by_neg = _ari_by_threshold(rows, -d, identity, count, tuple(-c for c in cutoffs_px), min_views)
    ari = {-k: v for k, v in by_neg.items()}
    best = max(ari, key=lambda c: (round(ari[c], 6), -abs(c - prefer_px)))
    return best, ari


def _ari_by_threshold(rows, scores, identity, count, thresholds, min_views) -> dict[float, float]:
    count = np.asarray(count)
    P = np.shape(identity)[2]
    ari = {}
    for th in thresholds:
        pred = propose_people(
            rows, scores, count, num_skeletons=P, threshold=th, min_views=min_views
        )
        ari[float(th)] = matching_scores(identity, pred.identity, count)["ari"]
    return ari


PROPOSAL_THRESHOLD_FILE = "proposal_threshold.json"


def write_proposal_threshold(
    folder: str | os.PathLike, threshold: float, ari: dict[float, float], composed_frames: int
) -> Path:
    """Writes a matcher's chosen threshold beside its checkpoints (`PROPOSAL_THRESHOLD_FILE`)."""
    record = {
        "threshold": threshold,
        "ari_by_threshold": {str(k): round(v, 6) for k, v in ari.items()},
        "composed_frames": int(composed_frames),
        "how": "the best per-frame adjusted Rand index of the proposals on multi-person frames composed "
        "from the dev recordings (inference.choose_matcher_threshold)",
    }
    path = Path(folder) / PROPOSAL_THRESHOLD_FILE
    atomic_write_text(path, json.dumps(record, indent=1) + "\n")
    return path


def read_proposal_threshold(folder: str | os.PathLike | None, given: float | None = None) -> float:
    """The proposal threshold: ``given``, else the matcher folder's chosen one, else the paper's 0.5."""
    if given is not None:
        return given
    path = Path(folder) / PROPOSAL_THRESHOLD_FILE if folder else None
    if path is None or not path.exists():
        return 0.5
    try:
        return float(json.loads(path.read_text())["threshold"])
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(
            f"unreadable proposal threshold ({e})", file=path, field="threshold"
        ) from e
