"""The combined matcher's two repairs (`proposals.propose_people`'s ``repair_splits`` and
``drop_duplicates``) written plainly with dicts, sets and Python's sorts: the implementation the
package ran before its compiled one (`proposals._repaired_roots`), kept as the independent
reference that the compiled one must equal, tie for tie (tests/test_proposals.py)."""

from __future__ import annotations

import functools

import numpy as np

from mvpose_jax.proposals import SPLIT_VETO_FRACTION


def linked_groups(
    root: np.ndarray, a: list[int], b: list[int], strength: np.ndarray
) -> tuple[dict[tuple[int, int], list[float]], dict[int, list[int]]]:
    """The pairs of distinct groups that pairs above the threshold (a, b, with their scores
    ``strength``) join: {(root_a, root_b): those pairs' scores}, and {root: its items} of every
    group among them."""
    links: dict[tuple[int, int], list[float]] = {}
    for x, y, s in zip(a, b, np.asarray(strength).tolist(), strict=True):
        rx, ry = int(root[x]), int(root[y])
        if rx != ry:
            links.setdefault((min(rx, ry), max(rx, ry)), []).append(s)
    members: dict[int, list[int]] = {}
    if links:
        involved = np.array(sorted({r for key in links for r in key}))
        for item in np.nonzero(np.isin(root, involved))[0].tolist():
            members.setdefault(int(root[item]), []).append(item)
    return links, members


class PairScores:
    """The score of every scored pair of skeletons (items) in the frames of ``items``, both
    ways: ``table.get(x, y, default)``, ``(x, y) in table``.

    A dense (frames, C*P, C*P) table, not a dict of pairs: a chunk's repairs look at thousands
    of pairs, and building a dict of them in Python was most of the combined matcher's time.
    """

    def __init__(
        self, pair_items: np.ndarray, pair_scores: np.ndarray, items: set[int], C: int, P: int
    ):
        self.per_frame = C * P
        frames = np.unique(np.fromiter(items, np.int64, len(items)) // self.per_frame)
        self.row = dict(zip(frames.tolist(), range(len(frames)), strict=True))
        shape = (len(frames), self.per_frame, self.per_frame)
        self.score = np.zeros(shape)
        self.known = np.zeros(shape, bool)
        frame = pair_items[:, 0] // self.per_frame
        pos = np.searchsorted(frames, frame)
        inside = (pos < len(frames)) & (frames[np.minimum(pos, len(frames) - 1)] == frame)
        x, y = pair_items[inside, 0] % self.per_frame, pair_items[inside, 1] % self.per_frame
        r, sc = pos[inside], np.asarray(pair_scores, np.float64)[inside]
        # Both ways, each row's two entries in turn: a pair scored twice keeps its last score.
        rr, xx, yy = (np.stack([u, v], 1).reshape(-1) for u, v in ((r, r), (x, y), (y, x)))
        self.score[rr, xx, yy] = np.repeat(sc, 2)
        self.known[rr, xx, yy] = True

    def _at(self, x: int, y: int) -> tuple[int, int, int] | None:
        f = x // self.per_frame
        if f != y // self.per_frame or f not in self.row:
            return None
        return self.row[f], x % self.per_frame, y % self.per_frame

    def get(self, pair: tuple[int, int], default: float) -> float:
        at = self._at(*pair)
        return float(self.score[at]) if at is not None and self.known[at] else default

    def __contains__(self, pair: tuple[int, int]) -> bool:
        at = self._at(*pair)
        return at is not None and bool(self.known[at])

    def __getitem__(self, pair: tuple[int, int]) -> float:
        if pair not in self:
            raise KeyError(pair)
        return float(self.score[self._at(*pair)])


def merge_split_people(
    root: np.ndarray,
    a: list[int],
    b: list[int],
    strength: np.ndarray,
    pair_items: np.ndarray,
    pair_scores: np.ndarray,
    threshold: float,
    C: int,
    P: int,
) -> np.ndarray:
    """`propose_people`'s ``repair_splits`` on a grouping: root (n,) each item's group; a, b the
    joining pairs (above the threshold) and their scores ``strength``; pair_items (M, 2) and
    pair_scores (M,) every scored pair. Returns the new roots (a dropped skeleton: its own)."""
    root = root.copy()
    camera = lambda item: item // P % C  # noqa: E731
    links, members = linked_groups(root, a, b, strength)
    candidates = []
    for (ra, rb), scores in links.items():
        cams_a = {camera(x) for x in members[ra]}
        cams_b = {camera(y) for y in members[rb]}
        shared = cams_a & cams_b
        possible = sum(camera(x) != camera(y) for x in members[ra] for y in members[rb])
        if len(shared) == 1 and len(scores) >= 2 and len(scores) >= 0.5 * possible:
            candidates.append((len(scores), sum(scores) / len(scores), ra, rb, shared.pop()))
    if not candidates:
        return root
    # Every scored pair of the candidates' skeletons, to choose the one kept in the shared camera.
    items = {x for *_, ra, rb, _ in candidates for x in members[ra] + members[rb]}
    score_of = PairScores(pair_items, pair_scores, items, C, P)
    veto = SPLIT_VETO_FRACTION * threshold
    touched: set[int] = set()
    for *_, ra, rb, c in sorted(candidates, reverse=True):  # most links first
        if ra in touched or rb in touched:
            continue
        group = members[ra] + members[rb]
        twins = [x for x in group if camera(x) == c]
        others = [x for x in group if camera(x) != c]

        def support(x: int) -> float:
            got = [score_of[(x, y)] for y in others if (x, y) in score_of]
            return sum(got) / len(got) if got else -np.inf

        of_twin = {x: support(x) for x in twins}
        # Both twins must belong with the other views (a duplicate or fragment does; another
        # person's skeleton does not): else the groups are two people.
        if min(of_twin.values()) <= threshold:
            continue
        drop = min(twins, key=lambda x: (of_twin[x], -x))
        kept = [x for x in group if x != drop]
        # Nor may any pair of the merged person be ruled out (two people whose groups are
        # linked by enough near pairs can still hold one far pair between them). Pairs of one
        # camera are never scored, so only cross-view pairs can veto.
        if any(
            score_of.get((x, y), np.inf) < veto
            for x in members[ra]
            for y in members[rb]
            if drop not in (x, y)
        ):
            continue
        touched |= {ra, rb}
        root[kept] = min(kept)
        root[drop] = drop
    return root


def drop_duplicate_people(
    root: np.ndarray,
    a: list[int],
    b: list[int],
    strength: np.ndarray,
    pair_items: np.ndarray,
    pair_scores: np.ndarray,
    threshold: float,
    C: int,
    P: int,
    min_views: int,
) -> np.ndarray:
    """`propose_people`'s ``drop_duplicates`` on a grouping: root (n,) each item's group; a, b the
    pairs above the threshold and their scores ``strength``; pair_items (M, 2) and pair_scores
    (M,) every scored pair. Returns the new roots (a ghost's skeletons: their own)."""
    root = root.copy()
    camera = lambda item: item // P % C  # noqa: E731
    links, members = linked_groups(root, a, b, strength)
    if not links:
        return root
    score_of = PairScores(pair_items, pair_scores, set().union(*members.values()), C, P)

    @functools.cache  # asked once per link a group has
    def own_score(r: int) -> float:
        got = [
            score_of.get((x, y), -np.inf)
            for i, x in enumerate(members[r])
            for y in members[r][i + 1 :]
        ]
        return float(np.mean(got)) if got else -np.inf

    veto = SPLIT_VETO_FRACTION * threshold
    candidates = []
    for (ra, rb), joining in links.items():
        n_links = len(joining)
        if min(len(members[ra]), len(members[rb])) < min_views:
            continue  # not two people
        cams = {r: {camera(x) for x in members[r]} for r in (ra, rb)}
        order = sorted((ra, rb), key=lambda r: (len(members[r]), own_score(r), -r), reverse=True)
        host, ghost = order
        if not cams[ghost] <= cams[host]:
            continue
        across = [(x, y) for x in members[ghost] for y in members[host] if camera(x) != camera(y)]
        if n_links < 0.5 * len(across):
            continue
        if any(score_of.get(pair, np.inf) < veto for pair in across):
            continue
        candidates.append((len(members[host]), n_links, host, ghost))
    dropped: set[int] = set()
    for *_, host, ghost in sorted(candidates, reverse=True):  # the largest people first
        if host in dropped or ghost in dropped:
            continue
        dropped.add(ghost)
        root[members[ghost]] = members[ghost]
    return root
