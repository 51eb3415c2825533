"""checkpoints.py: the whole train state round-trips; inference restores the parameters alone
(no optimiser state is read or needed), and another model's checkpoint is refused by name.
trained.ModelFolder: folders of the layout written before it existed load as they did; a new
folder appears whole or not at all."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from flax import nnx

from mvpose_jax.cameras import rig_centre_and_radius
from mvpose_jax.checkpoints import Checkpoints, TrainState
from mvpose_jax.data.calibration import load_preset
from mvpose_jax.errors import InputError
from mvpose_jax.models import GATConfig, MatchingGAT, MLPConfig, PoseMLP
from mvpose_jax.proposals import CombinedConfig
from mvpose_jax.train import init_train_state, make_optimizer
from mvpose_jax.trained import (
    EstimatorConfig,
    MatcherConfig,
    ModelFolder,
    ModelQualityWarning,
    TrainConfig,
    load_estimator,
    load_matcher,
    read_combined_config,
    read_proposal_threshold,
)


def _saved(tmp_path, widths=(8, 8)):
    model = PoseMLP(2, 4, MLPConfig(widths=widths), rngs=nnx.Rngs(3))
    _, _, state = init_train_state(model, make_optimizer(TrainConfig()))
    ck = Checkpoints(tmp_path)
    try:
        ck.save_best(state, {"run": "test"}, 0.25)
    finally:
        ck.close()
    return state


def _abstract_params(widths=(8, 8)):
    _, params, _ = nnx.split(
        PoseMLP(2, 4, MLPConfig(widths=widths), rngs=nnx.Rngs(0)), nnx.Param, ...
    )
    return jax.eval_shape(lambda: params)


def test_params_alone_restore_without_an_optimiser(tmp_path):
    state = _saved(tmp_path)
    ck = Checkpoints(tmp_path)
    try:
        params = ck.restore_params(_abstract_params())
        whole, config = ck.restore(jax.eval_shape(lambda: state))
    finally:
        ck.close()
    assert config == {"run": "test"}
    assert jax.tree.structure(params) == jax.tree.structure(state.params)
    for a, b, c in zip(
        jax.tree.leaves(params),
        jax.tree.leaves(state.params),
        jax.tree.leaves(whole.params),
        strict=True,
    ):
        assert isinstance(a, jax.Array)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_params_of_another_model_are_refused_by_name(tmp_path):
    _saved(tmp_path, widths=(8, 8))
    ck = Checkpoints(tmp_path)
    try:
        with pytest.raises(InputError, match="another model") as e:
            ck.restore_params(_abstract_params(widths=(16, 8)))
    finally:
        ck.close()
    assert "params" in str(e.value) and "best" in str(e.value.file)


def test_no_checkpoint_is_a_clear_error(tmp_path):
    ck = Checkpoints(tmp_path / "empty")
    try:
        with pytest.raises(InputError, match="no best checkpoint"):
            ck.restore_params(_abstract_params())
    finally:
        ck.close()


# ------------------------------------------------------------------ model folders of the old layout
# Built by hand as `train_estimator`, `train_matcher`, `write_proposal_threshold` and
# `save_adapted_*` wrote them before `ModelFolder` (file names spelled out, not taken from it).


def _old_estimator_folder(path, rig, adapted: bool = False):
    config = EstimatorConfig(mlp=MLPConfig(widths=(8, 8)), train=TrainConfig(seed=4))
    model = PoseMLP(rig.num_cameras, 18, config.mlp, rngs=nnx.Rngs(4))
    _, _, state = init_train_state(model, make_optimizer(config.train))
    saved = json.loads(json.dumps(dataclasses.asdict(config)))
    centre, radius = rig_centre_and_radius(rig)
    saved.update(
        train_cameras=list(rig.names),
        infer_cameras=list(rig.names),
        num_keypoints=18,
        frame=[float(x) for x in np.asarray(centre)] + [float(radius)],
    )
    if adapted:  # params alone, a report, the config's "adapted" entry
        state = TrainState(state.step, state.params, ())
        saved["adapted"] = {"steps": 3}
        (path / "adapt_report.json").parent.mkdir(parents=True, exist_ok=True)
        (path / "adapt_report.json").write_text(json.dumps({"steps": 3, "best_step": 2}))
    ck = Checkpoints(path)
    try:
        ck.save_best(state, saved, 0.5)
        if not adapted:
            ck.save_latest(state, saved)
    finally:
        ck.close()
    quality = {"estimator_px": 9.0, "triangulation_px": 3.0, "keypoints": 10, "how": "by hand"}
    (path / "dev_reprojection.json").write_text(json.dumps(quality))
    return state.params, quality


def _old_matcher_folder(path, rig):
    config = MatcherConfig(gat=GATConfig(widths=(8, 8, 1), heads=(2, 2, 1)))
    model = MatchingGAT(rig.num_cameras, 18, config.gat, rngs=nnx.Rngs(5))
    _, _, state = init_train_state(model, make_optimizer(config.train))
    saved = {**json.loads(json.dumps(dataclasses.asdict(config))), "num_keypoints": 18}
    ck = Checkpoints(path)
    try:
        ck.save_best(state, saved, 0.5)
    finally:
        ck.close()
    record = {
        "threshold": 0.35,
        "ari_by_threshold": {"0.35": 0.9},
        "composed_frames": 6,
        "combined": {**dataclasses.asdict(CombinedConfig(threshold=0.25)), "ari_by_threshold": {}},
    }
    (path / "proposal_threshold.json").write_text(json.dumps(record))
    return state.params


def _assert_same(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_an_estimator_folder_of_the_old_layout_loads_with_its_report(tmp_path):
    rig = load_preset("panoptic5")
    params, quality = _old_estimator_folder(tmp_path / "est", rig)
    with pytest.warns(ModelQualityWarning, match="triangulation reprojects 3.00 px"):
        estimator = load_estimator(tmp_path / "est", rig)
    _assert_same(estimator.params, params)
    folder = ModelFolder(tmp_path / "est")
    assert folder.kind() == "estimator" and not folder.is_adapted()
    assert folder.read_dev_quality() == quality and folder.read_adapt_report() is None
    assert read_proposal_threshold(tmp_path / "est") == 0.5  # an estimator chose none


def test_an_adapted_estimator_folder_of_the_old_layout_loads(tmp_path):
    rig = load_preset("panoptic5")
    params, _ = _old_estimator_folder(tmp_path / "adapted", rig, adapted=True)
    with pytest.warns(ModelQualityWarning):
        _assert_same(load_estimator(tmp_path / "adapted", rig).params, params)
    folder = ModelFolder(tmp_path / "adapted")
    assert folder.is_adapted() and folder.read_adapt_report() == {"steps": 3, "best_step": 2}


def test_a_matcher_folder_of_the_old_layout_loads_with_its_chosen_settings(tmp_path):
    rig = load_preset("panoptic5")
    params = _old_matcher_folder(tmp_path / "mat", rig)
    _assert_same(load_matcher(tmp_path / "mat", rig).params, params)
    folder = ModelFolder(tmp_path / "mat")
    assert folder.kind() == "matcher" and folder.read_dev_quality() is None
    assert read_proposal_threshold(tmp_path / "mat") == 0.35 == folder.read_proposal_threshold()
    assert read_combined_config(tmp_path / "mat") == CombinedConfig(threshold=0.25)
    # Its settings travel to another folder as they are.
    (tmp_path / "copy").mkdir()
    assert ModelFolder(tmp_path / "copy").copy_proposal_settings(folder)
    assert read_combined_config(tmp_path / "copy") == CombinedConfig(threshold=0.25)
    assert not ModelFolder(tmp_path / "copy").copy_proposal_settings(ModelFolder(tmp_path))


def test_a_new_folder_appears_whole_or_not_at_all(tmp_path):
    params = _abstract_params()
    params = jax.tree.map(lambda a: np.ones(a.shape, a.dtype), params)
    with ModelFolder.create(tmp_path / "m") as folder:
        assert folder.path != tmp_path / "m" and not (tmp_path / "m").exists()
        folder.save_params(params, 7, {"mlp": {}, "adapted": {}}, 0.1)
        folder.write_adapt_report({"steps": 7})
    made = ModelFolder(tmp_path / "m")
    assert made.is_adapted() and made.read_adapt_report() == {"steps": 7}
    assert made.adapt_report_path.is_file()
    _assert_same(made.restore_params(_abstract_params()), params)
    with pytest.raises(InputError, match="not an empty folder"), ModelFolder.create(tmp_path / "m"):
        pass
    with pytest.raises(RuntimeError), ModelFolder.create(tmp_path / "n") as folder:
        folder.write_adapt_report({"steps": 1})
        raise RuntimeError("killed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # no half-written folder


def test_a_path_that_is_no_model_folder_is_refused_before_anything_is_created(tmp_path):
    with pytest.raises(InputError, match="no such folder.*train-matcher"):
        ModelFolder(tmp_path / "typo").require("best", "train-matcher")
    assert not (tmp_path / "typo").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no best/ checkpoint folder"):
        load_estimator(tmp_path / "empty", load_preset("panoptic5"))
    assert list((tmp_path / "empty").iterdir()) == []


@pytest.mark.slow  # trains a matcher and an estimator for a few steps
def test_model_folders_record_the_pipeline_infer_runs_with_them(tmp_path):
    from mvpose_jax.data import save_recording
    from mvpose_jax.jobs.common import RigSource
    from mvpose_jax.jobs.infer import INFER_PIPELINE, resolve_pipeline
    from mvpose_jax.jobs.train import (
        EstimatorJob,
        MatcherJob,
        TrainingRun,
        model_pipeline,
        train_estimator_job,
        train_matcher_job,
    )
    from mvpose_jax.synthetic import generate_single_person_recordings

    rig = load_preset("panoptic5")
    recs = generate_single_person_recordings(rig, num_recordings=6, num_frames=8, seed=3)
    for split, part in (("train", recs[:4]), ("dev", recs[4:])):
        for i, rec in enumerate(part):
            save_recording(rec, tmp_path / split / f"r{i}.npz")
    run = TrainingRun(
        RigSource("panoptic5"), str(tmp_path / "train"), str(tmp_path / "dev"), str(tmp_path / "m")
    )
    train_matcher_job(MatcherJob(run, quick=True, max_epochs=1))
    est_run = dataclasses.replace(run, out=str(tmp_path / "e"))
    train_estimator_job(EstimatorJob(est_run, steps=2, batch_size=8))
    matcher = model_pipeline(str(tmp_path / "m"))
    # The matcher's: the combined matcher with the settings chosen and written beside it.
    assert matcher == resolve_pipeline(INFER_PIPELINE, str(tmp_path / "m"), estimator=False)
    assert matcher.matching.proposals == "combined"
    assert matcher.matching.combined == ModelFolder(tmp_path / "m").read_combined_config()
    estimator = model_pipeline(str(tmp_path / "e"))
    assert estimator.lifting.method == "blend" and estimator.tracking == INFER_PIPELINE.tracking
    assert model_pipeline(str(tmp_path / "nowhere")) is None
