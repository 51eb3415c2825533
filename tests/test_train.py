"""train.py (and the loaders of trained.py): the estimator and the matcher train on tiny data,
their checkpoints restore, a resumed run ends where an uninterrupted one does."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from mvpose_jax.estimator_training import random_view_subsets, train_estimator
from mvpose_jax.features import single_person_samples
from mvpose_jax.lifting import predict_people
from mvpose_jax.matcher_training import train_matcher
from mvpose_jax.models import MLPConfig, PoseMLP
from mvpose_jax.synthetic import (
    SyntheticConfig,
    generate_single_person_recordings,
)
from mvpose_jax.train import init_train_state, make_optimizer
from mvpose_jax.trained import EstimatorConfig, MatcherConfig, TrainConfig, load_estimator
from tests.helpers import TINY_GAT as TINY


@pytest.fixture(scope="module")
def clean_samples():
    from mvpose_jax.data.calibration import load_preset

    rig = load_preset("panoptic5")
    cfg = SyntheticConfig().replace(detector=SyntheticConfig().detector.clean())
    recs = generate_single_person_recordings(
        rig, num_recordings=4, num_frames=16, seed=0, config=cfg
    )
    return (rig, *single_person_samples(recs))


@pytest.mark.slow  # trains a model
def test_small_paper_style_mlp_fits_a_small_set(clean_samples, tmp_path):
    rig, xy, score = clean_samples
    cfg = EstimatorConfig(
        num_augment=0,
        mlp=MLPConfig(widths=(128, 128)),  # the paper's absolute output
        train=TrainConfig(
            learning_rate=3e-3,
            final_lr_fraction=0.01,
            max_steps=1500,
            batch_size=64,
            eval_every=100,
            patience=100,
        ),
    )
    est, res = train_estimator(
        rig, xy, score, xy, score, cfg, checkpoint_dir=tmp_path / "ckpt", progress=False
    )
    first, best = (
        res.history[0]["val_px_per_keypoint"],
        min(h["val_px_per_keypoint"] for h in res.history),
    )
    assert first > 20.0 and best < 5.0, (first, best)
    # The best checkpoint restores to the same predictions.
    restored = load_estimator(tmp_path / "ckpt", rig)
    a = predict_people(est, xy[:10], score[:10])
    b = predict_people(restored, xy[:10], score[:10])
    np.testing.assert_allclose(a, b, atol=1e-5)


@pytest.mark.slow  # trains a model
def test_padding_does_not_change_predictions(clean_samples):
    rig, xy, score = clean_samples
    cfg = EstimatorConfig(
        mlp=MLPConfig(widths=(32,), output="residual"), train=TrainConfig(max_steps=2, batch_size=8)
    )
    est, _ = train_estimator(rig, xy, score, xy, score, cfg, progress=False)
    alone = predict_people(est, xy[:1], score[:1])
    many = predict_people(est, xy[:40], score[:40])  # another padding bucket
    np.testing.assert_allclose(many[:1], alone, atol=1e-5)
    assert np.all(np.isfinite(many))


@pytest.mark.slow  # trains a model
def test_residual_output_starts_at_the_triangulation(clean_samples):
    from mvpose_jax.lifting import triangulate_people

    rig, xy, score = clean_samples
    model_cfg = MLPConfig(widths=(16,), output="residual")
    cfg = EstimatorConfig(
        mlp=model_cfg, train=TrainConfig(learning_rate=0.0, max_steps=1, batch_size=8)
    )
    est, _ = train_estimator(rig, xy, score, xy, score, cfg, progress=False)
    ours = predict_people(est, xy[:12], score[:12])
    tri, ok = triangulate_people(rig, xy[:12], score[:12])
    np.testing.assert_allclose(ours[ok], tri[ok], atol=1e-4)


def test_random_view_subsets_are_nonempty_proper_subsets():
    available = jnp.asarray(np.random.default_rng(0).uniform(size=(200, 5)) > 0.3)
    masks, ok = random_view_subsets(jax.random.key(0), available, 4)
    masks, ok, available = np.asarray(masks), np.asarray(ok), np.asarray(available)
    n = available.sum(-1)
    assert np.all(ok == (n >= 2)[None])
    k = masks.sum(-1)
    assert np.all(~masks | available[None])  # only available views
    assert np.all((k >= 1) & (k < n[None]) | ~ok)  # non-empty and proper where possible
    # Every size from 1 to n - 1 occurs.
    five = n == 5
    assert set(np.unique(k[:, five])) == {1, 2, 3, 4}


@pytest.mark.slow  # trains a model
def test_resumed_training_ends_where_an_uninterrupted_run_does(clean_samples, tmp_path):
    rig, xy, score = clean_samples

    def run(steps, folder, resume=False):
        cfg = EstimatorConfig(
            mlp=MLPConfig(widths=(32,), output="residual"),
            num_augment=2,
            train=TrainConfig(learning_rate=1e-3, max_steps=steps, batch_size=16, patience=100),
        )
        return train_estimator(
            rig,
            xy,
            score,
            xy[:8],
            score[:8],
            cfg,
            checkpoint_dir=folder,
            progress=False,
            resume=resume,
        )

    whole, _ = run(12, tmp_path / "a")  # 3 epochs of 4 steps
    run(8, tmp_path / "b")  # "killed" after 2 epochs ...
    resumed, fit = run(12, tmp_path / "b", resume=True)  # ... and resumed
    assert fit.steps == 12
    from mvpose_jax.checkpoints import Checkpoints

    latest = []
    for folder in ("a", "b"):
        ck = Checkpoints(tmp_path / folder)
        model = PoseMLP(5, 18, MLPConfig(widths=(32,), output="residual"), rngs=nnx.Rngs(0))
        _, _, state = init_train_state(model, make_optimizer(TrainConfig()))
        latest.append(ck.restore(jax.eval_shape(lambda: state), "latest")[0])
        ck.close()
    for a, b in zip(
        jax.tree.leaves(latest[0].params), jax.tree.leaves(latest[1].params), strict=True
    ):
        np.testing.assert_allclose(a, b, atol=1e-6)
    # Another config in the same folder is refused, not silently restarted.
    cfg = EstimatorConfig(
        mlp=MLPConfig(widths=(64,), output="residual"), train=TrainConfig(max_steps=4)
    )
    from mvpose_jax.errors import InputError

    with pytest.raises(InputError, match="another config"):
        train_estimator(
            rig,
            xy,
            score,
            xy[:8],
            score[:8],
            cfg,
            checkpoint_dir=tmp_path / "b",
            progress=False,
            resume=True,
        )


@pytest.mark.slow  # trains a model
def test_train_estimator_command(tmp_path, capsys):
    from mvpose_jax import cli

    assert (
        cli.main(
            [
                "generate",
                "--rig",
                "panoptic5",
                "--single-person-recordings",
                "2",
                "--frames",
                "20",
                "--out",
                str(tmp_path / "train"),
            ]
        )
        == 0
    )
    argv = [
        "train-estimator",
        "--rig",
        "panoptic5",
        "--train",
        str(tmp_path / "train"),
        "--out",
        str(tmp_path / "ckpt"),
        "--infer-cameras",
        "trackera",
        "trackerb",
        "--steps",
        "6",
        "--batch-size",
        "16",
    ]
    assert cli.main(argv) == 0
    assert "checkpoints in" in capsys.readouterr().out
    assert cli.main(argv + ["--resume"]) == 0  # nothing left to do: resumes at the end
    assert cli.main(argv[:-2] + ["--batch-size", "8", "--resume"]) == 2  # another config: refused
    assert "another config" in capsys.readouterr().err
    assert (
        cli.main(
            [
                "train-estimator",
                "--rig",
                "panoptic5",
                "--train",
                str(tmp_path / "nope"),
                "--out",
                str(tmp_path / "c2"),
            ]
        )
        == 2
    )


@pytest.mark.slow  # trains a model
def test_one_camera_estimator_works_in_the_training_rigs_frame(clean_samples, tmp_path):
    """M_1/t: the inference rig of one camera spans nothing (radius 0), so the model must live in
    the training rig's normalised frame, and that frame must survive a checkpoint round trip."""
    from mvpose_jax.cameras import project_points, rig_centre_and_radius

    rig, xy, score = clean_samples
    config = EstimatorConfig(
        infer_cameras=(rig.names[0],),
        mlp=MLPConfig(widths=(32,), output="residual"),
        train=TrainConfig(batch_size=16, max_steps=2, learning_rate=1e-3),
    )
    est, _ = train_estimator(
        rig,
        xy[:48],
        score[:48],
        xy[48:],
        score[48:],
        config,
        checkpoint_dir=tmp_path,
        progress=False,
    )
    centre, radius = rig_centre_and_radius(rig)
    np.testing.assert_allclose(est.normalisation[1], radius, rtol=1e-6)
    np.testing.assert_allclose(est.normalisation[0], centre, rtol=1e-6, atol=1e-6)
    loaded = load_estimator(tmp_path, rig)
    np.testing.assert_allclose(loaded.normalisation[1], radius, rtol=1e-6)
    one_xy, one_score = xy[:8, :1], score[:8, :1]
    out = predict_people(est, one_xy, one_score)
    np.testing.assert_allclose(predict_people(loaded, one_xy, one_score), out, atol=1e-5)
    # The residual start puts each seen keypoint on its camera's ray: it projects back onto the
    # detection (2 training steps move it little), not at the rig centre's image.
    px = np.asarray(project_points(rig.select([rig.names[0]]), out))[0]
    seen = one_score[:, 0] > 0
    assert np.median(np.linalg.norm(px - one_xy[:, 0], axis=-1)[seen]) < 20.0


@pytest.mark.slow  # trains a model
def test_train_matcher_quick_runs_and_checkpoints(ring_rig, tmp_path):
    from mvpose_jax.synthetic import generate_single_person_recordings
    from mvpose_jax.trained import load_matcher

    recs = generate_single_person_recordings(ring_rig, num_recordings=4, num_frames=5, seed=1)
    cfg = MatcherConfig.quick()
    cfg = dataclasses.replace(
        cfg,
        gat=TINY,
        samples_per_epoch=30,
        num_dev_samples=15,
        train=dataclasses.replace(cfg.train, max_epochs=2, eval_every=1),
    )
    matcher, fit = train_matcher(
        ring_rig, recs[:3], recs[3:], cfg, checkpoint_dir=tmp_path, progress=False
    )
    assert fit.steps == 4 and np.isfinite(fit.best_val_loss)
    again = load_matcher(tmp_path, ring_rig, cfg, num_keypoints=recs[0].num_keypoints)
    for a, b in zip(jax.tree.leaves(matcher.params), jax.tree.leaves(again.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_model_worse_than_triangulation_on_its_dev_data_says_so(clean_samples, tmp_path):
    from mvpose_jax.trained import DEV_QUALITY_FILE, ModelQualityWarning

    rig, xy, score = clean_samples
    cfg = EstimatorConfig(
        mlp=MLPConfig(widths=(16,)),  # absolute output, 2 steps: far worse than geometry
        train=TrainConfig(learning_rate=1e-3, max_steps=2, batch_size=16),
    )
    train_estimator(
        rig, xy, score, xy[:16], score[:16], cfg, checkpoint_dir=tmp_path, progress=False
    )
    quality = json.loads((tmp_path / DEV_QUALITY_FILE).read_text())
    assert quality["keypoints"] > 0
    # Clean detections: triangulation reprojects within a pixel or so; the untrained MLP does not.
    assert quality["triangulation_px"] < 2.0 < quality["estimator_px"]
    with pytest.warns(ModelQualityWarning, match="triangulation reprojects"):
        load_estimator(tmp_path, rig)
