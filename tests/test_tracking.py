"""The tracker: constant ids through crossings and slot swaps, entering and leaving, gaps shorter
and longer than the limit, chunks, and one track per true person on a synthetic recording."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mvpose_jax.data.calibration import load_rig
from mvpose_jax.inference import run_pipeline
from mvpose_jax.synthetic import generate_recording
from mvpose_jax.tracking import (
    TrackingConfig,
    initial_state,
    metres_per_pixel,
    track_frames,
    update_tracks,
)

FPS = 30.0
# A small rigid body: keypoint offsets (K, 3) around a root, metres.
BODY = np.array(
    [[0, 0, 1.7], [0.2, 0, 1.4], [-0.2, 0, 1.4], [0.1, 0, 0.9], [-0.1, 0, 0.9], [0, 0, 0.1]]
)


def _walk(start, velocity, frames):
    """(F, K, 3) the body moving at constant velocity (m/s) from start."""
    t = np.arange(frames)[:, None] / FPS
    root = np.asarray(start)[None] + t * np.asarray(velocity)[None]
    return root[:, None] + BODY[None]


def _frames(people, present):
    """People (list of (F, K, 3)) and presence (list of (F,) bool) -> slot-major xyz, kv, valid,
    truth: each frame's present people packed into the first slots, in a rotating order."""
    F, K = people[0].shape[:2]
    G = len(people)
    xyz = np.zeros((F, G, K, 3))
    valid = np.zeros((F, G), bool)
    truth = np.full((F, G), -1)
    for f in range(F):
        here = [i for i in range(G) if present[i][f]]
        here = here[f % max(len(here), 1) :] + here[: f % max(len(here), 1)]  # slots rotate
        for g, i in enumerate(here):
            xyz[f, g], valid[f, g], truth[f, g] = people[i][f], True, i
    kv = np.repeat(valid[..., None], K, axis=-1)
    return xyz, kv, valid, truth


def _track(xyz, kv, valid, config=TrackingConfig()):
    _, track = track_frames(
        initial_state(kv.shape[-1]),
        times=np.arange(len(valid)) / FPS,
        xyz=xyz,
        keypoint_valid=kv,
        valid=valid,
        config=config,
    )
    return track


def _ids_of(track, truth, person):
    """The track ids a person got (-1, a tentative track's first frames, left out)."""
    ids = track[truth == person]
    return set(np.unique(ids[ids >= 0]).tolist())


def test_people_crossing_with_slots_swapped_every_frame_keep_their_ids():
    # Two people walk towards each other and pass 0.45 m apart; a third stands still nearby.
    F = 90
    a = _walk([-2.0, 0.0, 0.0], [1.4, 0.0, 0.0], F)
    b = _walk([2.0, 0.45, 0.0], [-1.4, 0.0, 0.0], F)
    c = _walk([0.0, 1.5, 0.0], [0.0, 0.0, 0.0], F)
    rng = np.random.default_rng(0)
    people = [p + rng.normal(0, 0.01, p.shape) for p in (a, b, c)]
    xyz, kv, valid, truth = _frames(people, [np.ones(F, bool)] * 3)
    assert (truth[1:, 0] != truth[:-1, 0]).all()  # the slot order changes every frame
    track = _track(xyz, kv, valid)
    assert [_ids_of(track, truth, i) for i in range(3)] == [{0}, {1}, {2}]
    assert (track[~valid] == -1).all()
    # Every frame is labelled: the first two, tentative until the third (`confirm_hits`), get
    # the id once it is confirmed (`backfill`) ...
    assert (track[valid] >= 0).all()
    # ... which is all a strictly causal consumer cannot do.
    causal = _track(xyz, kv, valid, TrackingConfig(backfill=False))
    assert (causal[:2][valid[:2]] == -1).all() and (causal[2:] == track[2:]).all()


def test_entering_leaving_and_gaps_shorter_and_longer_than_the_limit():
    F = 120
    a = _walk([-1.0, 0.0, 0.0], [0.5, 0.0, 0.0], F)
    # (b passes 0.5 m from a: nearer, it would be taken for a part of a, see `split_m`)
    b = _walk([1.5, 1.0, 0.0], [0.0, -0.3, 0.0], F)
    present_a = np.ones(F, bool)
    present_b = np.zeros(F, bool)
    present_b[10:40] = True  # enters at 10
    present_b[55:70] = True  # back after 15 frames (0.5 s): the same person
    present_b[110:] = True  # back after 40 frames (1.33 s): a new track
    xyz, kv, valid, truth = _frames([a, b], [present_a, present_b])
    # Without re-linking (tested on its own below), the gap limit alone decides.
    track = _track(xyz, kv, valid, TrackingConfig(max_gap_s=1.0, relink_gap_s=0.0))
    assert _ids_of(track, truth, 0) == {0}
    f_b, g_b = np.nonzero(truth == 1)
    ids_b = track[f_b, g_b]
    assert (ids_b[f_b < 70] == 1).all()  # tentative at 10 and 11, labelled once confirmed
    assert set(ids_b[f_b >= 112]) == {2}  # never reused, never the old id
    # The limit is the configured one: with 2 s the third appearance keeps its id.
    track = _track(xyz, kv, valid, TrackingConfig(max_gap_s=2.0, relink_gap_s=0.0))
    assert _ids_of(track, truth, 1) == {1}


def test_a_frame_without_anyone_and_a_person_with_few_keypoints():
    F = 30
    a = _walk([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], F)
    xyz, kv, valid, truth = _frames([a], [np.ones(F, bool)])
    valid[10] = False
    kv[10] = False
    kv[15:18, 0, 2:] = False  # two keypoints only: matched by the centre
    track = _track(xyz, kv, valid)
    assert set(track[2:][valid[2:]].tolist()) == {0} and track[10, 0] == -1


def test_chunks_carry_the_state():
    F = 60
    people = [
        _walk([-2.0, 0.0, 0.0], [1.4, 0.0, 0.0], F),
        _walk([2.0, 0.45, 0.0], [-1.4, 0.0, 0.0], F),
    ]
    present = [np.ones(F, bool), np.r_[np.ones(20, bool), np.zeros(10, bool), np.ones(30, bool)]]
    xyz, kv, valid, _ = _frames(people, present)
    whole = _track(xyz, kv, valid)
    state, parts = initial_state(kv.shape[-1]), []
    for s in (slice(0, 7), slice(7, 25), slice(25, 60)):
        state, t = track_frames(
            state,
            times=np.arange(F)[s] / FPS,
            xyz=xyz[s],
            keypoint_valid=kv[s],
            valid=valid[s],
        )
        parts.append(t)
    np.testing.assert_array_equal(np.concatenate(parts), whole)
    assert state.next_id == 2


def test_the_gate_refuses_a_jump_and_the_2d_evidence_decides_between_near_people():
    at_once = TrackingConfig(confirm_hits=1)  # every person is a track from its first frame
    state = initial_state(len(BODY), 1)
    here = BODY[None] + np.array([0.0, 0.0, 0.0])
    state, ids = update_tracks(
        state, time=0.0, xyz=here, keypoint_valid=np.ones((1, 6), bool), config=at_once
    )
    # 1 m away one frame later: a new person, not the same one.
    far = here + np.array([1.0, 0.0, 0.0])
    state2, ids2 = update_tracks(
        state, time=1 / FPS, xyz=far, keypoint_valid=np.ones((1, 6), bool), config=at_once
    )
    assert ids.tolist() == [0] and ids2.tolist() == [1]

    # Two tracks 0.3 m apart; the new frame's two people are halfway between in 3D (equal 3D
    # cost either way), but their 2D skeletons in the one camera are those of the tracks.
    state = initial_state(len(BODY), 1)
    two = np.stack([BODY, BODY + [0.3, 0.0, 0.0]])
    xy = np.stack([np.zeros((1, 6, 2)), np.full((1, 6, 2), 100.0)])
    sc = np.ones((2, 1, 6))
    per_px = np.full((2, 1), 0.003)
    kv = np.ones((2, 6), bool)
    state, ids = update_tracks(
        state,
        time=0.0,
        xyz=two,
        keypoint_valid=kv,
        xy=xy,
        score=sc,
        metres_per_px=per_px,
        config=at_once,
    )
    mid = np.stack([BODY + [0.15, 0.0, 0.0]] * 2)
    state, ids = update_tracks(
        state,
        time=1 / FPS,
        xyz=mid,
        keypoint_valid=kv,
        xy=xy[::-1] + 1.0,
        score=sc,
        metres_per_px=per_px,
        config=at_once,
    )
    assert ids.tolist() == [1, 0]


def _track_people(frames, config=TrackingConfig()):
    """Frames as lists of (K, 3) people (K = 6, all keypoints valid unless NaN) -> per frame the
    list of track ids, by `update_tracks` one frame at a time."""
    state, out = initial_state(len(BODY)), []
    for f, people in enumerate(frames):
        xyz = np.asarray(people, float).reshape(-1, len(BODY), 3)
        kv = ~np.isnan(xyz).any(-1)
        state, ids = update_tracks(
            state, time=f / FPS, xyz=np.nan_to_num(xyz), keypoint_valid=kv, config=config
        )
        out.append(ids.tolist())
    return out


def test_a_ghost_lasting_one_or_two_frames_makes_no_track():
    F = 20
    a = _walk([-1.0, 0.0, 0.0], [0.5, 0.0, 0.0], F)
    b = _walk([1.0, 0.0, 0.0], [-0.5, 0.0, 0.0], F)
    ghost = BODY + [0.0, 1.2, 0.0]  # between and beside them: a wrong grouping
    frames = [[a[f], b[f]] for f in range(F)]
    frames[8] = frames[8] + [ghost]  # one frame
    frames[14] = frames[14] + [ghost]  # two frames
    frames[15] = frames[15] + [ghost + 0.01]
    ids = _track_people(frames)
    assert all(f[2] == -1 for f in ids if len(f) == 3)  # the ghost: never a track id
    assert [f[:2] for f in ids[2:]] == [[0, 1]] * (F - 2)
    # Without confirmation the ghost is a track.
    ids = _track_people(frames, TrackingConfig(confirm_hits=1))
    assert {f[2] for f in ids if len(f) == 3} == {2}
    # A person who stays is confirmed at the third frame, and keeps the id.
    ids = _track_people([[a[f]] for f in range(F)])
    assert [f[0] for f in ids] == [-1, -1] + [0] * (F - 2)
    # Over a chunk (`track_frames`), the people's tentative first frames get their ids once
    # confirmed, and the ghost's frames still get none.
    G = 3
    xyz = np.zeros((F, G, len(BODY), 3))
    valid = np.zeros((F, G), bool)
    for f, people in enumerate(frames):
        xyz[f, : len(people)], valid[f, : len(people)] = people, True
    kv = np.broadcast_to(valid[..., None], xyz.shape[:-1]).copy()
    state, track = track_frames(
        initial_state(len(BODY)), times=np.arange(F) / FPS, xyz=xyz, keypoint_valid=kv, valid=valid
    )
    assert (track[:, :2] == [0, 1]).all()
    assert (track[:, 2] == -1).all() and state.next_id == 2


def test_a_person_proposed_twice_keeps_one_id_on_the_better_supported_proposal():
    F = 20
    a = _walk([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], F)
    part = lambda p, keep: np.where(np.isin(np.arange(len(BODY)), keep)[:, None], p, np.nan)  # noqa: E731
    frames = [[a[f]] for f in range(F)]
    for f in range(6, 14):
        # Two proposals of the one person from different views: an upper-body fragment, and
        # from frame 10 on the fragment holds more keypoints than the other proposal.
        if f < 10:
            frames[f] = [a[f], part(a[f] + 0.02, [0, 1, 2])]
        else:
            frames[f] = [part(a[f], [0, 1, 2]), a[f] + 0.02]
    ids = _track_people(frames)
    assert [f for f in ids[6:10]] == [[0, -1]] * 4
    assert [f for f in ids[10:14]] == [[-1, 0]] * 4
    assert {i for f in ids for i in f} == {-1, 0}
    # Without it, the second proposal becomes a track of its own.
    ids = _track_people(frames, TrackingConfig(split_m=0.0))
    assert {i for f in ids for i in f} == {-1, 0, 1}


def test_a_track_lost_beyond_the_gap_is_relinked_by_body_size():
    # Person a (the BODY) and a larger person c; a is unseen for 1.5 s (beyond max_gap_s) and
    # comes back 0.5 m from where it was lost, while c walks in just where a was lost.
    big = np.diag([1.3, 1.3, 1.3])
    F = 120
    a = _walk([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], F)
    c = _walk([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], F) @ big.T
    frames = [[a[f]] for f in range(30)] + [[] for _ in range(45)]
    frames += [[c[f] + [0.05, 0.0, 0.0], a[f] + [0.5, 0.0, 0.0]] for f in range(75, F)]
    ids = _track_people(frames)
    assert [f for f in ids[80:]] == [[1, 0]] * (F - 80)  # a keeps id 0, c is new
    # By position alone (no body size) the nearer one, c, would take a's id.
    ids = _track_people(frames, TrackingConfig(relink_size_tolerance=np.inf))
    assert [f for f in ids[80:]] == [[0, 1]] * (F - 80)
    # Without re-linking, a comes back as a new track.
    ids = _track_people(frames, TrackingConfig(relink_gap_s=0.0))
    assert sorted({i for f in ids[80:] for i in f}) == [1, 2]


def test_stale_keypoints_are_forgotten():
    # The first frame's legs are 1.5 m off (a wrong grouping); they are "off" in every later
    # match, so without forgetting the track keeps them; later only the legs and one hip are
    # seen, and the stale legs decide the match.
    F = 90
    a = _walk([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], F)
    first = a[0].copy()
    first[3:] += [1.5, 0.0, 0.0]
    legs = np.where(np.isin(np.arange(len(BODY)), [2, 3, 4, 5])[:, None], a[0], np.nan)
    frames = [[first]] + [[a[f]] for f in range(1, 60)] + [[legs]] * (F - 60)
    config = TrackingConfig(relink_gap_s=0.0)
    ids = _track_people(frames, config)
    assert {i for f in ids[2:] for i in f} == {0}
    ids = _track_people(frames, dataclasses.replace(config, keypoint_ttl_s=np.inf))
    assert {i for f in ids[60:] for i in f} != {0}


def test_metres_per_pixel_is_depth_over_focal():
    point = np.array([0.3, -1.0, 0.2])
    # Each rig in turn, twice: its host copies of the cameras are kept per rig, never mixed.
    for name in ("panoptic5", "arplab6", "panoptic5", "arplab6"):
        rig = load_rig(name)
        got = metres_per_pixel(rig, point)
        R, t, K = (np.asarray(a) for a in (rig.R, rig.t, rig.K))
        depth = (R @ point + t)[:, 2]
        np.testing.assert_allclose(got, depth / ((K[:, 0, 0] + K[:, 1, 1]) / 2))
    assert metres_per_pixel(rig.select(rig.names[:2]), point).shape == (2,)


@pytest.mark.slow  # the geometric pipeline over 60 frames of 3 people (a few seconds)
def test_one_track_per_true_person_on_a_synthetic_recording():
    rig = load_rig("panoptic5")
    rec = generate_recording(rig, num_people=3, num_frames=60, seed=[7, 3, 3])
    res = run_pipeline(rig, rec.detections, tracking=TrackingConfig(), chunk_frames=60)
    chunked = run_pipeline(rig, rec.detections, tracking=TrackingConfig(), chunk_frames=16)
    np.testing.assert_array_equal(chunked.track, res.track)
    # Each reconstructed person's true identity: the majority of its skeletons' identities.
    f, g, c = np.nonzero(res.members >= 0)
    truth_of_skel = np.asarray(rec.identity)[f, c, res.members[f, g, c]]
    votes = np.zeros(res.members.shape[:2] + (3,), int)
    ok = truth_of_skel >= 0
    np.add.at(votes, (f[ok], g[ok], truth_of_skel[ok]), 1)
    valid = np.asarray(res.poses.valid) & (votes.sum(-1) > 0)
    truth = votes.argmax(-1)
    for person in range(3):
        ids, counts = np.unique(res.track[valid & (truth == person)], return_counts=True)
        main = ids[counts.argmax()]
        assert counts.max() >= 0.95 * counts.sum()  # one track holds (almost) all of the person
        # and that track is (almost) only this person
        others = (res.track == main) & valid & (truth != person)
        assert others.sum() <= 0.05 * counts.max()


def test_the_compiled_costs_equal_their_definition():
    """`_match_costs` (numba) against the costs written out in numpy: the lower median of the
    shared keypoints' distances (the centres' distance with fewer than 3 shared), blended with
    the per-camera mean pixel distance in metres where 3+ keypoints are shared and the track was
    seen in the previous frame."""
    from mvpose_jax.tracking import _match_costs, _row_medians

    rng = np.random.default_rng(0)
    T, D, C, K, min_common, w = 3, 4, 2, 6, 3, 0.5
    pred, xyz = rng.normal(size=(T, K, 3)), rng.normal(size=(D, K, 3))
    kv_track, kv = rng.random((T, K)) < 0.7, rng.random((D, K)) < 0.7
    kv[0, :] = False
    kv[1, :2], kv[1, 2:] = True, False  # fewer shared keypoints than min_common
    t_xy, xy = (rng.normal(0, 50, (n, C, K, 2)).astype(np.float32) for n in (T, D))
    t_score = (rng.random((T, C, K)) < 0.8).astype(np.float32)
    score = (rng.random((D, C, K)) < 0.8).astype(np.float32)
    per_px = rng.uniform(0.001, 0.01, (D, C))
    per_px[2, 0] = np.inf  # behind camera 0
    recent = np.array([True, True, False])
    dist, d3, cost = _match_costs(
        pred, kv_track, xyz, kv, min_common, t_xy, t_score, recent, xy, score, per_px, w
    )

    def centre(p, v):
        return p[v].mean(0) if v.any() else np.zeros(3)

    for t in range(T):
        for d in range(D):
            e = np.linalg.norm(pred[t] - xyz[d], axis=-1)
            np.testing.assert_allclose(dist[t, d], e)
            shared = np.sort(e[kv_track[t] & kv[d]])
            if len(shared) >= min_common:
                want = shared[(len(shared) - 1) // 2]
            else:
                want = np.linalg.norm(centre(pred[t], kv_track[t]) - centre(xyz[d], kv[d]))
            assert d3[t, d] == pytest.approx(want)
            views = []
            for c in range(C):
                both = (t_score[t, c] > 0) & (score[d, c] > 0)
                if recent[t] and both.sum() >= min_common and np.isfinite(per_px[d, c]):
                    px = np.linalg.norm(t_xy[t, c] - xy[d, c], axis=-1)[both].mean()
                    views.append(px * per_px[d, c])
            if views:
                want = (1 - w) * want + w * np.mean(views)
            assert cost[t, d] == pytest.approx(want, rel=1e-5)
    values, mask = rng.normal(size=(5, 7)), rng.random((5, 7)) < 0.5
    mask[0] = False
    for row, got in zip(range(5), _row_medians(values, mask), strict=True):
        kept = np.sort(values[row][mask[row]])
        assert got == (kept[(len(kept) - 1) // 2] if len(kept) else np.inf)


def _busy_scene(seed, F=150, G=7, C=5):
    """A crowded chunk: people walking in and out (gaps shorter and longer than the limits),
    passing near each other, missing keypoints, a person sometimes proposed twice, ghosts, slots
    shuffled every frame, with 2D evidence in C cameras. Returns times, xyz, kv, valid, xy,
    score."""
    rng = np.random.default_rng(seed)
    K = len(BODY)
    N = G - 2  # true people; the other slots hold fragments and ghosts
    start = rng.uniform(-1.5, 1.5, (N, 3)) * [1, 1, 0]
    velocity = rng.normal(0, 0.6, (N, 3)) * [1, 1, 0]
    times = np.arange(F) / FPS
    root = start[:, None] + times[None, :, None] * velocity[:, None]  # (N, F, 3)
    people = root[..., None, :] + BODY * rng.uniform(0.9, 1.2, (N, 1, 1, 1))
    present = np.ones((N, F), bool)
    for i in range(N):
        for _ in range(rng.integers(0, 3)):
            a = rng.integers(0, F)
            present[i, a : a + rng.integers(1, 60)] = False
    xyz = np.zeros((F, G, K, 3))
    kv = np.zeros((F, G, K), bool)
    valid = np.zeros((F, G), bool)
    xy = np.zeros((F, G, C, K, 2), np.float32)
    score = np.zeros((F, G, C, K), np.float32)
    cams = rng.uniform(-300, 300, (C, 1, 2))
    for f in range(F):
        here = [people[i, f] + rng.normal(0, 0.01, (K, 3)) for i in range(N) if present[i, f]]
        if here and rng.random() < 0.15:  # a fragment of someone, 0-10 cm off
            j = rng.integers(len(here))
            here.append(np.where(np.arange(K)[:, None] < 3, here[j] + 0.05, np.nan))
        if rng.random() < 0.08:  # a ghost
            here.append(BODY + rng.uniform(-2, 2, 3) * [1, 1, 0])
        slots = rng.permutation(G)[: len(here)]
        for g, p in zip(slots, here, strict=False):
            p = np.where(rng.random((K, 1)) < 0.1, np.nan, p)  # missed keypoints
            kv[f, g] = ~np.isnan(p).any(-1)
            xyz[f, g] = np.nan_to_num(p)
            valid[f, g] = True
            xy[f, g] = 100 * xyz[f, g, None, :, :2] + cams
            score[f, g] = kv[f, g] * (rng.random((C, K)) < 0.9)
    return times, xyz, kv, valid, xy, score


@pytest.mark.parametrize("views", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_chunk_is_its_frames_one_at_a_time_bit_for_bit(seed, views, monkeypatch):
    """`track_frames` takes the frames of people already tracked in one compiled loop
    (`_steady_frames`) and the others through `_update_tracks`: its ids and final state are
    those of `update_tracks` called frame by frame (backfill off), bit for bit, and with
    backfill its ids are those frames' ids with each confirmed track's tentative frames
    labelled."""
    from mvpose_jax import tracking

    rig = load_rig("panoptic5")
    times, xyz, kv, valid, xy, score = _busy_scene(seed)
    F, G = valid.shape
    evidence = dict(xy=xy, score=score, rig=rig) if views else {}
    per_px = metres_per_pixel(
        rig, (xyz * kv[..., None]).sum(-2) / np.maximum(kv.sum(-1), 1)[..., None]
    )
    causal = TrackingConfig(backfill=False)

    state = initial_state(len(BODY), rig.num_cameras if views else 0)
    want = np.full((F, G), -1, np.int32)
    serials = np.full((F, G), -1)
    for f in range(F):
        (d,) = np.nonzero(valid[f])
        state, ids, serial = tracking._update_tracks(
            state,
            time=float(times[f]),
            xyz=xyz[f, d],
            keypoint_valid=kv[f, d],
            xy=xy[f, d] if views else None,
            score=score[f, d] if views else None,
            metres_per_px=per_px[f, d] if views else None,
            config=causal,
        )
        want[f, d], serials[f, d] = ids, serial

    calls = []
    original = tracking._update_tracks

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(tracking, "_update_tracks", counted)
    got_state, got = track_frames(
        initial_state(len(BODY)),
        times=times,
        xyz=xyz,
        keypoint_valid=kv,
        valid=valid,
        config=causal,
        **evidence,
    )
    monkeypatch.undo()
    np.testing.assert_array_equal(got, want)
    for field in dataclasses.fields(state):
        np.testing.assert_array_equal(getattr(got_state, field.name), getattr(state, field.name))
    # Both paths were taken: the eventful frames in Python, the others in the compiled loop.
    assert 5 < len(calls) < F - 30
    assert len(np.unique(want[want >= 0])) >= 5

    # Backfill: a confirmed track's tentative frames get its id; a ghost's stay -1.
    _, filled = track_frames(
        initial_state(len(BODY)), times=times, xyz=xyz, keypoint_valid=kv, valid=valid, **evidence
    )
    id_of_serial = {s: i for s, i in zip(serials[want >= 0], want[want >= 0], strict=True)}
    expect = np.where(
        want >= 0,
        want,
        [[id_of_serial.get(s, -1) if s >= 0 else -1 for s in row] for row in serials],
    )
    np.testing.assert_array_equal(filled, expect)


# ------------------------------------------------------------------- track-level association


@pytest.mark.parametrize("density", [0.15, 0.4, 0.8])
def test_assignment_is_scipys_on_the_whole_gated_matrix(density):
    """`_assign` (with its shortcuts: one pair, and allowed pairs that already form a matching)
    against `scipy.optimize.linear_sum_assignment` on the whole cost matrix, the disallowed
    pairs priced out and dropped afterwards."""
    from scipy.optimize import linear_sum_assignment

    from mvpose_jax.tracking import _NO_MATCH, _assign

    rng = np.random.default_rng(int(density * 100))
    matchings = 0
    for _ in range(300):
        T, D = rng.integers(1, 7, size=2)
        cost = rng.uniform(0, 1, (T, D))
        ok = rng.random((T, D)) < density
        got = np.full(D, -1, np.int64)
        _assign(cost, ok, got)
        want = np.full(D, -1, np.int64)
        rows, cols = linear_sum_assignment(np.where(ok, cost, _NO_MATCH))
        keep = ok[rows, cols]
        want[cols[keep]] = rows[keep]
        np.testing.assert_array_equal(got, want)
        matchings += bool((ok.sum(0) <= 1).all() and (ok.sum(1) <= 1).all())
    assert 10 < matchings < 300  # both paths were taken


def _projections(rig, people):
    """Exact skeletons of (G, F, K, 3) people in every camera: xy (F, C, G, K, 2), score."""
    from mvpose_jax.cameras import project_points

    xyz = np.moveaxis(np.asarray(people, np.float32), 0, 1)  # (F, G, K, 3)
    xy = np.moveaxis(np.asarray(project_points(rig, xyz)), 0, 1)  # (F, C, G, K, 2)
    return xy.astype(np.float32), np.ones(xy.shape[:-1], np.float32)


def test_anchors_hold_missing_frames_and_predict_the_last_frames_tracks():
    from mvpose_jax.tracking import AssociationConfig, track_anchors

    F, G, K = 6, 2, len(BODY)
    a = _walk([0, 0, 0], [1, 0, 0], F)
    xyz = np.zeros((F, G, K, 3))
    xyz[:, 0] = a
    valid = np.zeros((F, G), bool)
    valid[:, 0] = True
    valid[3, 0] = False  # missed in frame 3: held from frame 2 (the earlier on a tie)
    track = np.where(valid, 5, -1)
    # A confirmed track of the last frames, seen at t = -0.1 s, walking at 1 m/s along y.
    state = dataclasses.replace(
        initial_state(K),
        ids=np.array([9]),
        xyz=BODY[None] + np.array([3.0, 0, 0]),
        keypoint_valid=np.ones((1, K), bool),
        velocity=np.array([[0.0, 1.0, 0.0]]),
        last_time=np.array([-0.1]),
    )
    times = np.arange(F) / FPS
    out, ok = track_anchors(
        state,
        times=times,
        track=track,
        valid=valid,
        xyz=xyz,
        keypoint_valid=np.ones((F, G, K), bool),
        config=TrackingConfig(max_gap_s=1.0),
        association=AssociationConfig(hold_frames=1),
    )
    assert out.shape == (F, 2, K, 3) and ok.all()
    np.testing.assert_allclose(out[[0, 1, 2, 4, 5], 0], a[[0, 1, 2, 4, 5]])
    np.testing.assert_allclose(out[3, 0], a[2])
    expected = BODY[None] + np.array([3.0, 0, 0]) + (times + 0.1)[:, None, None] * [0, 1, 0]
    np.testing.assert_allclose(out[:, 1], expected)


def test_skeletons_join_the_tracked_person_they_fit_and_split_people_are_regrouped():
    from mvpose_jax.tracking import AssociationConfig, associate_skeletons, regroup

    rig = load_rig("panoptic5")
    F, C = 3, rig.num_cameras
    people = np.stack([_walk([0.5, 0.0, 0.0], [0, 0, 0], F), _walk([-0.5, 0.5, 0.0], [0, 0, 0], F)])
    people = people[..., [0, 2, 1]] * np.array([1, -1, 1])  # panoptic5 is y-down
    xy, score = _projections(rig, people)
    # A third skeleton far from both in camera 0 (a false positive) fits nobody.
    far = np.concatenate([xy, xy[:, :, :1] + 400.0], axis=2)
    sc = np.concatenate([score, score[:, :, :1]], axis=2)
    owner = associate_skeletons(
        rig, far, sc, np.moveaxis(people, 0, 1), np.ones((F, 2, len(BODY)), bool)
    )
    np.testing.assert_array_equal(owner[:, :, :2], np.broadcast_to([0, 1], (F, C, 2)))
    assert (owner[:, :, 2] == -1).all()
    # The proposals split person 0 over two groups (cameras 0-2 and 3-4); person 1 is whole.
    members = np.full((F, 3, C), -1)
    members[:, 0, :3] = 0
    members[:, 1, 3:] = 0
    members[:, 2, :] = 1
    regrouped = regroup(members, owner[:, :, :2], 2)
    assert regrouped.shape == (F, 2, C)
    np.testing.assert_array_equal(regrouped[:, 0], 0)
    np.testing.assert_array_equal(regrouped[:, 1], 1)
    # Nothing fits within a tiny gate: nobody is taken.
    none = associate_skeletons(
        rig,
        xy + 3.0,
        score,
        np.moveaxis(people, 0, 1),
        np.ones((F, 2, len(BODY)), bool),
        AssociationConfig(gate=1e-3),
    )
    assert (none == -1).all()


def test_association_mends_a_grouping_that_splits_people():
    """Epipolar proposals with a far too strict cutoff split people; track-level association
    gives them back, live and offline."""
    from mvpose_jax.cameras import up_vector
    from mvpose_jax.inference import PipelineConfig
    from mvpose_jax.metrics import pose_metrics
    from mvpose_jax.tracking import AssociationConfig

    rig = load_rig("panoptic5")
    rec = generate_recording(rig, num_people=3, num_frames=40, seed=7)
    scores = {}
    for assoc in (None, AssociationConfig()):
        for chunk in (40, 1):
            config = PipelineConfig.of(
                method="robust", tracking=TrackingConfig(), half_score_px=4.0, chunk_frames=chunk
            )
            res = run_pipeline(rig, rec.detections, dataclasses.replace(config, association=assoc))
            m = pose_metrics(res.poses, rec.ground_truth, up=up_vector(rig))
            scores[(assoc is not None, chunk)] = m["pcp"]
    for chunk in (40, 1):
        assert scores[(True, chunk)] > scores[(False, chunk)] + 10
