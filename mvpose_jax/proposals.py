"""Proposals: skeletons grouped into people from scored cross-view pairs, and their settings.

`propose_people` is the paper's proposal step (DESIGN.md §1.2): pairs above a threshold, best
first, joined by a union-find that never puts two skeletons of one camera in one person. Its
settings are chosen here by one rule for every matcher: the best per-frame adjusted Rand index
on labelled frames (in practice, frames composed from held-out single-person recordings):
`choose_proposal_threshold` for the GAT, `choose_geometric_cutoff` for the epipolar matcher,
`choose_combined_threshold` for the combined matcher. The chosen settings travel in the
matcher's folder, which `trained.ModelFolder` writes and reads (`write_proposal_settings`,
`read_proposal_threshold`, `read_combined_config`).

The combined matcher (`propose_combined`, issue 19) joins the GAT's decisions with epipolar
geometry so that it does not lose to the epipolar matcher where the GAT meets data it was not
trained on (a floor 0.6 m off: GAT ARI 0.20, epipolar 0.998 on the validation scenes):

1. Pair score ``w * s_gat * [d < cutoff] + (1 - w) * 2^(-d / half_score_px)`` (d: the pair's
   symmetric epipolar distance, `combined_pair_distances`: the mean over the keypoints both
   views see, or the median where that is smaller and enough keypoints are shared, so that a
   skeleton carrying another person's limb, as bottom-up detectors make them, still joins its
   person). Geometry carries most of the weight; the GAT moves the distance
   under which a pair may join (with w = 0.2, threshold 0.2: from 40 px for s_gat = 0 to 100 px
   for s_gat = 1) and orders near-ties. The gate: the GAT counts only for pairs the epipolar
   matcher itself could join (d under its cutoff), so the network alone never joins a
   geometrically impossible pair, or one the geometry cannot judge (fewer than 3 shared
   keypoints).
2. Per frame, a label-free check: the combined grouping and the epipolar matcher's are scored by
   their geometric consistency (`grouping_consistency`: every pair of skeletons put into one
   person adds ``cutoff - min(d_median, 1.5 cutoff)``, so consistent joins count for a grouping
   and fewer, larger people are preferred while their views agree); the frame keeps the better
   one (ties: the combined). This is what keeps the combined matcher from falling below the
   epipolar one where the network is confidently wrong.

Host-side numpy; no model here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import numba
import numpy as np

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
    repair_splits: bool = False,
    drop_duplicates: bool = False,
) -> Proposals:
    """Groups skeletons into people from scored cross-view pairs (DESIGN.md §1.2).

    Pairs scoring above ``threshold`` are taken best first; each joins its two skeletons' groups
    unless the joined group would hold two skeletons of one camera. A person is a group of at
    least ``min_views`` skeletons. With a single camera every skeleton is its own person.

    ``repair_splits``: a bottom-up detector reports some people twice in a view (a duplicate, or
    a fragment beside the whole skeleton); the greedy pass then splits that person into two
    groups that both hold a skeleton of that camera, each taking some of the other views. Two
    groups that share exactly one camera and are joined by at least two pairs above the
    threshold, at least half of the pairs they could have across cameras, and whose two skeletons
    of the shared camera both score above the threshold on average with the other views, are one
    person: they are merged, keeping in the shared camera the skeleton with the better mean pair
    score to the other views (the other is left out, as a false positive is), unless a pair of
    the merged person's skeletons scores under `SPLIT_VETO_FRACTION` of the threshold (two
    people). One pass, most links first.

    ``drop_duplicates``: when a person is reported twice in several views, the duplicates can
    also form a person of their own, a ghost beside the real one in 3D. A person whose cameras
    all belong to another person with more skeletons (as many: the one whose own pairs score
    lower), joined to it by pairs above the threshold for at least half of the pairs they have
    across cameras and by none under `SPLIT_VETO_FRACTION` of the threshold, is such a ghost
    (two people can share a camera set, but not stand where each other's views agree): its
    skeletons are left out (`_drop_duplicates_frame`). After the split repair.

    Args:
      rows: (M, 5) int ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]``.
      scores: (M,) pair scores.
      count: (F, C) skeletons per view.
      num_skeletons: P, the padded skeleton axis of the output (default ``count.max()``).
    Returns:
      `Proposals`.
    """
    count, ok = _skeleton_slots(count, num_skeletons)
    F, C, P = ok.shape
    if C == 1:
        return _proposals_from_roots(np.arange(F * C * P).reshape(F, C, P), ok, 1)
    scores = np.asarray(scores).reshape(-1)
    keep = np.nonzero(scores > threshold)[0]  # in the scores' own precision
    joins = keep[np.argsort(-scores[keep], kind="stable")]  # best first
    scores = np.ascontiguousarray(scores, np.float64)
    pair_items, a, b, root = _joined(
        np.ascontiguousarray(rows, np.int64).reshape(-1, 5), joins, F, C, P
    )
    if repair_splits or drop_duplicates:  # they read every scored pair, not only the joins
        root = _repaired_roots(
            root,
            a,
            b,
            scores[joins],
            pair_items,
            scores,
            float(threshold),
            # The Python float product, as the rule was tuned.
            float(SPLIT_VETO_FRACTION * threshold),
            C,
            P,
            min_views,
            repair_splits,
            drop_duplicates,
        )
    return _proposals_from_roots(root.reshape(F, C, P), ok, min_views)


# Compiled: a live frame's grouping was about 30 numpy calls around three compiled ones, twice a
# frame for the combined matcher (its grouping and the epipolar one). Three flat calls, not one
# that calls the others: numba optimises a caller with all its callees again, and compiling on a
# fresh install took seconds longer.
@numba.njit(cache=True)
def _joined(rows, joins, F, C, P):
    """The union-find of `propose_people`: rows (M, 5), joins (J,) the rows joined, best first.
    Returns every pair's two items (M, 2) (flat (frame, camera, skeleton) indices), the joins'
    items a, b (J,) and each item's root (F * C * P,)."""
    pair_items = np.empty((len(rows), 2), np.int64)
    for m in range(len(rows)):
        pair_items[m, 0] = (rows[m, 0] * C + rows[m, 1]) * P + rows[m, 2]
        pair_items[m, 1] = (rows[m, 0] * C + rows[m, 3]) * P + rows[m, 4]
    a = np.empty(len(joins), np.int64)
    b = np.empty(len(joins), np.int64)
    for k in range(len(joins)):
        a[k], b[k] = pair_items[joins[k], 0], pair_items[joins[k], 1]
    n = F * C * P
    camera = np.empty(n, np.int64)
    for i in range(n):
        camera[i] = i // P % C
    return pair_items, a, b, _union_find_exclusive(n, a, b, camera)


@numba.njit(cache=True)
def _people_table(root, ok, C, P, min_views):
    """`_proposals_from_roots`'s arrays from flat (F * C * P,) roots and slots: the identity
    (F * C * P,) int32, the people's table (F, people, C) int32 and the people per frame (F,)."""
    per_frame = C * P
    F = len(ok) // per_frame
    identity, num = _identity_from_roots(root, ok, F, per_frame, min_views)
    most = 1
    for f in range(F):
        most = max(most, num[f])
    table = np.full((F, most, C), -1, np.int32)
    for i in range(len(ok)):
        if identity[i] >= 0:
            table[i // per_frame, identity[i], i // P % C] = i % P
    return identity, table, num


def _skeleton_slots(count: np.ndarray, num_skeletons: int | None) -> tuple[np.ndarray, np.ndarray]:
    """count (F, C) as an array and which of the P skeleton slots hold a skeleton, ok (F, C, P)
    (P: ``num_skeletons``, default ``count.max()``, at least 1). Camera sets are 64-bit masks:
    at most 62 cameras."""
    count = np.asarray(count)
    P = max(1, int(count.max(initial=0)) if num_skeletons is None else num_skeletons)
    if count.shape[1] > 62:
        raise InputError("proposals support at most 62 cameras", field="cameras")
    return count, np.arange(P)[None, None] < count[..., None]


# `propose_people`'s split repair never merges two groups with a pair between them scoring
# under this fraction of the threshold. Chosen on the domain-shift validation scenes (seed-0
# quick models, combined scores, where a pair past the epipolar cutoff scores about 0): 0.02
# and 0.1 keep the repair from merging two people on floor-0.3 (a pair 330 px apart) and give
# the same part-mixing figures; 0.3 vetoes true merges too (robust triangulation 0.05 PCP
# farther from the true groups).
SPLIT_VETO_FRACTION = 0.1


# Compiled: as Python (dicts of links, sets of cameras) the two repairs were most of the combined
# matcher's host time, about 0.25 ms a live frame. Groups never span frames, so each frame is
# repaired on its own dense (C*P, C*P) table of pair scores; the rules and their orders are the
# ones `propose_people`'s docstring states, tie for tie.
@numba.njit(cache=True)
def _repaired_roots(
    root, a, b, strength, pair_items, pair_scores, threshold, veto, C, P, min_views, repair, drop
):
    """`propose_people`'s ``repair_splits`` then ``drop_duplicates`` on a grouping: root (n,)
    each item's group (its lowest item), n = F * C * P; a, b (J,) the joining pairs' items, best
    first, strength (J,) their scores; pair_items (M, 2) and pair_scores (M,) every scored pair;
    veto: `SPLIT_VETO_FRACTION` of the threshold. Returns the new roots (a dropped skeleton, and
    a ghost's skeletons: their own)."""
    root = root.copy()
    per_frame = C * P
    F = len(root) // per_frame
    # Loops, not array expressions, here and below: numba compiles each of those into a kernel
    # of its own, and compiling was seconds on a fresh install.
    join_frame = np.empty(len(a), np.int64)
    for k in range(len(a)):
        join_frame[k] = a[k] // per_frame
    pair_frame = np.empty(len(pair_items), np.int64)
    for m in range(len(pair_items)):
        pair_frame[m] = pair_items[m, 0] // per_frame
    join_order, join_start = _by_frame(join_frame, F)
    pair_order, pair_start = _by_frame(pair_frame, F)
    r = np.empty(per_frame, np.int64)
    score = np.zeros((per_frame, per_frame))
    known = np.zeros((per_frame, per_frame), np.bool_)
    index = np.full((per_frame, per_frame), -1, np.int64)
    for f in range(F):
        if join_start[f] == join_start[f + 1]:
            continue  # nothing joins two groups here
        base = f * per_frame
        ja = np.empty(join_start[f + 1] - join_start[f], np.int64)
        jb = np.empty(len(ja), np.int64)
        js = np.empty(len(ja))
        for k in range(len(ja)):
            j = join_order[join_start[f] + k]
            ja[k], jb[k], js[k] = a[j] - base, b[j] - base, strength[j]
        # Both ways, in the pairs' order: a pair scored twice keeps its last score.
        for k in range(pair_start[f], pair_start[f + 1]):
            m = pair_order[k]
            x, y = pair_items[m, 0] - base, pair_items[m, 1] - base
            score[x, y] = pair_scores[m]
            score[y, x] = pair_scores[m]
            known[x, y] = True
            known[y, x] = True
        for i in range(per_frame):
            r[i] = root[base + i] - base
        if repair:
            r = _merge_split_frame(r, ja, jb, js, score, known, index, threshold, veto, P)
        if drop:
            r = _drop_duplicates_frame(r, ja, jb, js, score, known, index, veto, P, min_views)
        for i in range(per_frame):
            root[base + i] = r[i] + base
        for k in range(pair_start[f], pair_start[f + 1]):
            m = pair_order[k]
            x, y = pair_items[m, 0] - base, pair_items[m, 1] - base
            known[x, y] = False
            known[y, x] = False
    return root


@numba.njit(cache=True)
def _by_frame(frame, F):
    """A stable order of items by their frame (F,), and where each frame's items start (F + 1,)."""
    start = np.zeros(F + 1, np.int64)
    for f in frame:
        start[f + 1] += 1
    for f in range(F):
        start[f + 1] += start[f]
    fill = np.empty(F, np.int64)
    for f in range(F):
        fill[f] = start[f]
    order = np.empty(len(frame), np.int64)
    for i in range(len(frame)):
        order[fill[frame[i]]] = i
        fill[frame[i]] += 1
    return order, start


@numba.njit(cache=True)
def _links(r, ja, jb, js, index):
    """The pairs of distinct groups that the joins (ja, jb; scores js) link, in the order first
    linked: (lo, hi) roots, how many joins link each, and the sum of their scores in join order.
    index: (C*P, C*P) all -1, a scratch table left as it was found."""
    lo = np.empty(len(ja), np.int64)
    hi = np.empty(len(ja), np.int64)
    count = np.zeros(len(ja), np.int64)
    total = np.zeros(len(ja))
    num = 0
    for k in range(len(ja)):
        rx, ry = r[ja[k]], r[jb[k]]
        if rx == ry:
            continue
        u, v = min(rx, ry), max(rx, ry)
        if index[u, v] < 0:
            index[u, v] = num
            lo[num], hi[num] = u, v
            num += 1
        i = index[u, v]
        count[i] += 1
        total[i] += js[k]
    for i in range(num):
        index[lo[i], hi[i]] = -1
    return lo[:num], hi[:num], count[:num], total[:num]


@numba.njit(cache=True)
def _members(r, group):
    """The items of ``group`` (those whose root it is), ascending."""
    out = np.empty(len(r), np.int64)
    m = 0
    for i in range(len(r)):
        if r[i] == group:
            out[m] = i
            m += 1
    return out[:m]


@numba.njit(cache=True)
def _camera_mask(items, P):
    mask = np.int64(0)
    for x in items:
        mask |= np.int64(1) << (x // P)
    return mask


@numba.njit(cache=True)
def _merge_split_frame(r0, ja, jb, js, score, known, index, threshold, veto, P):
    """One frame of ``repair_splits``: r0 (C*P,) roots, frame-local items."""
    r = r0.copy()
    lo, hi, count, total = _links(r0, ja, jb, js, index)
    L = len(lo)
    ok = np.zeros(L, np.bool_)
    shared_camera = np.zeros(L, np.int64)
    for i in range(L):
        A, B = _members(r0, lo[i]), _members(r0, hi[i])
        shared = _camera_mask(A, P) & _camera_mask(B, P)
        possible = 0
        for x in A:
            for y in B:
                if x // P != y // P:
                    possible += 1
        one = shared != 0 and (shared & (shared - 1)) == 0
        ok[i] = one and count[i] >= 2 and count[i] >= 0.5 * possible
        if one:
            c = 0
            while not (shared >> c) & 1:
                c += 1
            shared_camera[i] = c
    mean = np.empty(L)
    for i in range(L):
        mean[i] = total[i] / count[i]
    touched = np.zeros(len(r), np.bool_)
    # Most links first, then the higher mean score, then the higher roots (`sorted(reverse=True)`
    # over (links, mean, root a, root b)).
    while True:
        best = _take_largest(ok, count, mean, lo, hi)
        if best < 0:
            break
        ra, rb, c = lo[best], hi[best], shared_camera[best]
        if touched[ra] or touched[rb]:
            continue
        A, B = _members(r0, ra), _members(r0, rb)
        group = np.empty(len(A) + len(B), np.int64)
        for k in range(len(A)):
            group[k] = A[k]
        for k in range(len(B)):
            group[len(A) + k] = B[k]
        # Each twin's mean score to the other views, over the pairs scored (Python's sum order).
        drop, drop_support, lowest = -1, 0.0, np.inf
        for x in group:
            if x // P != c:
                continue
            got, num = 0.0, 0
            for y in group:
                if y // P != c and known[x, y]:
                    got += score[x, y]
                    num += 1
            support = got / num if num else -np.inf
            lowest = min(lowest, support)
            if drop < 0 or support < drop_support or (support == drop_support and x > drop):
                drop, drop_support = x, support
        # Both twins must belong with the other views (a duplicate or fragment does; another
        # person's skeleton does not): else the groups are two people.
        if lowest <= threshold:
            continue
        # Nor may any cross-view pair of the merged person be ruled out.
        vetoed = False
        for x in A:
            for y in B:
                if x != drop and y != drop and known[x, y] and score[x, y] < veto:
                    vetoed = True
        if vetoed:
            continue
        touched[ra] = touched[rb] = True
        kept = len(r)
        for x in group:
            if x != drop:
                kept = min(kept, x)
        for x in group:
            r[x] = kept
        r[drop] = drop
    return r


@numba.njit(cache=True)
def _take_largest(ok, k1, k2, k3, k4):
    """The candidate i with ok[i] whose key (k1[i], k2[i], k3[i], k4[i]) is the largest, as
    Python orders tuples (-1: none left); it is taken (ok[i] set False)."""
    best = -1
    for i in range(len(ok)):
        if ok[i] and (
            best < 0 or _after(k1[i], k2[i], k3[i], k4[i], k1[best], k2[best], k3[best], k4[best])
        ):
            best = i
    if best >= 0:
        ok[best] = False
    return best


@numba.njit(cache=True)
def _after(a1, a2, a3, a4, b1, b2, b3, b4):
    """(a1, a2, a3, a4) > (b1, b2, b3, b4), as Python compares tuples."""
    if a1 != b1:
        return a1 > b1
    if a2 != b2:
        return a2 > b2
    if a3 != b3:
        return a3 > b3
    return a4 > b4


@numba.njit(cache=True)
def _pairwise_sum(values):
    """numpy's own summation order for float64 (``np.add.reduce``: 8 running sums in blocks of
    up to 128 values, halved above), so that a mean here is the one ``np.mean`` gives, bit for
    bit."""
    n = len(values)
    if n > 128:
        half = n // 2
        half -= half % 8
        return _pairwise_sum(values[:half]) + _pairwise_sum(values[half:])
    if n < 8:
        total = 0.0
        for v in values:
            total += v
        return total
    part = values[:8].copy()
    i = 8
    while i < n - n % 8:
        for j in range(8):
            part[j] += values[i + j]
        i += 8
    total = ((part[0] + part[1]) + (part[2] + part[3])) + (
        (part[4] + part[5]) + (part[6] + part[7])
    )
    while i < n:
        total += values[i]
        i += 1
    return total


@numba.njit(cache=True)
def _own_score(r, group, score, known):
    """The mean score of a group's pairs of items (unscored: -inf), -inf for one item."""
    items = _members(r, group)
    m = len(items)
    if m < 2:
        return -np.inf
    got = np.empty(m * (m - 1) // 2)
    k = 0
    for i in range(m):
        for j in range(i + 1, m):
            got[k] = score[items[i], items[j]] if known[items[i], items[j]] else -np.inf
            k += 1
    return _pairwise_sum(got) / len(got)


@numba.njit(cache=True)
def _drop_duplicates_frame(r0, ja, jb, js, score, known, index, veto, P, min_views):
    """One frame of ``drop_duplicates``: r0 (C*P,) roots, frame-local items."""
    r = r0.copy()
    lo, hi, count, _ = _links(r0, ja, jb, js, index)
    L = len(lo)
    host = np.empty(L, np.int64)
    ghost = np.empty(L, np.int64)
    host_size = np.zeros(L, np.int64)
    ok = np.zeros(L, np.bool_)
    for i in range(L):
        A, B = _members(r0, lo[i]), _members(r0, hi[i])
        if min(len(A), len(B)) < min_views:
            continue  # not two people
        # The host: more skeletons, then the higher own score, then the lower root.
        own_a = _own_score(r0, lo[i], score, known)
        own_b = _own_score(r0, hi[i], score, known)
        if _after(len(A), own_a, -lo[i], 0, len(B), own_b, -hi[i], 0):
            H, G = A, B
            host[i], ghost[i] = lo[i], hi[i]
        else:
            H, G = B, A
            host[i], ghost[i] = hi[i], lo[i]
        cams_h, cams_g = _camera_mask(H, P), _camera_mask(G, P)
        if cams_g & ~cams_h:
            continue
        across, vetoed = 0, False
        for x in G:
            for y in H:
                if x // P != y // P:
                    across += 1
                    if known[x, y] and score[x, y] < veto:
                        vetoed = True
        if count[i] < 0.5 * across or vetoed:
            continue
        ok[i] = True
        host_size[i] = len(H)
    dropped = np.zeros(len(r), np.bool_)
    # The largest people first (`sorted(reverse=True)` over (host size, links, host, ghost)).
    while True:
        best = _take_largest(ok, host_size, count, host, ghost)
        if best < 0:
            break
        if dropped[host[best]] or dropped[ghost[best]]:
            continue
        dropped[ghost[best]] = True
        for x in _members(r0, ghost[best]):
            r[x] = x
    return r


def propose_people_linked(
    rows: np.ndarray,
    scores: np.ndarray,
    count: np.ndarray,
    *,
    num_skeletons: int | None = None,
    threshold: float = 0.5,
    min_views: int = 2,
) -> Proposals:
    """Groups skeletons into people by average linkage over their cross-view pairs.

    `propose_people` joins two groups on the one best pair between them, so one wrong pair
    scored above the threshold can give a person's view to someone else, and one of the person's
    own pairs scored below it leaves the person split. Here every skeleton starts as its own
    group and, per frame, the two groups without a camera in common whose mean score over all
    their cross-view pairs is highest are merged, while that mean exceeds ``threshold``: a
    person's pairs are weighed together. Pairs not in ``rows`` score 0. Ties go to the groups
    of the lower skeleton indices (camera, then skeleton). A person is a group of at least
    ``min_views`` skeletons.

    Args and returns as `propose_people` (rows (M, 5), scores (M,), count (F, C)).
    Host-side numpy, a loop over frames and merges: for offline comparisons, not a hot path.
    """
    count, ok = _skeleton_slots(count, num_skeletons)
    F, C, P = ok.shape
    n = C * P
    rows = np.asarray(rows, np.int64).reshape(-1, 5)
    scores = np.asarray(scores, np.float64).reshape(-1)
    camera = np.repeat(np.arange(C), P)  # (n,) of each frame-local item
    root = np.tile(np.arange(n), (F, 1))  # (F, n)
    if C > 1:
        table = np.zeros((F, n, n))
        a, b = rows[:, 1] * P + rows[:, 2], rows[:, 3] * P + rows[:, 4]
        table[rows[:, 0], a, b] = scores
        table[rows[:, 0], b, a] = scores
        for f in range(F):
            root[f] = _average_linkage(table[f], ok[f].reshape(-1), camera, threshold)
    flat = root + (np.arange(F) * n)[:, None]
    return _proposals_from_roots(flat.reshape(F, C, P), ok, 1 if C == 1 else min_views)


def _average_linkage(
    score: np.ndarray, valid: np.ndarray, camera: np.ndarray, threshold: float
) -> np.ndarray:
    """One frame of `propose_people_linked`: score (n, n) symmetric pair scores, valid (n,) real
    skeletons, camera (n,). Returns (n,) each item's group, named by its lowest item."""
    n = len(valid)
    items = np.nonzero(valid)[0]
    root = np.arange(n)
    if len(items) < 2:
        return root
    m = len(items)
    # Groups sharing a camera may never merge (the item itself included: the diagonal). Between
    # two groups that may, every item pair is cross-view: their pair count is the sizes' product.
    conflict = camera[items][:, None] == camera[items][None]
    total = score[np.ix_(items, items)].copy()  # score sums over the groups' item pairs
    size = np.ones(m)
    alive = np.ones(m, bool)
    members = [[i] for i in range(m)]
    while True:
        ok = alive[:, None] & alive[None] & ~conflict
        mean = np.where(ok, total / np.outer(size, size), -np.inf)
        best = int(np.argmax(mean))
        i, j = divmod(best, m)
        if not mean[i, j] > threshold:
            break
        i, j = min(i, j), max(i, j)
        total[i] += total[j]
        total[:, i] += total[:, j]
        conflict[i] |= conflict[j]
        conflict[:, i] |= conflict[:, j]
        size[i] += size[j]
        alive[j] = False
        members[i] += members[j]
    for g in np.nonzero(alive)[0]:
        group = members[g]
        if len(group) > 1:
            root[items[group]] = items[min(group)]
    return root


def union_find_exclusive(
    num_items: int, a: list[int] | np.ndarray, b: list[int] | np.ndarray, group: np.ndarray
) -> np.ndarray:
    """Greedy union-find that never joins two items of the same group (camera).

    Args:
      num_items: items 0..n-1.
      a, b: the pairs to join, in order (best first).
      group: (n,) int in 0..62, the camera of each item.
    Returns:
      (n,) the root of every item's set.
    """
    return _union_find_exclusive(
        num_items,
        np.asarray(a, np.int64).reshape(-1),
        np.asarray(b, np.int64).reshape(-1),
        np.asarray(group, np.int64).reshape(-1),
    )


# Compiled: an offline chunk joins tens of thousands of pairs, and as Python the loop cost more
# than the rest of the proposals.
@numba.njit(cache=True)
def _union_find_exclusive(num_items, a, b, group):
    """`union_find_exclusive` on (M,) int64 pairs and (n,) int64 groups."""
    parent = np.arange(num_items)
    cams = np.empty(num_items, np.int64)  # camera bitmask of each root
    for i in range(num_items):
        cams[i] = np.int64(1) << group[i]
    for m in range(len(a)):
        rx, ry = _find(parent, a[m]), _find(parent, b[m])
        if rx == ry or cams[rx] & cams[ry]:
            continue
        if rx > ry:
            rx, ry = ry, rx
        parent[ry] = rx
        cams[rx] |= cams[ry]
    return np.array([_find(parent, x) for x in range(num_items)], np.int64)


@numba.njit(cache=True)
def _find(parent, x):
    """The root of item x, compressing its path."""
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:
        parent[x], x = root, parent[x]
    return root


def _proposals_from_roots(root: np.ndarray, ok: np.ndarray, min_views: int) -> Proposals:
    """The people of a grouping: root (F, C, P) each skeleton's set, ok (F, C, P) which slots
    hold skeletons; a set of at least ``min_views`` skeletons is a person, numbered 0.. within
    its frame in the order of its root."""
    F, C, P = ok.shape
    identity, table, num = _people_table(
        np.ascontiguousarray(root, np.int64).reshape(-1), ok.reshape(-1), C, P, min_views
    )
    return Proposals(identity.reshape(F, C, P), [table[f, : num[f]] for f in range(F)])


# Compiled: a live frame's numbering cost about 50 us of numpy calls (unique, bincount, search).
@numba.njit(cache=True)
def _identity_from_roots(root, ok, F, per_frame, min_views):
    """(F * per_frame,) roots and slots -> (the int32 person of each slot, -1 none; (F,) the
    people per frame)."""
    n = F * per_frame
    size = np.zeros(n, np.int64)
    for i in range(n):
        if ok[i]:
            size[root[i]] += 1
    identity = np.full(n, -1, np.int32)
    num = np.zeros(F, np.int64)
    # A frame's people numbered in the order of their roots (slots of that frame), by marking
    # them: np.unique and searchsorted here cost seconds of compiling and nothing at run time.
    rank = np.empty(per_frame, np.int32)
    for f in range(F):
        start = f * per_frame
        rank[:] = -1
        for i in range(start, start + per_frame):
            if ok[i] and size[root[i]] >= min_views:
                rank[root[i] - start] = 0
        for j in range(per_frame):
            if rank[j] >= 0:
                rank[j] = num[f]
                num[f] += 1
        for i in range(start, start + per_frame):
            if ok[i] and size[root[i]] >= min_views:
                identity[i] = rank[root[i] - start]
    return identity, num


PROPOSAL_THRESHOLDS = (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def choose_proposal_threshold(
    rows: np.ndarray,
    scores: np.ndarray,
    identity: np.ndarray,
    count: np.ndarray,
    *,
    thresholds: tuple[float, ...] = PROPOSAL_THRESHOLDS,
    min_views: int = 2,
    shared_keypoints: np.ndarray | None = None,
    grouping: Callable[..., Proposals] | None = None,
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
      grouping: the grouping the threshold is for, with `propose_people`'s arguments (None:
        `propose_people` itself; e.g. `propose_people_linked`).
    Returns:
      (the threshold, {threshold: ARI}).
    """
    ari = _ari_by_threshold(rows, scores, identity, count, thresholds, min_views, grouping)
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


def _ari_by_threshold(
    rows, scores, identity, count, thresholds, min_views, grouping=None
) -> dict[float, float]:
    count = np.asarray(count)
    P = np.shape(identity)[2]
    group = propose_people if grouping is None else grouping
    ari = {}
    for th in thresholds:
        pred = group(rows, scores, count, num_skeletons=P, threshold=th, min_views=min_views)
        ari[float(th)] = matching_scores(identity, pred.identity, count)["ari"]
    return ari


# =========================================================================== combined matcher


@dataclasses.dataclass(frozen=True)
class CombinedConfig:
    """Settings of the combined matcher (`propose_combined`; the module docstring says how it works).

    Attributes:
      gat_weight: w, the GAT's share of the pair score.
      half_score_px: the epipolar distance (px) at which the geometric part of the score halves.
      threshold: the proposal threshold on the combined score; chosen per matcher on frames
        composed from the dev recordings (`choose_combined_threshold`).
      epipolar_cutoff_px: the epipolar matcher's cutoff (`choose_geometric_cutoff`, chosen on the
        same frames): the GAT's gate, the fallback grouping's cutoff and the consistency scale.
      median_min_shared: the pair distance is the smaller of the mean and the median epipolar
        distance where the two views share at least this many keypoints, else the mean
        (`combined_pair_distances`); a very large value keeps the mean alone.
      repair_splits: merge a person split over two groups by a duplicate or fragment skeleton
        (`propose_people`'s ``repair_splits``), in both groupings. On: on the domain-shift
        experiment's validation scenes (quick models of training seeds 0 and 1 on the right
        floor, seed 0 trained 0.6 m too low; ``median_min_shared`` 6) it changes part-mixing
        alone, and there only for the better (ARI +0.010 each; robust triangulation behind it
        0.30, 0.25 and 0.49 PCP nearer the true groups; combined + blend +0.07, +0.07, +0.09).
        Before the veto on ruled-out pairs (`SPLIT_VETO_FRACTION`) it merged two people on
        ``floor-0.3`` (the blend lost 0.27 PCP there) and was off.
      drop_duplicates: leave out a person made of another person's duplicates
        (`propose_people`'s ``drop_duplicates``), in both groupings. On: on the same validation
        scenes (scenes of seeds 0-2 for the seed-0 matcher) it changes part-mixing alone, never
        for the worse (ARI +0.0002 to +0.0006, robust triangulation up to 0.19 PCP nearer the
        true groups); a record written before it existed gets it on.

    The defaults of ``gat_weight`` and ``half_score_px`` were chosen on the validation scenes of
    ``python -m experiments.run --experiment domain-shift`` (seed-0 quick models, every shift):
    the largest worst-shift difference of per-frame ARI to the epipolar matcher, then the largest
    mean (a grid of w in 0.05-0.5, 15-50 px, thresholds 0.1-0.35; at w 0.2, 20 px every
    threshold from 0.1 to 0.3 keeps the worst shift within -0.0001 and the mean at +0.003,
    part-mixing +0.017 to +0.025). ``threshold`` and ``epipolar_cutoff_px`` default to what frames
    composed from that experiment's dev recordings choose for its seed-0 matcher (0.2; 100 px).
    ``median_min_shared`` was chosen on the same validation scenes by the same rule, with two
    seed-0 matchers (trained on the right floor, and on one 0.6 m too low): over 4-8 keypoints
    (and the mean alone, and the median at any count) 6 and 7 keep the worst shift at -0.0001
    (the mean alone: -0.0056, the wrong-floor matcher on the ``scores`` shift) and 6 has the
    larger mean gain (+0.0045 and +0.0055 against the epipolar matcher; the mean alone +0.0034
    and +0.0003; part-mixing 0.9655 -> 0.9784 and 0.9405 -> 0.9722).
    """

    gat_weight: float = 0.2
    half_score_px: float = 20.0
    threshold: float = 0.2
    epipolar_cutoff_px: float = 100.0
    median_min_shared: int = 6
    repair_splits: bool = True
    drop_duplicates: bool = True

    def __post_init__(self):
        if not 0.0 <= self.gat_weight <= 1.0:
            raise InputError(f"must be in [0, 1], not {self.gat_weight}", field="gat_weight")
        for name in ("half_score_px", "epipolar_cutoff_px"):
            if not getattr(self, name) > 0:
                raise InputError(f"must be > 0, not {getattr(self, name)}", field=name)
        if not self.median_min_shared >= 1:
            raise InputError(
                f"must be >= 1, not {self.median_min_shared}", field="median_min_shared"
            )


def combined_pair_distances(
    mean_px: np.ndarray,
    median_px: np.ndarray,
    shared_keypoints: np.ndarray | None,
    config: CombinedConfig,
) -> np.ndarray:
    """The combined matcher's distance of each pair (M,) px: the smaller of the mean and the
    median symmetric epipolar distance where the views share ``config.median_min_shared``+
    keypoints, else the mean (``shared_keypoints`` None: the mean everywhere).

    Part-mixed skeletons (a limb of a nearby person in the wrong skeleton) move the mean by the
    stray keypoints' distances, tens to hundreds of pixels, and not the median; with few shared
    keypoints the median is a coin toss between two people, so it is trusted only over enough.
    """
    mean = np.asarray(mean_px, np.float64)
    if shared_keypoints is None:
        return mean
    robust = np.asarray(shared_keypoints) >= config.median_min_shared
    return np.where(robust, np.minimum(mean, np.asarray(median_px, np.float64)), mean)


def combined_pair_scores(
    gat_scores: np.ndarray, distances_px: np.ndarray, config: CombinedConfig
) -> np.ndarray:
    """The combined matcher's pair scores (M,) from the GAT's (M,) and the epipolar distances (M,).

    ``w * s_gat * [d < cutoff] + (1 - w) * 2^(-d / half_score_px)``; d = inf (too few shared
    keypoints) leaves nothing: such a pair is never joined.
    """
    d = np.asarray(distances_px, np.float64)
    w = config.gat_weight
    gated = np.where(d < config.epipolar_cutoff_px, np.asarray(gat_scores, np.float64), 0.0)
    return (w * gated + (1.0 - w) * np.exp2(-d / config.half_score_px)).astype(np.float32)


def grouping_consistency(
    rows: np.ndarray,
    robust_distances_px: np.ndarray,
    identity: np.ndarray,
    *,
    scale_px: float,
) -> np.ndarray:
    """How well a grouping's people agree with epipolar geometry, per frame (label-free).

    Every pair of skeletons that the grouping puts into one person adds
    ``scale_px - min(d, 1.5 * scale_px)``: a pair nearer than ``scale_px`` counts for the
    grouping, a farther one (or one the geometry cannot judge, d = inf) against it, bounded so
    that one wild pair does not decide a frame. A person of n consistent views adds n(n-1)/2
    such terms, so of two groupings that agree in geometry the one with fewer, larger people
    scores higher (splitting a person is penalised).

    Args:
      rows: (M, 5) ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]``, every cross-view pair.
      robust_distances_px: (M,) each pair's median symmetric epipolar distance (inf: not judged).
      identity: (F, C, P) the grouping (`Proposals.identity`, -1 in no person).
      scale_px: the distance under which a pair agrees (the epipolar matcher's cutoff).
    Returns:
      (F,) the consistency of each frame's grouping.
    """
    rows = np.asarray(rows, np.int64).reshape(-1, 5)
    identity = np.asarray(identity)
    a = identity[rows[:, 0], rows[:, 1], rows[:, 2]]
    b = identity[rows[:, 0], rows[:, 3], rows[:, 4]]
    together = (a >= 0) & (a == b)
    d = np.minimum(np.asarray(robust_distances_px, np.float64), 1.5 * scale_px)
    return np.bincount(
        rows[:, 0], weights=np.where(together, scale_px - d, 0.0), minlength=identity.shape[0]
    )


def propose_combined(
    rows: np.ndarray,
    gat_scores: np.ndarray,
    distances_px: np.ndarray,
    robust_distances_px: np.ndarray,
    count: np.ndarray,
    *,
    config: CombinedConfig = CombinedConfig(),
    shared_keypoints: np.ndarray | None = None,
    num_skeletons: int | None = None,
    min_views: int = 2,
) -> tuple[Proposals, np.ndarray]:
    """The combined matcher's proposals: gated, blended pair scores, then per frame the grouping
    (this or the epipolar matcher's) that agrees better with the geometry (module docstring).

    Args:
      rows: (M, 5) every cross-view pair of every frame; gat_scores (M,): the GAT's scores;
        distances_px, robust_distances_px (M,): their mean and median symmetric epipolar
        distances (`inference.epipolar_distances_of_rows`); count (F, C).
      config: `CombinedConfig`.
      shared_keypoints: (M,) how many keypoints each pair's views share (the third output of
        `inference.epipolar_distances_of_rows`); None: the pair distance is the mean alone.
      num_skeletons, min_views: as `propose_people`.
    Returns:
      (`Proposals`, used_epipolar (F,) bool: the frames that kept the epipolar grouping).
    """
    count = np.asarray(count)
    kw = dict(
        num_skeletons=num_skeletons,
        min_views=min_views,
        repair_splits=config.repair_splits,
        drop_duplicates=config.drop_duplicates,
    )
    d = combined_pair_distances(distances_px, robust_distances_px, shared_keypoints, config)
    combined = propose_people(
        rows,
        combined_pair_scores(gat_scores, d, config),
        count,
        threshold=config.threshold,
        **kw,
    )
    # The epipolar matcher at its cutoff: nearest first, pairs under the cutoff (its pipeline
    # scores 2^(-d / cutoff) at threshold 0.5 give the same grouping), on the same distances.
    epipolar = propose_people(rows, -d, count, threshold=-config.epipolar_cutoff_px, **kw)
    robust = np.asarray(robust_distances_px)
    scale = config.epipolar_cutoff_px
    use_epipolar = grouping_consistency(
        rows, robust, epipolar.identity, scale_px=scale
    ) > grouping_consistency(rows, robust, combined.identity, scale_px=scale)
    return pick_frames(combined, epipolar, use_epipolar), use_epipolar


def pick_frames(first: Proposals, second: Proposals, take_second: np.ndarray) -> Proposals:
    """Per frame, ``second``'s grouping where ``take_second`` (F,) else ``first``'s."""
    take = np.asarray(take_second, bool)
    identity = np.where(take[:, None, None], second.identity, first.identity)
    people = [b if t else a for a, b, t in zip(first.people, second.people, take, strict=True)]
    return Proposals(identity.astype(np.int32), people)


def choose_combined_threshold(
    rows: np.ndarray,
    gat_scores: np.ndarray,
    distances_px: np.ndarray,
    robust_distances_px: np.ndarray,
    identity: np.ndarray,
    count: np.ndarray,
    *,
    config: CombinedConfig = CombinedConfig(),
    thresholds: tuple[float, ...] = PROPOSAL_THRESHOLDS,
    min_views: int = 2,
    shared_keypoints: np.ndarray | None = None,
) -> tuple[float, dict[float, float]]:
    """The combined matcher's threshold by the GAT threshold's rule: the best per-frame ARI of its
    proposals (`propose_combined` with ``config``'s other settings) on labelled frames, in
    practice frames composed from the dev recordings. Ties go to the one nearest
    ``config.threshold``.

    Returns:
      (the threshold, {threshold: ARI}).
    """
    count = np.asarray(count)
    P = np.shape(identity)[2]
    ari = {}
    for th in thresholds:
        pred, _ = propose_combined(
            rows,
            gat_scores,
            distances_px,
            robust_distances_px,
            count,
            config=dataclasses.replace(config, threshold=float(th)),
            shared_keypoints=shared_keypoints,
            num_skeletons=P,
            min_views=min_views,
        )
        ari[float(th)] = matching_scores(identity, pred.identity, count)["ari"]
    best = max(ari, key=lambda th: (round(ari[th], 6), -abs(th - config.threshold)))
    return best, ari
