"""proposals.py: the proposal step's settings chosen by one rule (hand-built frames with known
answers), and the chosen threshold written beside a matcher and read back."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from flax import nnx
from hypothesis import given, settings
from hypothesis import strategies as st

from mvpose_jax.errors import InputError
from mvpose_jax.metrics import matching_scores
from mvpose_jax.models import GATConfig, MatchingGAT
from mvpose_jax.proposals import (
    PROPOSAL_THRESHOLDS,
    CombinedConfig,
    choose_combined_threshold,
    choose_geometric_cutoff,
    choose_proposal_threshold,
    combined_pair_distances,
    combined_pair_scores,
    grouping_consistency,
    propose_combined,
    propose_people,
    propose_people_linked,
    union_find_exclusive,
)
from mvpose_jax.synthetic import generate_single_person_recordings
from mvpose_jax.trained import (
    PROPOSAL_THRESHOLD_FILE,
    MatcherConfig,
    read_combined_config,
    read_proposal_threshold,
    write_proposal_threshold,
)


def test_choose_proposal_threshold_takes_the_band_that_separates_true_from_false_pairs():
    # Camera 0 sees people A and B, camera 1 sees A and a false detection X.
    identity = np.array([[[0, 1], [0, -1]]])
    count = np.array([[2, 2]])
    rows = np.array(
        [
            [0, 0, 0, 1, 0],  # A-A, true
            [0, 0, 1, 1, 1],  # B-X, false
            [0, 0, 0, 1, 1],  # A-X, false
            [0, 0, 1, 1, 0],
        ]
    )  # B-A, false
    scores = np.array([0.3, 0.1, 0.05, 0.04])
    best, ari = choose_proposal_threshold(rows, scores, identity, count)
    # A pair is taken when its score is above the threshold: from 0.1 (B-X refused) to below 0.3
    # (A-A taken) every threshold is perfect, and 0.2 is the nearest to 0.5.
    assert best == 0.2
    assert ari[0.1] == ari[0.15] == ari[0.2] == pytest.approx(1.0)
    assert ari[0.05] < 1.0 and ari[0.3] < 1.0 and ari[0.5] < 1.0


def test_choose_geometric_cutoff_is_a_pixel_distance_with_the_same_rule():
    # The frame of the threshold test, with distances instead of scores: A-A at 7 px, the false
    # pairs at 13, 18 and 22 px. Cutoffs from 8 to 12 px keep A-A alone (ARI 1); 12 is nearest 30.
    identity = np.array([[[0, 1], [0, -1]]])
    count = np.array([[2, 2]])
    rows = np.array([[0, 0, 0, 1, 0], [0, 0, 1, 1, 1], [0, 0, 0, 1, 1], [0, 0, 1, 1, 0]])
    d = np.array([7.0, 13.0, 18.0, 22.0])
    best, ari = choose_geometric_cutoff(rows, d, identity, count)
    assert best == 12.0
    assert ari[8.0] == ari[10.0] == ari[12.0] == pytest.approx(1.0)
    assert ari[6.0] < 1.0 and ari[15.0] < 1.0
    # The same as the GAT rule applied to the pipeline's scores 2^(-d / cutoff) at threshold 0.5.
    p = propose_people(rows, np.exp2(-d / best), count, num_skeletons=2, threshold=0.5)
    assert matching_scores(identity, p.identity, count)["ari"] == pytest.approx(1.0)


def test_matcher_threshold_is_chosen_written_and_read_back(tmp_path):

    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.matcher_settings import choose_matcher_threshold
    from mvpose_jax.trained import Matcher

    rig = load_rig("panoptic5")
    recs = generate_single_person_recordings(rig, num_recordings=4, num_frames=3, seed=5)
    tiny = GATConfig(widths=(8, 1), heads=(2, 1))
    graphdef, params, rest = nnx.split(
        MatchingGAT(rig.num_cameras, recs[0].num_keypoints, tiny, rngs=nnx.Rngs(0)), nnx.Param, ...
    )
    matcher = Matcher(graphdef, rest, params, rig, MatcherConfig(gat=tiny, max_people=3))
    threshold, ari, composed = choose_matcher_threshold(matcher, recs, num_samples=24)
    write_proposal_threshold(tmp_path, threshold, ari, composed)
    assert threshold in PROPOSAL_THRESHOLDS and ari[threshold] == max(ari.values())
    record = json.loads((tmp_path / PROPOSAL_THRESHOLD_FILE).read_text())
    assert record["threshold"] == threshold and record["composed_frames"] == 24
    assert read_proposal_threshold(str(tmp_path), None) == threshold
    assert read_proposal_threshold(str(tmp_path), 0.7) == 0.7  # --threshold wins
    assert read_proposal_threshold(None, None) == 0.5  # geometric matcher: the paper's
    assert (
        read_proposal_threshold(str(tmp_path / "elsewhere"), None) == 0.5
    )  # a folder without the file
    (tmp_path / PROPOSAL_THRESHOLD_FILE).write_text("{")
    with pytest.raises(InputError, match=PROPOSAL_THRESHOLD_FILE):
        read_proposal_threshold(str(tmp_path), None)


@pytest.mark.slow  # a GAT on composed frames, the epipolar distances, 12 proposal runs
def test_matcher_settings_come_from_one_composition():
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.matcher_settings import choose_matcher_settings, choose_matcher_threshold
    from mvpose_jax.trained import Matcher

    rig = load_rig("panoptic5")
    recs = generate_single_person_recordings(rig, num_recordings=4, num_frames=3, seed=5)
    tiny = GATConfig(widths=(8, 1), heads=(2, 1))
    graphdef, params, rest = nnx.split(
        MatchingGAT(rig.num_cameras, recs[0].num_keypoints, tiny, rngs=nnx.Rngs(0)), nnx.Param, ...
    )
    matcher = Matcher(graphdef, rest, params, rig, MatcherConfig(gat=tiny, max_people=3))
    threshold, ari, _ = choose_matcher_threshold(matcher, recs, num_samples=24)
    # The same GAT threshold, the epipolar cutoff, the combined matcher's threshold at it.
    chosen = choose_matcher_settings(matcher, recs, num_samples=24)
    assert chosen.threshold == threshold and chosen.ari_by_threshold == ari
    assert chosen.combined.epipolar_cutoff_px == chosen.geometric_cutoff_px
    assert chosen.ari_by_cutoff_px[chosen.geometric_cutoff_px] == max(
        chosen.ari_by_cutoff_px.values()
    )
    best = chosen.ari_by_combined_threshold
    assert best[chosen.combined.threshold] == max(best.values()) and chosen.composed_frames == 24


def test_proposals_join_best_first_and_respect_cameras():
    count = np.array([[2, 2, 1]])  # one frame, 3 cameras
    rows = np.array(
        [
            [0, 0, 0, 1, 0],  # a: 0.9
            [0, 0, 0, 1, 1],  # would put two camera-1 skeletons in a's person: refused
            [0, 0, 1, 1, 1],  # b: 0.8
            [0, 1, 0, 2, 0],  # a gets camera 2
            [0, 0, 1, 2, 0],  # refused: camera 2 taken
        ]
    )
    scores = np.array([0.9, 0.85, 0.8, 0.7, 0.95])
    p = propose_people(rows, scores, count)
    # The best pair (0,1)-(2,0) goes first: b = {(0,1), (2,0)}, then (0,0)-(1,0), then (1,1) joins b.
    ident = p.identity[0]
    assert ident[0, 1] == ident[2, 0] == ident[1, 1]
    assert ident[0, 0] == ident[1, 0] != ident[0, 1]
    assert len(p.people[0]) == 2
    for person in p.people[0]:
        assert (person >= 0).sum() >= 2


def test_proposals_threshold_min_views_and_single_camera():
    count = np.array([[1, 1], [2, 0]])
    rows = np.array([[0, 0, 0, 1, 0]])
    assert (propose_people(rows, np.array([0.4]), count).identity[0] == -1).all()
    assert (propose_people(rows, np.array([0.6]), count).identity[0, :, 0] == 0).all()
    single = propose_people(np.zeros((0, 5), int), np.zeros(0), np.array([[3], [0]]))
    assert single.identity[0, 0].tolist() == [0, 1, 2] and len(single.people[1]) == 0


def _random_frames(rng, F, cams, P):
    """Random skeleton counts (F, cams) (up to P per camera) and every cross-camera pair of
    skeletons that exist, as rows (frame, camera a, skeleton a, camera b, skeleton b)."""
    count = rng.integers(0, P + 1, (F, cams))
    f, ca, pa, cb, pb = np.meshgrid(
        np.arange(F), np.arange(cams), np.arange(P), np.arange(cams), np.arange(P), indexing="ij"
    )
    rows = np.stack([a.ravel() for a in (f, ca, pa, cb, pb)], 1)
    rows = rows[
        (rows[:, 1] < rows[:, 3])
        & (rows[:, 2] < count[rows[:, 0], rows[:, 1]])
        & (rows[:, 4] < count[rows[:, 0], rows[:, 3]])
    ]
    return count, rows


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 4), st.integers(2, 4), st.integers(1, 4), st.integers(0, 2**31 - 1))
def test_proposals_never_give_a_person_two_skeletons_of_one_camera(F, cams, P, seed):
    rng = np.random.default_rng(seed)
    count, rows = _random_frames(rng, F, cams, P)
    scores = rng.random(len(rows))
    for repair in (False, True):
        for drop in (False, True):
            got = propose_people(
                rows, scores, count, num_skeletons=P, repair_splits=repair, drop_duplicates=drop
            )
            _check_exclusive(got)


def _check_exclusive(p):
    F = p.identity.shape[0]
    for fr in range(F):
        ident = p.identity[fr]
        for person in np.unique(ident[ident >= 0]):
            per_cam = (ident == person).sum(axis=1)
            assert per_cam.max() == 1 and per_cam.sum() >= 2
        assert len(p.people[fr]) == len(np.unique(ident[ident >= 0]))
        for g, person in enumerate(p.people[fr]):
            for c, sk in enumerate(person):
                assert (sk < 0) or ident[c, sk] == g


def _duplicate_split_frame():
    """One person in cameras 0-3 (skeleton 0 each) and a duplicate in camera 0 (skeleton 1) that
    grabs camera 1 first: the greedy pass makes two groups sharing camera 0. Returns count,
    rows and scores, and the row index of each (camera_a, skeleton_a, camera_b, skeleton_b)."""
    count = np.array([[2, 1, 1, 1]])
    pairs = {
        (0, 1, 1, 0): 0.95,  # duplicate - camera 1
        (0, 0, 2, 0): 0.9,
        (0, 0, 3, 0): 0.9,
        (2, 0, 3, 0): 0.9,
        (1, 0, 2, 0): 0.85,
        (1, 0, 3, 0): 0.85,
        (0, 0, 1, 0): 0.8,
        (0, 1, 2, 0): 0.6,
        (0, 1, 3, 0): 0.6,
    }
    rows = np.array([[0, *key] for key in pairs])
    return count, rows, np.array(list(pairs.values())), {k: i for i, k in enumerate(pairs)}


def test_a_person_split_by_a_duplicate_is_merged_keeping_the_better_skeleton():
    count, rows, scores, _ = _duplicate_split_frame()
    split = propose_people(rows, scores, count).identity[0]
    assert split[0, 1] == split[1, 0] != split[0, 0] == split[2, 0] == split[3, 0]
    merged = propose_people(rows, scores, count, repair_splits=True)
    ident = merged.identity[0]
    # The original's mean score to the other views is 0.87, the duplicate's 0.72: it is left out.
    assert ident[0, 0] == ident[1, 0] == ident[2, 0] == ident[3, 0] == 0 and ident[0, 1] == -1
    assert len(merged.people[0]) == 1


def test_a_split_person_is_not_merged_across_a_ruled_out_pair():
    # The duplicate frame, but camera 1's skeleton and camera 3's now score 0.01 (under a tenth
    # of the threshold): every other condition of the merge still holds, yet the merged person
    # would hold a pair the scores rule out, so the two groups stay apart.
    count, rows, scores, index = _duplicate_split_frame()
    scores[index[(1, 0, 3, 0)]] = 0.01
    split = propose_people(rows, scores, count).identity[0]
    for repair in (False, True):
        ident = propose_people(rows, scores, count, repair_splits=repair).identity[0]
        np.testing.assert_array_equal(ident, split)
    assert split[0, 1] == split[1, 0] != split[0, 0] == split[2, 0] == split[3, 0]
    scores[index[(1, 0, 3, 0)]] = 0.06  # above the veto: merged
    ident = propose_people(rows, scores, count, repair_splits=True).identity[0]
    assert ident[0, 0] == ident[1, 0] == ident[2, 0] == ident[3, 0] == 0 and ident[0, 1] == -1


def test_two_people_sharing_a_camera_with_one_link_stay_apart():
    # X = camera 0 skeleton 0 + camera 1; Y = camera 0 skeleton 1 + camera 2; one pair across.
    count = np.array([[2, 1, 1]])
    rows = np.array([[0, 0, 0, 1, 0], [0, 0, 1, 2, 0], [0, 1, 0, 2, 0], [0, 0, 0, 2, 0]])
    scores = np.array([0.9, 0.9, 0.6, 0.1])
    for repair in (False, True):
        ident = propose_people(rows, scores, count, repair_splits=repair).identity[0]
        assert ident[0, 0] == ident[1, 0] != ident[0, 1] == ident[2, 0]


def _ghost_frame():
    """One person in cameras 0-3 (skeleton 0 each) and duplicates of it in cameras 0 and 1
    (skeleton 1) that score high with each other: the greedy pass makes them a second person.
    Returns count, rows, scores and the row index of each (camera_a, skel_a, camera_b, skel_b)."""
    count = np.array([[2, 2, 1, 1]])
    pairs = {(a, 0, b, 0): 0.9 for a, b in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))}
    pairs |= {
        (0, 1, 1, 1): 0.85,  # the duplicates' own pair
        (0, 1, 1, 0): 0.7,
        (0, 0, 1, 1): 0.7,
        (0, 1, 2, 0): 0.6,
        (1, 1, 2, 0): 0.1,
        (0, 1, 3, 0): 0.1,
        (1, 1, 3, 0): 0.1,
    }
    rows = np.array([[0, *key] for key in pairs])
    return count, rows, np.array(list(pairs.values())), {k: i for i, k in enumerate(pairs)}


def test_a_person_made_of_another_persons_duplicates_is_left_out():
    count, rows, scores, index = _ghost_frame()
    ghost = propose_people(rows, scores, count, threshold=0.5).identity[0]
    assert ghost[0, 0] == ghost[1, 0] == ghost[2, 0] == ghost[3, 0] == 0
    assert ghost[0, 1] == ghost[1, 1] == 1
    # 3 of the 6 pairs across cameras are above the threshold (half): the ghost is left out.
    ident = propose_people(rows, scores, count, threshold=0.5, drop_duplicates=True).identity[0]
    assert ident[:, 0].tolist() == [0, 0, 0, 0] and ident[:, 1].tolist() == [-1, -1, -1, -1]
    # 2 of 6: two people (the duplicates' pair agrees, the rest of the geometry does not).
    scores[index[(0, 1, 2, 0)]] = 0.4
    got = propose_people(rows, scores, count, threshold=0.5, drop_duplicates=True).identity[0]
    np.testing.assert_array_equal(got, ghost)
    # 3 of 6 again, but one pair across is ruled out (under a tenth of the threshold): kept.
    scores[index[(0, 1, 2, 0)]] = 0.6
    scores[index[(1, 1, 3, 0)]] = 0.04
    got = propose_people(rows, scores, count, threshold=0.5, drop_duplicates=True).identity[0]
    np.testing.assert_array_equal(got, ghost)


def test_of_two_duplicate_people_on_the_same_cameras_the_weaker_is_left_out():
    # Two 2-view groups on cameras 0 and 1 that agree across: one person seen twice in both.
    count = np.array([[2, 2]])
    rows = np.array([[0, 0, 0, 1, 0], [0, 0, 1, 1, 1], [0, 0, 0, 1, 1], [0, 0, 1, 1, 0]])
    for own, kept in (((0.9, 0.8), 0), ((0.8, 0.9), 1)):
        scores = np.array([*own, 0.7, 0.7])
        ident = propose_people(rows, scores, count, drop_duplicates=True).identity[0]
        assert ident[:, kept].tolist() == [0, 0] and ident[:, 1 - kept].tolist() == [-1, -1]
        both = propose_people(rows, scores, count).identity[0]
        assert both[0, 0] == both[1, 0] != both[0, 1] == both[1, 1]


def test_compiled_repairs_equal_the_plain_reference():
    """`propose_people` with the split repair and the duplicate drop (compiled) gives the people
    of the plain Python reference (tests/reference_proposals.py, on the same union-find) on
    random frames: scores from four values (so that link counts, mean scores and supports tie)
    or continuous, some pairs scored twice (the last score counts), thresholds in both signs
    (the epipolar grouping's are negative distances), float32 and float64 scores, one to three
    views a person. Both repairs must change the grouping in many of the cases."""
    from mvpose_jax.proposals import _proposals_from_roots, _skeleton_slots
    from tests import reference_proposals as reference

    rng = np.random.default_rng(0)
    changed = {"repair": 0, "drop": 0}
    for case in range(600):
        F, C, P = int(rng.integers(1, 4)), int(rng.integers(2, 6)), int(rng.integers(1, 5))
        count, rows = _random_frames(rng, F, C, P)
        twice = rows[rng.random(len(rows)) < 0.1][:, [0, 3, 4, 1, 2]]
        rows = np.concatenate([rows, twice])
        coarse = rng.choice([0.01, 0.3, 0.6, 0.9], len(rows))
        scores = coarse if case % 2 else rng.random(len(rows))
        threshold, min_views = float(rng.choice([0.2, 0.5])), int(rng.integers(1, 4))
        if case % 3 == 0:  # as the epipolar grouping: minus distances, minus the cutoff
            scores, threshold = -100 * scores, -100 * threshold
        scores = scores.astype(rng.choice([np.float32, np.float64]))
        pair_items = (rows[:, [0]] * C + rows[:, [1, 3]]) * P + rows[:, [2, 4]]
        keep = np.nonzero(scores > threshold)[0]
        joins = keep[np.argsort(-scores[keep], kind="stable")]
        a, b = pair_items[joins, 0], pair_items[joins, 1]
        parent = union_find_exclusive(F * C * P, a, b, np.tile(np.repeat(np.arange(C), P), F))
        _, ok = _skeleton_slots(count, P)
        # The reference's arguments: the joins as lists, their scores, every scored pair.
        pairs = (a.tolist(), b.tolist(), scores[joins], pair_items, scores, threshold, C, P)
        for repair in (False, True):
            for drop in (False, True):
                want = parent
                if repair:
                    want = reference.merge_split_people(want, *pairs)
                    changed["repair"] += not drop and (want != parent).any()
                if drop:
                    before = want
                    want = reference.drop_duplicate_people(want, *pairs, min_views)
                    changed["drop"] += not repair and (want != before).any()
                want = _proposals_from_roots(want.reshape(F, C, P), ok, min_views)
                flags = dict(min_views=min_views, repair_splits=repair, drop_duplicates=drop)
                got = propose_people(
                    rows, scores, count, num_skeletons=P, threshold=threshold, **flags
                )
                np.testing.assert_array_equal(got.identity, want.identity, err_msg=f"{case}")
                for g, w in zip(got.people, want.people, strict=True):
                    np.testing.assert_array_equal(g, w, err_msg=f"case {case}")
    assert min(changed.values()) >= 20, changed


def test_union_find_exclusive_plain():
    roots = union_find_exclusive(4, [0, 1, 2], [1, 2, 3], np.array([0, 1, 0, 2]))
    assert roots.tolist() == [0, 0, 2, 2]  # 1-2 refused (camera 0 twice), 2-3 joined


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_union_find_exclusive_is_greedy_set_merging(data):
    # The compiled union-find against sets merged in the pairs' order, each merge refused when
    # the two sets share a camera; a set's root is its smallest item.
    n = data.draw(st.integers(1, 30))
    group = np.array(data.draw(st.lists(st.integers(0, 62), min_size=n, max_size=n)))
    pairs = data.draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1))))
    sets = [{i} for i in range(n)]
    for x, y in pairs:
        a, b = sets[x], sets[y]
        if a is not b and not {group[i] for i in a} & {group[i] for i in b}:
            merged = a | b
            for i in merged:
                sets[i] = merged
    a, b = [x for x, _ in pairs], [y for _, y in pairs]
    assert union_find_exclusive(n, a, b, group).tolist() == [min(sets[i]) for i in range(n)]


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_people_are_numbered_by_root_within_each_frame(data):
    from mvpose_jax.proposals import _proposals_from_roots

    F, C, P = (data.draw(st.integers(1, 4)) for _ in range(3))
    ok = np.array(data.draw(st.lists(st.booleans(), min_size=F * C * P, max_size=F * C * P)))
    ok = ok.reshape(F, C, P)
    # Each slot's root: any slot of its own frame.
    local = data.draw(st.lists(st.integers(0, C * P - 1), min_size=F * C * P, max_size=F * C * P))
    root = np.asarray(local).reshape(F, C, P) + (np.arange(F) * C * P)[:, None, None]
    min_views = data.draw(st.integers(1, 3))
    got = _proposals_from_roots(root, ok, min_views)
    for f in range(F):
        size = {r: int((ok[f] & (root[f] == r)).sum()) for r in np.unique(root[f])}
        people = sorted(r for r in size if size[r] >= min_views)
        want = np.where(
            ok[f], [[people.index(r) if r in people else -1 for r in row] for row in root[f]], -1
        )
        np.testing.assert_array_equal(got.identity[f], want)
        table = np.full((len(people), C), -1)
        for c, p in zip(*np.nonzero(want >= 0), strict=True):
            table[want[c, p], c] = p  # the last skeleton of a camera, as numpy assigns
        np.testing.assert_array_equal(got.people[f], table)


# --------------------------------------------------------------------------- combined matcher


def _two_people_three_views():
    """One frame, 3 cameras, people A (skeleton 0) and B (skeleton 1) in each: every cross-view
    pair, with a flag for the true ones."""
    rows = np.array(
        [
            [0, ca, pa, cb, pb]
            for ca, cb in ((0, 1), (0, 2), (1, 2))
            for pa in (0, 1)
            for pb in (0, 1)
        ]
    )
    true = rows[:, 2] == rows[:, 4]
    identity = np.array([[[0, 1], [0, 1], [0, 1]]])
    return rows, true, identity, np.array([[2, 2, 2]])


def test_combined_scores_gate_and_closed_form():
    cfg = CombinedConfig(
        gat_weight=0.2, half_score_px=20.0, threshold=0.2, epipolar_cutoff_px=100.0
    )
    s = combined_pair_scores(
        np.array([0.5, 1.0, 1.0, 1.0]), np.array([20.0, 99.0, 150.0, np.inf]), cfg
    )
    # 0.2 * 0.5 + 0.8 / 2; at 99 px the GAT still counts; past the cutoff (and with too few
    # shared keypoints, d = inf) only the geometry does.
    np.testing.assert_allclose(
        s, [0.5, 0.2 + 0.8 * 2 ** (-99 / 20), 0.8 * 2 ** (-150 / 20), 0.0], rtol=1e-6
    )
    # The gate drops a geometrically impossible pair the GAT is sure of: it is never joined,
    # while the GAT alone joins it.
    rows, count = np.array([[0, 0, 0, 1, 0]]), np.array([[1, 1]])
    far = np.array([150.0])
    p, _ = propose_combined(rows, np.array([1.0]), far, far, count, config=cfg)
    assert (p.identity == -1).all()
    assert (
        propose_people(rows, np.array([1.0]), count, threshold=cfg.threshold).identity >= 0
    ).all()
    with pytest.raises(InputError, match="gat_weight"):
        CombinedConfig(gat_weight=1.5)


def test_combined_recovers_the_truth_when_the_gat_is_adversarially_wrong():
    rows, true, identity, count = _two_people_three_views()
    # The GAT is sure of every false pair and rejects every true one; the geometry is clean but
    # close: true pairs 30 px, false 35 px. The blend then ranks the false pairs first
    # (0.2 + 0.8 * 2^-1.75 = 0.44 > 0.8 * 2^-1.5 = 0.28), so the combined grouping alone is wrong;
    # the epipolar grouping (nearest first) is right and agrees better with the geometry.
    gat = np.where(true, 0.0, 1.0)
    d = np.where(true, 30.0, 35.0)
    cfg = CombinedConfig()
    blended = propose_people(rows, combined_pair_scores(gat, d, cfg), count, threshold=0.2)
    assert matching_scores(identity, blended.identity, count)["ari"] < 1.0
    p, used_epipolar = propose_combined(rows, gat, d, d, count, config=cfg)
    assert used_epipolar.tolist() == [True]
    assert matching_scores(identity, p.identity, count)["ari"] == pytest.approx(1.0)
    # Far false pairs (200 px): the gate alone is enough, the blend's grouping is kept.
    d = np.where(true, 30.0, 200.0)
    p, used_epipolar = propose_combined(rows, gat, d, d, count, config=cfg)
    assert used_epipolar.tolist() == [False]
    assert matching_scores(identity, p.identity, count)["ari"] == pytest.approx(1.0)


def test_combined_pair_distance_is_the_median_only_over_enough_shared_keypoints():
    cfg = CombinedConfig(median_min_shared=6)
    mean, median = np.array([150.0, 150.0, 20.0, np.inf]), np.array([10.0, 10.0, 30.0, np.inf])
    got = combined_pair_distances(mean, median, np.array([12, 5, 12, 2]), cfg)
    np.testing.assert_array_equal(got, [10.0, 150.0, 20.0, np.inf])
    np.testing.assert_array_equal(combined_pair_distances(mean, median, None, cfg), mean)
    with pytest.raises(InputError, match="median_min_shared"):
        CombinedConfig(median_min_shared=0)


def test_combined_joins_a_part_mixed_skeleton_by_its_median():
    # Camera 2's skeleton of A carries B's arm: its pairs with A's other views have a mean
    # distance of 150 px (past the 100 px cutoff) but a median of 8 px over 12 shared keypoints.
    rows, true, identity, count = _two_people_three_views()
    mixed = true & ((rows[:, 1] == 2) | (rows[:, 3] == 2)) & (rows[:, 2] == 0)
    mean = np.where(true, np.where(mixed, 150.0, 6.0), 300.0)
    median = np.where(true, np.where(mixed, 8.0, 6.0), 280.0)
    gat = np.where(true, 0.9, 0.05)
    cfg = CombinedConfig()
    p, _ = propose_combined(
        rows, gat, mean, median, count, config=cfg, shared_keypoints=np.full(len(rows), 12)
    )
    assert matching_scores(identity, p.identity, count)["ari"] == pytest.approx(1.0)
    # The mean alone (or too few shared keypoints to trust the median) leaves A's third view out.
    for shared in (None, np.full(len(rows), 5)):
        p, _ = propose_combined(rows, gat, mean, median, count, config=cfg, shared_keypoints=shared)
        assert p.identity[0, 2, 0] == -1 and p.identity[0, 2, 1] >= 0
        assert (p.identity[0, :2, 0] >= 0).all()


def test_combined_changes_nothing_where_gat_and_geometry_agree():
    rows, true, identity, count = _two_people_three_views()
    gat, d = np.where(true, 0.97, 0.01), np.where(true, 6.0, 80.0)
    p, used_epipolar = propose_combined(rows, gat, d, d, count)
    for other in (
        propose_people(rows, gat, count, threshold=0.5),
        propose_people(rows, -d, count, threshold=-100.0),
    ):
        np.testing.assert_array_equal(p.identity, other.identity)
    assert used_epipolar.tolist() == [False]  # equal consistency: the combined grouping


def test_grouping_consistency_closed_form_prefers_consistent_joins_and_penalises_splits():
    rows, true, identity, _ = _two_people_three_views()
    d = np.where(true, 10.0, 400.0)
    score = grouping_consistency(rows, d, identity, scale_px=100.0)
    assert score.tolist() == [6 * 90.0]  # 2 people x 3 pairs, each 100 - 10
    split = identity.copy()
    split[0, 2] = -1  # camera 2's skeletons in no person: 2 consistent pairs lost
    assert grouping_consistency(rows, d, split, scale_px=100.0).tolist() == [2 * 90.0]
    wrong = np.array([[[0, 1], [1, 0], [0, 1]]])  # camera 1 swapped: 4 far pairs, 2 near
    # far pairs count -50 each (bounded at 1.5 x 100), near ones +90.
    assert grouping_consistency(rows, d, wrong, scale_px=100.0).tolist() == [2 * 90.0 - 4 * 50.0]


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 3), st.integers(2, 4), st.integers(1, 4), st.integers(0, 2**31 - 1))
def test_combined_proposals_shapes_masks_and_exclusivity(F, cams, P, seed):
    rng = np.random.default_rng(seed)
    count, rows = _random_frames(rng, F, cams, P)
    d = np.where(rng.random(len(rows)) < 0.1, np.inf, rng.uniform(0, 200, len(rows)))
    p, used = propose_combined(
        rows, rng.random(len(rows)), d, d * rng.uniform(0.5, 1.5, len(rows)), count, num_skeletons=P
    )
    assert p.identity.shape == (F, cams, P) and used.shape == (F,) and len(p.people) == F
    assert (p.identity[np.arange(P)[None, None] >= count[..., None]] == -1).all()
    for fr in range(F):
        ident = p.identity[fr]
        for person in np.unique(ident[ident >= 0]):
            per_cam = (ident == person).sum(axis=1)
            assert per_cam.max() == 1 and per_cam.sum() >= 2
        for g, person in enumerate(p.people[fr]):
            for c, sk in enumerate(person):
                assert (sk < 0) or ident[c, sk] == g


def test_choose_combined_threshold_and_the_record(tmp_path):
    # Camera 0 sees A and B, camera 1 sees A and a false detection X (the frame of the GAT
    # threshold test). A-A: GAT 0.9 at 50 px (combined 0.32); the false pairs: GAT 0 at 90 px
    # (0.035), past the 80 px cutoff.
    identity, count = np.array([[[0, 1], [0, -1]]]), np.array([[2, 2]])
    rows = np.array([[0, 0, 0, 1, 0], [0, 0, 1, 1, 1], [0, 0, 0, 1, 1], [0, 0, 1, 1, 0]])
    gat, d = np.array([0.9, 0.0, 0.0, 0.0]), np.array([50.0, 90.0, 90.0, 90.0])
    cfg = CombinedConfig(epipolar_cutoff_px=80.0)
    best, ari = choose_combined_threshold(rows, gat, d, d, identity, count, config=cfg)
    for th, value in ari.items():  # each threshold's ARI is its proposals' (fallback included)
        p, used = propose_combined(
            rows, gat, d, d, count, config=dataclasses.replace(cfg, threshold=th)
        )
        assert matching_scores(identity, p.identity, count)["ari"] == value
        # At 0.4 the blend joins nobody: the frame falls back to the epipolar grouping (A-A
        # alone), which agrees better with the geometry. At 0.02 it also joins B-X, whose pairs
        # across to A-A are above 0.02 as well: a duplicate of A-A, left out (A-A alone again).
        assert used.tolist() == [th >= 0.4]
        if th == 0.02:
            off = dataclasses.replace(cfg, threshold=th, drop_duplicates=False)
            assert propose_combined(rows, gat, d, d, count, config=off)[1].tolist() == [True]
    assert all(v == pytest.approx(1.0) for v in ari.values()) and best == 0.2  # ties: nearest
    assert (
        choose_combined_threshold(
            rows, gat, d, d, identity, count, config=dataclasses.replace(cfg, threshold=0.6)
        )[0]
        == 0.6
    )
    cfg = CombinedConfig(threshold=best, epipolar_cutoff_px=80.0)
    write_proposal_threshold(tmp_path, 0.3, {0.3: 0.9}, 6, combined=cfg, combined_ari=ari)
    assert read_combined_config(tmp_path) == cfg
    assert read_combined_config(None) == CombinedConfig()
    assert read_combined_config(tmp_path / "elsewhere") == CombinedConfig()
    off = dataclasses.replace(cfg, repair_splits=False, drop_duplicates=False)  # its own switches
    write_proposal_threshold(tmp_path, 0.3, {0.3: 0.9}, 6, combined=off, combined_ari=ari)
    assert read_combined_config(tmp_path) == off
    (tmp_path / PROPOSAL_THRESHOLD_FILE).write_text('{"threshold": 0.3, "combined": 3}')
    with pytest.raises(InputError, match="combined"):
        read_combined_config(tmp_path)
    # A switch written by hand as a string is refused, not read as true.
    bad = '{"threshold": 0.3, "combined": {"threshold": 0.2, "repair_splits": "false"}}'
    (tmp_path / PROPOSAL_THRESHOLD_FILE).write_text(bad)
    with pytest.raises(InputError, match="repair_splits must be true or false"):
        read_combined_config(tmp_path)


# --------------------------------------------------------------------------- average linkage


def _linked_by_definition(score, valid, camera, threshold):
    """Average linkage written out: groups as sets, every candidate pair's mean recomputed."""
    groups = [{i} for i in np.nonzero(valid)[0]]
    while True:
        best, pick = -np.inf, None
        for x in range(len(groups)):
            for y in range(x + 1, len(groups)):
                if {camera[i] for i in groups[x]} & {camera[j] for j in groups[y]}:
                    continue
                vals = [score[i, j] for i in groups[x] for j in groups[y]]
                mean = float(np.mean(vals))
                if mean > best + 1e-12:
                    best, pick = mean, (x, y)
        if pick is None or not best > threshold:
            return groups
        x, y = pick
        groups[x] |= groups.pop(y)


@pytest.mark.parametrize("seed", range(4))
def test_linked_proposals_are_average_linkage_by_definition(seed):
    """`propose_people_linked` against average linkage recomputed from scratch at every merge,
    on random frames of 2-4 cameras (scores in [0, 1] on 8 levels, so ties happen)."""
    rng = np.random.default_rng(seed)
    F, C, P = 6, int(rng.integers(2, 5)), 4
    count = rng.integers(0, P + 1, (F, C))
    rows = np.array(
        [
            [f, ca, pa, cb, pb]
            for f in range(F)
            for ca in range(C)
            for cb in range(ca + 1, C)
            for pa in range(count[f, ca])
            for pb in range(count[f, cb])
        ],
        np.int64,
    ).reshape(-1, 5)
    scores = rng.integers(0, 8, len(rows)) / 7.0
    got = propose_people_linked(rows, scores, count, num_skeletons=P, threshold=0.45)
    camera = np.repeat(np.arange(C), P)
    for f in range(F):
        score = np.zeros((C * P, C * P))
        for (_, ca, pa, cb, pb), s in zip(
            rows[rows[:, 0] == f], scores[rows[:, 0] == f], strict=True
        ):
            score[ca * P + pa, cb * P + pb] = score[cb * P + pb, ca * P + pa] = s
        valid = (np.arange(P)[None] < count[f][:, None]).reshape(-1)
        want = {
            frozenset(g) for g in _linked_by_definition(score, valid, camera, 0.45) if len(g) >= 2
        }
        ident = got.identity[f].reshape(-1)
        have = {frozenset(np.nonzero(ident == k)[0].tolist()) for k in range(ident.max() + 1)}
        # Ties may be broken differently only where the means are equal; with these levels the
        # merge order of equal means is the lowest pair first in both.
        assert have == want, (f, have, want)


def test_linkage_weighs_a_persons_pairs_together():
    """Three views: person 0 in views 0 and 1, person 1 in all three, and a false skeleton in
    view 2 that scores above the threshold with person 0's view 1 (0.6) and 0 with its view 0.
    The greedy grouping joins it to person 0 on that one pair; average linkage does not (mean
    0.3)."""
    pairs = {(0, 0, 1, 0): 0.9, (0, 1, 1, 1): 0.9, (0, 1, 2, 1): 0.9, (1, 1, 2, 1): 0.9}
    pairs |= {(1, 0, 2, 0): 0.6}
    rows = np.array(
        [
            [0, ca, pa, cb, pb]
            for ca, cb in ((0, 1), (0, 2), (1, 2))
            for pa in (0, 1)
            for pb in (0, 1)
        ]
    )
    scores = np.array([pairs.get(tuple(r[1:]), 0.0) for r in rows])
    count = np.full((1, 3), 2)
    truth = np.array([[[0, 1], [0, 1], [-1, 1]]])
    greedy = propose_people(rows, scores, count, threshold=0.5)
    linked = propose_people_linked(rows, scores, count, threshold=0.5)
    assert greedy.identity[0, 2, 0] == greedy.identity[0, 1, 0] >= 0
    assert linked.identity[0, 2, 0] == -1
    assert matching_scores(truth, linked.identity, count)["ari"] == pytest.approx(1.0)
    assert matching_scores(truth, greedy.identity, count)["ari"] < 1.0
    # The threshold rule takes either grouping; by default the greedy one.
    assert choose_proposal_threshold(rows, scores, truth, count) == choose_proposal_threshold(
        rows, scores, truth, count, grouping=propose_people
    )
    best, ari = choose_proposal_threshold(
        rows, scores, truth, count, grouping=propose_people_linked
    )
    assert ari[best] == pytest.approx(1.0) and ari[0.5] == pytest.approx(1.0)
    assert ari[0.5] > choose_proposal_threshold(rows, scores, truth, count)[1][0.5]
