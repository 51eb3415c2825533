"""Learned view confidence: features, training, confident triangulation, save/load, the stage."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from mvpose_jax import stages
from mvpose_jax.data import calibration
from mvpose_jax.lifting import LiftingConfig, lift_confident
from mvpose_jax.skeletons import get_layout
from mvpose_jax.synthetic import SyntheticConfig, simulate
from mvpose_jax.triangulate import (
    leave_one_view_out,
    triangulate_points,
    triangulate_skeletons_robust,
)
from mvpose_jax.view_confidence import (
    confident_weights,
    inlier_probability,
    load_view_confidence,
    save_view_confidence,
    triangulate_confident,
)
from mvpose_jax.view_confidence_training import (
    examples_from_recordings,
    features_of,
    fit_view_confidence,
)

LAY = get_layout("coco18")
WRISTS = (LAY.keypoints.index("l_wrist"), LAY.keypoints.index("r_wrist"))
ELBOWS = (LAY.keypoints.index("l_elbow"), LAY.keypoints.index("r_elbow"))


@pytest.fixture(scope="module")
def rig():
    return calibration.load_rig("panoptic5")


@pytest.fixture(scope="module")
def trained(rig):
    """A model trained on one small synthetic scene with many swaps, and a second scene."""
    config = SyntheticConfig().with_detector(swap_rate=0.2)
    scenes = simulate(rig, num_people=3, num_frames=20, num_scenes=2, config=config, seed=3)
    train = examples_from_recordings([scenes[0].recording])
    dev = examples_from_recordings([scenes[1].recording])
    x, y, _ = features_of(rig, train)
    dx, dy, _ = features_of(rig, dev)
    model, record = fit_view_confidence((x, y), (dx, dy), steps=300, batch_size=512, seed=0)
    return model, record, dev


def _inverted(ex, view: int):
    """The dev people with both arms (elbow and wrist) exchanged left for right in ``view``."""
    xy, score = ex.xy.copy(), ex.score.copy()
    for a, b in (WRISTS, ELBOWS):
        xy[:, view, [a, b]] = xy[:, view, [b, a]]
        score[:, view, [a, b]] = score[:, view, [b, a]]
    return xy, score


def test_leave_one_view_out_is_the_others_consensus(rig):
    rng = np.random.default_rng(0)
    C, N, K = rig.num_cameras, 2, 5
    px = rng.uniform(200, 800, (C, N, K, 2)).astype(np.float32)
    w = (rng.random((C, N, K)) > 0.2).astype(np.float32)
    xyz, ok, views = (np.asarray(a) for a in leave_one_view_out(rig, px, w))
    for c in (0, C - 1):
        wc = w.copy()
        wc[c] = 0
        ref, ref_ok, kept = (np.asarray(a) for a in triangulate_skeletons_robust(rig, px, wc))
        np.testing.assert_array_equal(ok[c], ref_ok)
        np.testing.assert_allclose(xyz[c], ref, atol=1e-5)
        np.testing.assert_array_equal(views[c], kept.sum(0))
        assert not kept[c].any()


def test_confident_weights_keep_two_views_at_least():
    w = np.array([[0.9], [0.8], [0.7], [0.0]], np.float32)  # (C=4, 1), the last view unseen
    p = np.array([[0.1], [0.9], [0.3], [0.99]], np.float32)
    out = np.asarray(confident_weights(w, p, threshold=0.5))[:, 0]
    # Only view 1 passes: the two most likely seen views (1 and 2) stay, the unseen one never.
    np.testing.assert_allclose(out, [0.0, 0.8 * 0.9, 0.7 * 0.3, 0.0], rtol=1e-6)
    out = np.asarray(confident_weights(w, p, threshold=0.05))[:, 0]
    np.testing.assert_allclose(out, [0.09, 0.72, 0.21, 0.0], rtol=1e-6)


def test_training_lowers_the_loss_and_learns_outliers(trained):
    _, record, _ = trained
    history = record["history"]
    assert history[-1]["train_loss"] < 0.6 * history[0]["train_loss"] or (record["dev_loss"] < 0.2)
    # Better than always answering "inlier" (the majority class).
    assert record["dev_accuracy"] > 1 - record["dev_outlier_share"]
    assert record["dev_outlier_recall"] > 0.3


def test_injected_inversions_are_rejected_and_beat_dlt(rig, trained):
    model, _, dev = trained
    view = 1
    xy, score = _inverted(dev, view)
    p = inlier_probability(model, rig, xy, score)  # (N, C, K)
    arms = list(WRISTS + ELBOWS)
    hit = (score[:, view, arms] > 0) & (dev.score[:, view, arms] > 0)
    clean = np.delete(p[..., arms], view, axis=1)[np.delete(score[..., arms], view, axis=1) > 0]
    # The inverted views score far below the clean ones.
    assert p[:, view, arms][hit].mean() < clean.mean() - 0.3
    px, w = np.moveaxis(xy, 1, 0), np.moveaxis(score, 1, 0)
    conf, ok_c = triangulate_confident(rig, px, w, np.moveaxis(p, 1, 0), threshold=0.5, then="dlt")
    dlt, ok_d = triangulate_points(rig, px, w)
    use = np.asarray(ok_c & ok_d)[:, arms] & dev.truth_valid[:, arms]

    def err(a):
        return np.linalg.norm(np.asarray(a)[:, arms] - dev.truth[:, arms], axis=-1)[use].mean()

    assert err(conf) < 0.6 * err(dlt)


def test_save_load_round_trip_and_stage(rig, trained, tmp_path):
    model, record, dev = trained
    folder = tmp_path / "conf"
    save_view_confidence(folder, model, record["dev_loss"])
    loaded = load_view_confidence(folder)
    assert loaded.config == model.config
    a = inlier_probability(model, rig, dev.xy[:8], dev.score[:8])
    b = inlier_probability(loaded, rig, dev.xy[:8], dev.score[:8])
    np.testing.assert_allclose(a, b, atol=1e-6)
    # Saved again over it, another model replaces it whole (orbax alone kept the old step 0).
    again = tmp_path / "again"
    save_view_confidence(again, model, record["dev_loss"])
    other = model._replace(params=jax.tree.map(lambda p: p * 0.5, model.params))
    save_view_confidence(again, other, record["dev_loss"])
    c = inlier_probability(load_view_confidence(again), rig, dev.xy[:8], dev.score[:8])
    d = inlier_probability(other, rig, dev.xy[:8], dev.score[:8])
    np.testing.assert_allclose(c, d, atol=1e-6)
    assert np.abs(np.asarray(c) - np.asarray(a)).max() > 1e-4
    assert not (tmp_path / "again.partial").exists()
    assert stages.lookup("lifting", "confident").needs_estimator is False
    # The registered stage on grouped people (F=1 frame, G people) gives 3D near the truth.
    xy, score = dev.xy[None, :8], dev.score[None, :8]
    poses, _ = lift_confident(
        rig, xy, score, LiftingConfig("confident", confidence=str(folder)), layout="coco18"
    )
    kv = np.asarray(poses.keypoint_valid)[0] & dev.truth_valid[:8]
    err = np.linalg.norm(np.asarray(poses.xyz)[0] - dev.truth[:8], axis=-1)[kv]
    assert kv.sum() > 50 and np.median(err) < 0.05
    with pytest.raises(ValueError, match="confidence"):
        lift_confident(rig, xy, score, LiftingConfig("confident"))


def test_infer_options_pair_method_and_model():
    import argparse

    from mvpose_jax.cli.infer import _infer_arguments, pipeline_config
    from mvpose_jax.errors import InputError

    p = argparse.ArgumentParser()
    _infer_arguments(p)
    base = ["--detections", "d.json", "--rig", "r.json", "--out", "o"]
    args = p.parse_args(base + ["--method", "confident", "--confidence", "m"])
    config = pipeline_config(args)
    assert (config.lifting.method, config.lifting.confidence) == ("confident", "m")
    for extra in (["--method", "confident"], ["--method", "robust", "--confidence", "m"]):
        with pytest.raises(InputError, match="--confidence"):
            pipeline_config(p.parse_args(base + extra))
