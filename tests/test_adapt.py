"""adapt.py: fine-tuning an estimator on a recording's own detections (no labels), held-out
blocks of frames, early stopping that keeps the best parameters, the ``adapt`` command."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from flax import nnx

from mvpose_jax import adapt as adapt_module
from mvpose_jax import estimator_training as train_module
from mvpose_jax.adapt import (
    AdaptConfig,
    MatcherAdaptConfig,
    adapt_estimator,
    adapt_matcher,
    heldout_frames,
    person_samples,
    save_adapted_matcher,
)
from mvpose_jax.cameras import rig_centre_and_radius
from mvpose_jax.data.calibration import load_preset
from mvpose_jax.errors import InputError
from mvpose_jax.estimator_training import train_estimator
from mvpose_jax.features import single_person_samples
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import predict_people
from mvpose_jax.matching import gat_match_table, propose_with_matcher
from mvpose_jax.metrics import matching_scores
from mvpose_jax.models import GATConfig, MatchingGAT, MLPConfig, PoseMLP
from mvpose_jax.proposals import CombinedConfig, propose_people
from mvpose_jax.synthetic import (
    SyntheticConfig,
    generate_recording,
    generate_single_person_recordings,
)
from mvpose_jax.trained import (
    Estimator,
    EstimatorConfig,
    Matcher,
    MatcherConfig,
    TrainConfig,
    load_estimator,
    load_matcher,
    read_combined_config,
    read_proposal_threshold,
    write_proposal_threshold,
)

TINY = MLPConfig(widths=(32, 32), output="residual")


@pytest.fixture(scope="module")
def rig():
    return load_preset("panoptic5")


@pytest.fixture(scope="module")
def shifted_scene(rig):
    """Two people on a floor 0.5 m above the one the estimators train on, 60 frames."""
    config = SyntheticConfig().with_scene(floor_offset_m=0.5)
    return generate_recording(rig, num_people=2, num_frames=60, config=config, seed=3)


def untrained_estimator(rig, K: int = 18, seed: int = 0) -> Estimator:
    """A freshly initialised estimator (residual output: it starts at the triangulation)."""
    model = PoseMLP(rig.num_cameras, K, TINY, rngs=nnx.Rngs(seed))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    config = EstimatorConfig(mlp=TINY, loss_power=1.0, num_augment=2)
    return Estimator(graphdef, rest, params, rig, config, rig_centre_and_radius(rig))


@pytest.fixture(scope="module")
def trained(rig):
    """A tiny estimator trained briefly on the default world (the floor the rig implies)."""
    recs = generate_single_person_recordings(rig, num_recordings=6, num_frames=20, seed=0)
    xy, score = single_person_samples(recs)
    config = EstimatorConfig(
        mlp=TINY,
        loss_power=1.0,
        num_augment=2,
        train=TrainConfig(
            learning_rate=3e-3, batch_size=64, max_steps=300, eval_every=50, patience=100
        ),
    )
    est, _ = train_estimator(rig, xy, score, xy[:40], score[:40], config, progress=False)
    return est


def test_heldout_frames_are_every_nth_whole_block():
    held = heldout_frames(47, block_frames=4, holdout_every=3)
    block = np.arange(47) // 4
    np.testing.assert_array_equal(held, block % 3 == 2)
    # Whole blocks: a frame is held out exactly when its block's first frame is.
    np.testing.assert_array_equal(held, held[block * 4])
    assert not held[:8].any() and held[8:12].all()


def test_person_samples_keep_groups_of_enough_views():
    F, C, P, K = 2, 3, 2, 4
    xy = np.arange(F * C * P * K * 2, dtype=np.float32).reshape(F, C, P, K, 2)
    score = np.ones((F, C, P, K), np.float32)
    members = np.array([[[0, 1, -1], [1, -1, -1]], [[-1, -1, -1], [1, 0, 1]]])
    out_xy, out_score, frame = person_samples(
        adapt_module.Detections(xy, score, np.full((F, C), P)), members, min_views=2
    )
    np.testing.assert_array_equal(frame, [0, 1])
    np.testing.assert_array_equal(out_xy[0, 0], xy[0, 0, 0])
    np.testing.assert_array_equal(out_xy[0, 1], xy[0, 1, 1])
    assert (out_score[0, 2] == 0).all()  # no skeleton in camera 2
    np.testing.assert_array_equal(out_xy[1, 2], xy[1, 2, 1])


@pytest.mark.slow  # proposals and a train step compiled (~10 s)
def test_heldout_people_are_never_trained_on(rig, shifted_scene, monkeypatch):
    det = shifted_scene.detections
    config = AdaptConfig(
        max_steps=6, max_seconds=600, check_every=3, block_frames=5, holdout_every=4, min_people=8
    )
    members = run_pipeline(rig, det).members
    trained_rows = []
    make_step = train_module.make_train_step

    def spying_make_train_step(*args, **kwargs):
        step = make_step(*args, **kwargs)

        def spy(state, batch, key):
            trained_rows.append(np.asarray(batch.xy))
            return step(state, batch, key)

        return spy

    # The estimator's set-up (`estimator_training.estimator_training`) makes the step adaptation runs.
    monkeypatch.setattr(train_module, "make_train_step", spying_make_train_step)
    _, report = adapt_estimator(
        rig, det, untrained_estimator(rig), members=members, config=config, progress=False
    )
    assert report.steps == 6 and len(trained_rows) == 6
    xy, _, frame = person_samples(det, members, 2)
    held = heldout_frames(len(det.count), 5, 4)[frame]
    assert report.people_heldout == held.sum() > 0
    key = lambda a: a.tobytes()  # noqa: E731  (float pixels: a person's rows identify them)
    held_keys = {key(x) for x in xy[held]}
    adapt_keys = {key(x) for x in xy[~held]}
    seen = {key(x) for batch in trained_rows for x in batch}
    assert seen <= adapt_keys and not seen & held_keys
    assert len(seen) > 0.5 * len(adapt_keys)  # the batches cover the adaptation set


def test_too_short_a_recording_is_refused(rig, shifted_scene):
    det = jax.tree.map(lambda a: np.asarray(a)[:9], shifted_scene.detections)
    with pytest.raises(InputError, match="too little to adapt on"):
        adapt_estimator(rig, det, untrained_estimator(rig), progress=False)


def test_bad_settings_and_layouts_are_refused(rig, shifted_scene):
    det = shifted_scene.detections
    with pytest.raises(InputError, match="holdout_every"):
        adapt_estimator(
            rig, det, untrained_estimator(rig), config=AdaptConfig(holdout_every=1), progress=False
        )
    with pytest.raises(InputError, match="keypoints"):
        adapt_estimator(rig, det, untrained_estimator(rig, K=17), progress=False)


@pytest.mark.slow  # proposals and a train step compiled (~10 s)
def test_wall_clock_budget_stops_it(rig, shifted_scene):
    config = AdaptConfig(max_steps=10_000, max_seconds=1e-3, check_every=5, min_people=8)
    _, report = adapt_estimator(
        rig, shifted_scene.detections, untrained_estimator(rig), config=config, progress=False
    )
    assert report.stopped == "max_seconds" and 1 <= report.steps <= 5


@pytest.mark.slow  # trains a model
def test_adapting_lowers_the_heldout_loss_on_a_shifted_floor(rig, trained, shifted_scene):
    config = AdaptConfig(
        learning_rate=1e-3, max_steps=200, max_seconds=600, check_every=20, block_frames=5
    )
    adapted, report = adapt_estimator(
        rig, shifted_scene.detections, trained, config=config, progress=False
    )
    assert report.heldout_loss_after < 0.8 * report.heldout_loss_before, report
    assert report.best_step > 0 and report.frames_heldout == 10
    # What is returned is the best check's state, recomputed on the held-out frames.
    best = min(report.history, key=lambda h: h["val_loss"])
    assert report.best_step == best["step"]
    assert report.heldout_loss_after == pytest.approx(best["val_loss"], rel=1e-5)
    # The given estimator is untouched (the train step donates its own copy).
    xy, score, _ = person_samples(
        shifted_scene.detections, run_pipeline(rig, shifted_scene.detections).members, 2
    )
    before = predict_people(trained, xy[:8], score[:8])
    after = predict_people(adapted, xy[:8], score[:8])
    assert np.abs(before - after).max() > 1e-3
    np.testing.assert_allclose(before, predict_people(trained, xy[:8], score[:8]))


@pytest.mark.slow  # trains a model
def test_early_stopping_returns_the_best_not_the_last(rig, trained, shifted_scene):
    # A step size that diverges at once: every check is worse than the given parameters.
    config = AdaptConfig(
        learning_rate=0.3, max_steps=60, max_seconds=600, check_every=5, patience=3, block_frames=5
    )
    adapted, report = adapt_estimator(
        rig, shifted_scene.detections, trained, config=config, progress=False
    )
    checks = [h["val_loss"] for h in report.history]
    assert report.stopped == "patience" and len(checks) == 3 and report.steps == 15
    assert min(checks) > 2 * report.heldout_loss_before
    # The returned parameters are the given ones (the best), not those of the last step.
    assert report.best_step == 0
    assert report.heldout_loss_after == pytest.approx(report.heldout_loss_before, rel=1e-6)
    for a, b in zip(jax.tree.leaves(adapted.params), jax.tree.leaves(trained.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow  # trains, adapts and infers through the command line
def test_adapt_command_writes_a_model_infer_loads(rig, trained, shifted_scene, tmp_path, capsys):
    from mvpose_jax import cli
    from mvpose_jax.data import save_recording
    from mvpose_jax.data.poses import load_poses

    # The trained estimator as a model folder, the recording as an npz.
    recs = generate_single_person_recordings(rig, num_recordings=2, num_frames=20, seed=1)
    xy, score = single_person_samples(recs)
    cfg = dataclasses.replace(
        trained.config, train=TrainConfig(max_steps=2, batch_size=16, eval_every=1)
    )
    train_estimator(rig, xy, score, xy, score, cfg, checkpoint_dir=tmp_path / "est", progress=False)
    save_recording(shifted_scene, tmp_path / "rec.npz")
    common = ["--rig", "panoptic5", "--detections", str(tmp_path / "rec.npz")]
    argv = ["adapt", *common, "--model", str(tmp_path / "est"), "--max-steps", "20"]
    assert cli.main(argv + ["--out", str(tmp_path / "adapted"), "--block-frames", "5"]) == 0
    out = capsys.readouterr().out
    assert "held-out reprojection" in out and "wrote" in out
    report = json.loads((tmp_path / "adapted" / "adapt_report.json").read_text())
    assert report["frames"] == 60 and report["settings"]["grouping"].startswith("epipolar")
    adapted = load_estimator(tmp_path / "adapted", rig)
    assert adapted.rig_infer.names == rig.names
    np.testing.assert_allclose(adapted.normalisation[1], rig_centre_and_radius(rig)[1])
    # An existing, non-empty --out is refused, before any work.
    assert cli.main(argv + ["--out", str(tmp_path / "adapted")]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (
        cli.main(
            [
                "infer",
                *common,
                "--estimator",
                str(tmp_path / "adapted"),
                "--out",
                str(tmp_path / "poses"),
            ]
        )
        == 0
    )
    assert load_poses(tmp_path / "poses").poses.valid.any()
    # infer --adapt: in memory, then inference.
    argv = ["infer", *common, "--estimator", str(tmp_path / "est"), "--adapt"]
    assert (
        cli.main(
            argv
            + ["--adapt-max-steps", "4", "--adapt-block-frames", "5", "--out", str(tmp_path / "p2")]
        )
        == 0
    )
    assert "held-out reprojection" in capsys.readouterr().out
    assert cli.main(argv + ["--resume", "--out", str(tmp_path / "p3")]) == 2


# --------------------------------------------------------------------------- the matcher


@pytest.fixture(scope="module")
def crowd(rig):
    """Four people, 100 frames: the matcher's recording (its true identities are the labels)."""
    return generate_recording(rig, num_people=4, num_frames=100, seed=5)


def untrained_matcher(rig, K: int = 18, seed: int = 0) -> Matcher:
    """A freshly initialised tiny GAT on every camera of ``rig`` (its scores mean nothing)."""
    config = MatcherConfig(gat=GATConfig(widths=(16, 16, 1), heads=(2, 2, 1)))
    model = MatchingGAT(rig.num_cameras, K, config.gat, rngs=nnx.Rngs(seed))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    return Matcher(graphdef, rest, params, rig, config)


FAST = MatcherAdaptConfig(learning_rate=3e-3, max_steps=300, patience=100, min_frames=8)


def _adapt_on_truth(rig, rec, matcher, max_steps: int = FAST.max_steps):
    """`adapt_matcher` with the recording's true identities as labels, ``FAST`` settings."""
    config = dataclasses.replace(FAST, max_steps=max_steps)
    return adapt_matcher(
        rig, rec.detections, matcher, identity=rec.identity, config=config, progress=False
    )


def _gat_ari(matcher, rec) -> float:
    got = propose_with_matcher(matcher, rec.detections, mode="gat", threshold=0.5)
    return matching_scores(rec.identity, got.identity, rec.detections.count)["ari"]


def test_a_matcher_learns_a_recordings_groups_from_its_labels(rig, crowd):
    matcher = untrained_matcher(rig)
    given = jax.tree.map(np.array, matcher.params)
    adapted, report = _adapt_on_truth(rig, crowd, matcher)
    # The given parameters are untouched (the train step donates its own copy).
    jax.tree.map(np.testing.assert_array_equal, given, jax.tree.map(np.array, matcher.params))
    # From scratch, 300 steps on 80 frames: far from a trained matcher, but clearly learning
    # (held-out loss 0.24 -> 0.15, ARI 0 -> 0.35 when written).
    assert report.heldout_loss_after < 0.7 * report.heldout_loss_before
    assert report.heldout_accuracy_after > report.heldout_accuracy_before + 0.03
    assert report.best_step > 0
    assert _gat_ari(adapted, crowd) > _gat_ari(matcher, crowd) + 0.2
    held = heldout_frames(100, FAST.block_frames, FAST.holdout_every)
    counts = crowd.detections.count
    has_pair = (counts.sum(1) ** 2 - (counts**2).sum(1)) > 0
    assert report.frames_adapt == int((~held & has_pair).sum())
    assert report.frames_heldout == int((held & has_pair).sum())
    # Positive pairs: cross-camera pairs of one person, counted independently.
    ident = crowd.identity[~held & has_pair]
    same = sum(
        int(((ident[:, a, :, None] == ident[:, b, None, :]) & (ident[:, a, :, None] >= 0)).sum())
        for a in range(5)
        for b in range(a + 1, 5)
    )
    assert report.positive_fraction == pytest.approx(same / report.pairs_adapt)
    # The threshold: the adapted GAT's proposals on the held-out frames, against their labels,
    # at each threshold tried (ARI recomputed here); the best one, ties to the one nearest 0.5.
    held_f = np.flatnonzero(held & has_pair)
    held_det = jax.tree.map(lambda a: np.asarray(a)[held_f], crowd.detections)
    rows, scores = gat_match_table(adapted, held_det)
    aris = {}
    for t in report.threshold_ari:
        got = propose_people(
            rows, scores, held_det.count, num_skeletons=held_det.score.shape[2], threshold=t
        )
        aris[t] = matching_scores(crowd.identity[held_f], got.identity, held_det.count)["ari"]
    assert report.threshold_ari == pytest.approx(aris)
    best = max(aris.values())
    assert report.threshold == min(
        (t for t, a in aris.items() if a == best), key=lambda t: abs(t - 0.5)
    )


def test_matcher_adaptation_keeps_the_given_matcher_when_nothing_helps(rig, crowd):
    matcher = untrained_matcher(rig)
    same, report = _adapt_on_truth(rig, crowd, matcher, max_steps=0)
    assert report.steps == 0 and report.best_step == 0 and report.stopped == "max_steps"
    jax.tree.map(np.testing.assert_array_equal, same.params, matcher.params)
    assert report.heldout_loss_after == report.heldout_loss_before


def test_matcher_adaptation_refuses_what_does_not_fit(rig, crowd):
    matcher = untrained_matcher(rig)
    short = jax.tree.map(lambda a: a[:12], crowd.detections)
    with pytest.raises(InputError, match="too little to adapt on"):
        adapt_matcher(rig, short, matcher, identity=crowd.identity[:12], progress=False)
    with pytest.raises(InputError, match="identity has shape"):
        adapt_matcher(rig, crowd.detections, matcher, identity=crowd.identity[:5], progress=False)
    three = rig.select(list(rig.names[:3]))
    det3 = jax.tree.map(lambda a: a[:, :3], crowd.detections)
    with pytest.raises(InputError, match="not in the recording"):
        adapt_matcher(three, det3, matcher, progress=False)
    with pytest.raises(InputError, match="learning_rate"):
        MatcherAdaptConfig(learning_rate=0.0).check()
    with pytest.raises(InputError, match="holdout_every"):
        MatcherAdaptConfig(holdout_every=1).check()


def test_an_adapted_matcher_is_saved_as_a_folder_load_matcher_reads(rig, crowd, tmp_path):
    matcher = untrained_matcher(rig)
    adapted, report = _adapt_on_truth(rig, crowd, matcher, max_steps=25)
    source = tmp_path / "matcher"
    source.mkdir()
    write_proposal_threshold(source, 0.3, {0.3: 0.9}, 10, combined=CombinedConfig(threshold=0.25))
    out = save_adapted_matcher(tmp_path / "adapted", adapted, report, settings_from=source)
    loaded = load_matcher(out, rig)
    jax.tree.map(
        lambda a, b: np.testing.assert_allclose(np.asarray(a), np.asarray(b)),
        loaded.params,
        adapted.params,
    )
    # The combined matcher's settings are the source's; the GAT's threshold the adapted one's.
    assert read_combined_config(out).threshold == 0.25
    assert read_proposal_threshold(out) == report.threshold
    assert read_combined_config(
        save_adapted_matcher(tmp_path / "a2", adapted, report)
    ).threshold == (CombinedConfig().threshold)
    assert read_proposal_threshold(tmp_path / "a2") == report.threshold
    assert json.loads((out / "adapt_report.json").read_text())["best_step"] == report.best_step
    with pytest.raises(InputError, match="not an empty folder"):
        save_adapted_matcher(out, adapted, report)


def test_adapt_command_adapts_the_matcher_too(rig, shifted_scene, tmp_path, capsys):
    from mvpose_jax import cli
    from mvpose_jax.data import save_recording

    assert MatcherAdaptConfig().max_steps == cli.MATCHER_ADAPT_STEPS
    # A matcher folder (an untrained GAT, saved as an adapted one is) and an estimator folder.
    matcher = untrained_matcher(rig)
    _, report = _adapt_on_truth(rig, shifted_scene, matcher, max_steps=0)
    save_adapted_matcher(tmp_path / "m", matcher, report)
    write_proposal_threshold(
        tmp_path / "m", 0.15, {0.15: 0.9}, 10, combined=CombinedConfig(threshold=0.25)
    )
    save_recording(shifted_scene, tmp_path / "rec.npz")
    common = ["--rig", "panoptic5", "--detections", str(tmp_path / "rec.npz")]
    est = untrained_estimator(rig)
    est_report = adapt_estimator(
        rig,
        shifted_scene.detections,
        est,
        config=AdaptConfig(max_steps=0, block_frames=5),
        progress=False,
    )[1]
    adapt_module.save_adapted_estimator(tmp_path / "e", est, est_report)
    argv = ["adapt", *common, "--estimator", str(tmp_path / "e"), "--max-steps", "2"]
    argv += ["--block-frames", "5", "--out", str(tmp_path / "e2")]
    assert cli.main(argv + ["--matcher-out", str(tmp_path / "m2")]) == 2
    assert "give --matcher" in capsys.readouterr().err
    argv += ["--matcher", str(tmp_path / "m"), "--matcher-out", str(tmp_path / "m2")]
    assert cli.main(argv + ["--matcher-max-steps", "5", "--proposals", "gat"]) == 0
    out = capsys.readouterr().out
    assert "adapted the matcher on" in out and "wrote" in out
    saved = json.loads((tmp_path / "m2" / "adapt_report.json").read_text())
    assert saved["steps"] == 5 and saved["settings"]["grouping"] == "combined"
    # One budget for the command (60 frames: the 30 s floor): half of it for the matcher.
    assert saved["settings"]["budget_seconds"] == pytest.approx(15.0)
    est_budget = json.loads((tmp_path / "e2" / "adapt_report.json").read_text())["settings"]
    assert est_budget["budget_seconds"] == pytest.approx(30.0 - saved["seconds"], abs=1e-6)
    # The combined matcher's settings travel; the GAT's threshold is the adapted one's.
    assert read_combined_config(tmp_path / "m2").threshold == 0.25
    assert read_proposal_threshold(tmp_path / "m2") == saved["threshold"] != 0.15
    assert load_matcher(tmp_path / "m2", rig).rig.names == rig.names
    # The estimator adapted behind the adapted matcher's proposals, at its threshold.
    est_saved = json.loads((tmp_path / "e2" / "adapt_report.json").read_text())
    assert est_saved["steps"] == 2 and est_saved["settings"]["proposals"] == "gat"
    assert est_saved["settings"]["threshold"] == saved["threshold"]
