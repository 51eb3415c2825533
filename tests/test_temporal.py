"""The learned temporal stage: windows, the network's invariances, the loss's terms, dropout,
training, `refine_tracks` and save/load."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from mvpose_jax.cameras import project_points
from mvpose_jax.data import calibration
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import get_layout
from mvpose_jax.synthetic import generate_single_person_recordings
from mvpose_jax.temporal import (
    TemporalConfig,
    apply_windows,
    init_temporal,
    load_temporal,
    refine_tracks,
    save_temporal,
    track_windows,
)
from mvpose_jax.temporal_training import (
    TemporalBatch,
    TemporalTrainConfig,
    _bone_tables,
    drop_inputs,
    fit_temporal,
    window_terms,
    windows_of_recordings,
    windows_of_tracks,
)
from mvpose_jax.triangulate import triangulate_skeletons_robust

LAY = get_layout("coco18")
SMALL = TemporalConfig(window=8, view_widths=(32,), width=32, dilations=(1, 2))


@pytest.fixture(scope="module")
def rig():
    return calibration.load_rig("panoptic5")


@pytest.fixture(scope="module")
def recordings(rig):
    return generate_single_person_recordings(rig, num_recordings=4, num_frames=24, seed=3)


def _exact_views(rig, xyz):
    """Noise-free detections of (F, K, 3) poses in every camera: (F, C, K, 2), scores 1."""
    px = np.moveaxis(np.asarray(project_points(rig, jnp.asarray(xyz, jnp.float32))), 0, 1)
    return px.astype(np.float32), np.ones(px.shape[:-1], np.float32)


def _truth(recordings):
    gt = recordings[0].ground_truth
    return np.asarray(gt.xyz)[:, 0]  # (F, K, 3)


def _perturbed(model, seed=1, scale=0.05):
    """The model with random (non-zero) output weights, so that it is not the identity."""
    leaves, tree = jax.tree.flatten(model.params)
    keys = jax.random.split(jax.random.key(seed), len(leaves))
    leaves = [a + scale * jax.random.normal(k, a.shape) for a, k in zip(leaves, keys, strict=True)]
    return model._replace(params=jax.tree.unflatten(tree, leaves))


def test_windows_cover_each_track_once_per_frame_with_tent_weights():
    F, G = 30, 3
    track = np.full((F, G), -1)
    valid = np.zeros((F, G), bool)
    track[2:27, 0], valid[2:27, 0] = 7, True  # 25 frames
    valid[10:13, 0] = False  # a gap inside the track
    track[:5, 2], valid[:5, 2] = 4, True  # shorter than a window
    win = track_windows(track, valid, 8)
    seen = np.zeros(F * G)
    np.add.at(seen, win.rows[win.rows >= 0], 1)
    people = (valid & (track >= 0)).reshape(-1)
    assert (seen[people] >= 1).all() and (seen[~people] == 0).all()
    # Track 7: 25 frames, windows of 8 by 4 -> starts 0, 4, ..., 16 and one aligned to the end.
    t7 = [r for r in win.rows if (r >= 0).any() and (r[r >= 0][0] % G) == 0]
    assert len(t7) == 6
    assert all(w[r >= 0].min() >= 1 for w, r in zip(win.weight, win.rows, strict=True))
    assert (win.weight[win.rows < 0] == 0).all()
    # Slots never mix tracks.
    for r in win.rows:
        assert len({int(x) % G for x in r[r >= 0]}) == 1


def test_untrained_model_returns_the_triangulation_of_exact_views(rig, recordings):
    truth = _truth(recordings)[:8]  # (8, K, 3)
    xy, score = _exact_views(rig, truth)
    model = init_temporal(18, SMALL, rig=rig)
    net = nnx.merge(model.graphdef, model.params, model.rest)
    out = apply_windows(net, rig, xy[None], score[None], np.ones((1, 8), bool))
    np.testing.assert_allclose(np.asarray(out)[0], truth, atol=2e-3)


def test_camera_order_does_not_matter(rig, recordings):
    truth = _truth(recordings)[:8]
    xy, score = _exact_views(rig, truth)
    xy = xy + np.random.default_rng(0).normal(0, 2.0, xy.shape).astype(np.float32)
    score[3, 1] = 0.0  # a view missing in one frame
    model = _perturbed(init_temporal(18, SMALL, rig=rig))
    net = nnx.merge(model.graphdef, model.params, model.rest)
    present = np.ones((1, 8), bool)
    a = apply_windows(net, rig, xy[None], score[None], present)
    order = [3, 0, 4, 1, 2]
    b = apply_windows(
        net, rig.select(order), xy[None][:, :, order], score[None][:, :, order], present
    )
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-4)
    assert float(jnp.abs(a - truth[None]).max()) > 1e-3  # the perturbed model is not the identity


def test_loss_terms_vanish_for_the_truth(rig, recordings):
    truth = _truth(recordings)[:8]
    xy, score = _exact_views(rig, truth)
    batch = TemporalBatch(xy[None], score[None], np.ones((1, 8), bool))
    bones, pairs = _bone_tables("coco18")
    rep, px, bone, sym, ok = window_terms(
        rig, jnp.asarray(truth[None]), batch, bones, pairs, 1.0, 100.0
    )
    assert float(px[0]) < 1e-2 and bool(ok[0])
    assert float(bone[0]) < 1e-2  # a rigid body: constant bone lengths (to 1 mm)
    # A body stretched in one frame: its bones vary.
    moved = truth.copy()
    knee, ankle = LAY.keypoints.index("l_knee"), LAY.keypoints.index("l_ankle")
    shank = moved[4, ankle] - moved[4, knee]
    moved[4, ankle] += 0.1 * shank / np.linalg.norm(shank)  # one shank 10 cm longer, one frame
    _, px2, bone2, _, _ = window_terms(
        rig, jnp.asarray(moved[None]), batch, bones, pairs, 1.0, 100.0
    )
    # Its variance, 7/64 of 100 cm^2, averaged over the bones.
    J = len(bones)
    assert float(px2[0]) > float(px[0])
    np.testing.assert_allclose(float(bone2[0]), 100 * 7 / 64 / J, rtol=0.05)
    # Mirrored bones of a generated body are equal to within its build.
    assert float(sym[0]) < 4.0


def test_dropout_only_removes_detections(rig):
    score = np.random.default_rng(0).uniform(0.1, 1.0, (6, 8, 5, 18)).astype(np.float32)
    given = np.asarray(drop_inputs(jax.random.key(0), jnp.asarray(score), TemporalTrainConfig()))
    assert ((given == score) | (given == 0)).all()
    assert (given == 0).any()
    none = TemporalTrainConfig(view_drop=0.0, keypoint_drop=0.0, run_drop=0.0)
    np.testing.assert_array_equal(
        np.asarray(drop_inputs(jax.random.key(0), jnp.asarray(score), none)), score
    )


@pytest.fixture(scope="module")
def trained(rig, recordings):
    # Scored on its own windows: a few steps on three short recordings fit them, not more.
    train = windows_of_recordings(recordings[:3], SMALL.window)
    config = TemporalTrainConfig(steps=40, batch_size=8, eval_every=10)
    return fit_temporal(rig, train, train, SMALL, config)


def test_training_lowers_the_loss(trained):
    model, record = trained
    assert record["dev_loss"] < record["initial_dev_loss"]
    assert record["best_step"] > 0 and record["train_windows"] > 0


def test_refine_tracks_blends_with_robust_triangulation_and_round_trips(
    rig, recordings, trained, tmp_path
):
    model, record = trained
    rec = recordings[0]
    from mvpose_jax.features import main_skeletons

    xy, score = main_skeletons(np.asarray(rec.detections.xy), np.asarray(rec.detections.score))
    F = len(score)
    xy, score = xy[:, None], score[:, None]  # (F, 1, C, K, ...)
    valid = (score > 0).any(-1).sum(-1) >= 2
    track = np.where(valid, 0, -1)
    out, from_tri = refine_tracks(model, rig, xy, score, track, valid, method="blend")
    tri, ok, _ = triangulate_skeletons_robust(
        rig, np.moveaxis(xy[:, 0], 1, 0), np.moveaxis(score[:, 0], 1, 0)
    )
    tri, ok = np.asarray(tri), np.asarray(ok)
    sel = from_tri[:, 0] & valid[:, :1]
    assert sel.any()
    np.testing.assert_allclose(out[:, 0][sel], tri[sel], atol=1e-4)
    np.testing.assert_array_equal(from_tri[:, 0], ok & valid[:, :1])
    alone, none = refine_tracks(model, rig, xy, score, track, valid, method="alone")
    assert not none.any() and np.isfinite(alone[valid]).all()
    assert (alone[~valid] == 0).all()
    save_temporal(tmp_path / "t", model, record)
    save_temporal(tmp_path / "t", model, record)  # over an older model: replaced whole
    again = load_temporal(tmp_path / "t", rig)
    alone2, _ = refine_tracks(again, rig, xy, score, track, valid, method="alone")
    np.testing.assert_allclose(alone2, alone, atol=1e-6)
    # Windows of the tracks as fine-tuning data: every window holds one track's frames.
    ft = windows_of_tracks(xy, score, track, valid, SMALL.window)
    assert len(ft.present) >= F // SMALL.window and ft.present.any(1).all()
    with pytest.raises(InputError, match="keypoints"):
        refine_tracks(model, rig, xy[..., :17, :], score[..., :17], track, valid)
    with pytest.raises(InputError, match="method"):
        refine_tracks(model, rig, xy, score, track, valid, method="mean")
    with pytest.raises(InputError, match="temporal model"):
        load_temporal(tmp_path / "nothing", rig)


@pytest.mark.slow
def test_experiment_smoke_writes_its_tables(tmp_path):
    """``python -m experiments.temporal --scale smoke --parts synthetic``: every row on both
    splits, the choice made on validation, the chosen variant over seeds on test."""
    import json

    from experiments.temporal import VARIANTS, main

    main(["--out", str(tmp_path), "--scale", "smoke", "--parts", "synthetic"])
    report = json.loads((tmp_path / "temporal.json").read_text())
    syn = report["synthetic"]
    for split in ("validation", "test"):
        rows = syn["tables"][split]
        assert {"robust triangulation", "blend", "blend + Butterworth"} <= set(rows)
        assert all(f"temporal ({v}), blend + Butterworth" in rows for v in VARIANTS)
        assert all(np.isfinite(r["mpjpe_mm"]) for r in rows.values())
    assert syn["chosen_on_validation"] in syn["tables"]["validation"]
    assert syn["chosen_variant"] in VARIANTS and len(syn["test_over_seeds"]["seeds"]) == 2
    assert "### test scenes" in (tmp_path / "temporal.md").read_text()


def test_for_rig_turns_the_rig_up_to_z_and_leaves_the_model_alone(rig):
    from mvpose_jax.cameras import up_vector
    from mvpose_jax.synthetic.rigs import random_rig
    from mvpose_jax.temporal import for_rig

    def rotation(m):
        return np.asarray(nnx.merge(m.graphdef, m.params, m.rest).rotation[...])

    model = init_temporal(18, SMALL, rig=rig)
    q = rotation(model)
    np.testing.assert_allclose(q @ up_vector(rig), [0, 0, 1], atol=1e-6)
    other, _ = random_rig("ring", seed=1)  # z-up
    turned = for_rig(model, other)
    np.testing.assert_allclose(rotation(turned), np.eye(3), atol=1e-6)
    np.testing.assert_array_equal(rotation(model), q)
