"""The rig-agnostic estimator: random rigs, the view-pooled network, pretraining over rigs, and
loading one model for any rig."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from mvpose_jax.cameras import (
    camera_centres,
    pixel_rays,
    project_points,
    rig_centre_and_radius,
    up_vector,
)
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.errors import InputError
from mvpose_jax.features import (
    assemble_features,
    estimator_inputs,
    rig_agnostic_frame,
    single_person_samples,
)
from mvpose_jax.graphs import make_pool, match_table, sample_batches
from mvpose_jax.losses import reprojection_error_l1
from mvpose_jax.matcher_training import train_matcher
from mvpose_jax.matching import gat_match_table
from mvpose_jax.models import (
    GATConfig,
    MLPConfig,
    RigAgnosticGAT,
    ViewPooledMLP,
    closest_ray_points,
    estimator_model,
    initial_estimate,
    rotation_to_z_up,
)
from mvpose_jax.pretraining import (
    CAMERA_BUCKETS,
    REFERENCE_FOCAL_PX,
    RigPeople,
    _person_error,
    bucketed,
    compose_rig_samples,
    pad_rig,
    pooled_batch,
    pooled_eval,
    pretrain_estimator,
    pretrain_matcher,
    rig_pool,
)
from mvpose_jax.synthetic import DetectorConfig, SyntheticConfig, generate_single_person_recordings
from mvpose_jax.synthetic.rigs import RIG_FAMILIES, look_at, random_rig
from mvpose_jax.trained import (
    EstimatorConfig,
    MatcherConfig,
    TrainConfig,
    load_estimator,
    load_matcher,
    read_proposal_threshold,
    rig_agnostic_matcher,
)

TINY = MLPConfig(widths=(32,), output="residual", views="pooled", view_widths=(32, 32))


@pytest.mark.parametrize("family", RIG_FAMILIES)
def test_random_rigs_have_a_capture_area_and_look_at_it(family):
    rig, floor = random_rig(family, [3, 1])
    assert rig.up == (0.0, 0.0, 1.0)
    assert 2 <= rig.num_cameras <= 10
    config = SyntheticConfig().with_scene(up=rig.up, floor_height=floor)
    (rec,) = generate_single_person_recordings(rig, num_recordings=1, num_frames=4, config=config)
    # The person is seen whole by at least two cameras in most frames.
    views = (np.asarray(rec.detections.count) > 0).sum(-1)
    assert np.median(views) >= 2
    # Cameras stand above the floor.
    assert (np.asarray(camera_centres(rig))[:, 2] > floor).all()


def test_look_at_matches_opencv_projection():
    """A camera built by look_at projects its target to the image centre (cv2 as reference)."""
    import cv2

    centre, target = np.array([3.0, -2.0, 2.5]), np.array([0.2, 0.1, 1.0])
    R = look_at(centre, target)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    K = np.array([[1000.0, 0, 640], [0, 1000, 360], [0, 0, 1]])
    px, _ = cv2.projectPoints(target[None], cv2.Rodrigues(R)[0], -R @ centre, K, None)
    np.testing.assert_allclose(px.reshape(2), [640, 360], atol=1e-6)
    # No roll: the image's x axis is level (perpendicular to up).
    assert abs(R[0] @ np.array([0, 0, 1.0])) < 1e-12


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 1, 0), (0, -1, 0), (0, 0, -1), (1, 2, 3)])
def test_rotation_to_z_up(up):
    q = rotation_to_z_up(up)
    np.testing.assert_allclose(q @ (np.array(up) / np.linalg.norm(up)), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(q @ q.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(q) == pytest.approx(1.0)


def _features(seed=0, n=6, c=5, k=18):
    x = jax.random.normal(jax.random.key(seed), (n, c, k, 14))
    seen = jax.random.uniform(jax.random.key(seed + 1), (n, c, k)) > 0.3
    x = x.at[..., 0].set(seen).at[..., 10].set(seen)
    return jnp.where(seen[..., None], x, 0.0)


def test_pooled_estimator_ignores_camera_order_and_count():
    model = ViewPooledMLP(18, TINY, rngs=nnx.Rngs(0))
    # Non-zero output weights: an untrained model returns the initial estimate exactly.
    x = _features()
    np.testing.assert_allclose(model(x), initial_estimate(x, per_keypoint=True), atol=1e-6)
    model.out.kernel[...] = jax.random.normal(jax.random.key(2), model.out.kernel[...].shape)
    y = model(x)
    perm = np.array([3, 0, 4, 1, 2])
    np.testing.assert_allclose(model(x[:, perm]), y, atol=1e-5)
    # An empty view slot (a padded camera) changes nothing.
    padded = jnp.concatenate([x, jnp.zeros_like(x[:, :2])], axis=1)
    np.testing.assert_allclose(model(padded), y, atol=1e-5)


def test_frame_rotation_is_equivariant():
    """Turning the world and the model's frame together turns the output with them."""
    model = ViewPooledMLP(18, TINY, rngs=nnx.Rngs(0))
    model.out.kernel[...] = jax.random.normal(jax.random.key(2), model.out.kernel[...].shape)
    x = _features()
    y = model(x)
    q = jnp.asarray(rotation_to_z_up((0.3, -1.0, 0.2)), jnp.float32)  # world -> z-up
    turn = lambda v: v @ q.T.T  # noqa: E731  (z-up world -> the turned world: q^T v)
    turned = jnp.concatenate(
        [x[..., :4], turn(x[..., 4:7]), turn(x[..., 7:10]), x[..., 10:11], turn(x[..., 11:14])],
        -1,
    )
    model.rotation[...] = q
    np.testing.assert_allclose(model(turned), turn(y), atol=1e-4)


def test_estimator_model_picks_the_architecture():
    assert isinstance(estimator_model(5, 18, TINY, rngs=nnx.Rngs(0)), ViewPooledMLP)
    assert not isinstance(
        estimator_model(5, 18, MLPConfig.quick(), rngs=nnx.Rngs(0)), ViewPooledMLP
    )
    with pytest.raises(ValueError, match="residual"):
        MLPConfig(views="pooled", output="absolute")


def _people(rig, floor, seed, n=2, frames=6):
    config = SyntheticConfig().with_scene(up=(0.0, 0.0, 1.0), floor_height=floor)
    recs = generate_single_person_recordings(
        rig, num_recordings=n, num_frames=frames, config=config, seed=seed
    )
    return RigPeople(rig, *single_person_samples(recs))


def test_person_error_is_the_reprojection_error_in_reference_pixels():
    rig, floor = random_rig("ring", [5, 0])
    people = _people(rig, floor, 1)
    xyz = jnp.asarray(np.random.default_rng(0).normal(0, 1, (18, 3)) + [0, 0, floor + 1.0])
    xy, score = jnp.asarray(people.xy[0]), jnp.asarray(people.score[0])
    got = _person_error(rig, xyz, xy, score)
    scale = REFERENCE_FOCAL_PX / np.asarray(rig.K)[:, 0, 0]
    per_camera = [
        float(
            reprojection_error_l1(
                rig.select([c]), xyz[None], xy[None, c : c + 1], score[None, c : c + 1]
            )[0]
        )
        for c in range(rig.num_cameras)
    ]
    assert float(got) == pytest.approx(float(np.dot(per_camera, scale)), rel=1e-5)


def test_padded_rigs_change_no_input():
    """A person's inputs in a rig padded to its bucket are its inputs in the rig, plus empty
    views."""
    rig, floor = random_rig("wall", [6, 2])
    people = _people(rig, floor, 2)
    batch = pooled_batch(people)
    C = rig.num_cameras
    assert batch.available.shape[1] in (3, 6, 10) and batch.available.shape[1] >= C
    assert not batch.available[:, C:].any()
    frame = (jnp.mean(camera_centres(rig), 0), jnp.asarray(1.0))
    own = estimator_inputs(rig, jnp.asarray(people.xy), jnp.asarray(people.score), frame)
    a = assemble_features(own, (jnp.asarray(people.score) > 0).any(-1))
    b = assemble_features(batch.inputs, batch.available)
    np.testing.assert_allclose(b[:, :C], a, atol=1e-4)
    assert not np.asarray(b[:, C:]).any()
    padded = pad_rig(rig, batch.available.shape[1])
    np.testing.assert_allclose(padded.K[:C], rig.K)


def test_pretraining_learns_and_one_model_loads_for_any_rig(tmp_path):
    """Pretraining lowers the dev reprojection error; the model folder loads for rigs of other
    camera counts and up directions and gives what the network gives on their inputs."""
    train = [
        _people(*random_rig(f, [7, i]), [7, i]) for i, f in enumerate(["ring", "arc", "wall"] * 2)
    ]
    dev = [_people(*random_rig("corners", [8, 0]), [8, 0])]
    config = EstimatorConfig(
        mlp=TINY,
        train=TrainConfig(
            learning_rate=1e-3, batch_size=16, max_steps=30, eval_every=1, patience=100
        ),
        loss_power=1.0,
    )
    (graphdef, rest, params), fit = pretrain_estimator(
        train, dev, config, checkpoint_dir=tmp_path / "m", progress=False
    )
    assert fit.steps == 30 and len(bucketed(train)) >= 2  # more than one camera bucket
    # The training people's reprojection loss fell below the untrained model's (which returns
    # the initial estimate).
    data = bucketed(train)
    start = nnx.split(estimator_model(10, 18, TINY, rngs=nnx.Rngs(0)), nnx.Param, ...)
    before = pooled_eval(start[0], start[2], start[1], data, 1.0)["val_loss"]
    after = pooled_eval(graphdef, rest, params, data, 1.0)["val_loss"]
    assert after < 0.95 * before, (before, after)
    for name in ("panoptic5", "arplab6"):
        rig = load_rig(name)
        est = load_estimator(tmp_path / "m", rig)
        assert est.rig_infer.names == rig.names
        np.testing.assert_allclose(est.rest["rotation"][...] @ up_vector(rig), [0, 0, 1], atol=1e-5)
        np.testing.assert_allclose(est.normalisation[0], camera_centres(rig).mean(0), atol=1e-5)
        xyz = jnp.asarray([[0.1, 0.2, 1.0]] * 18) + est.normalisation[0][None]
        px = jnp.moveaxis(project_points(rig, xyz[None]), 0, 1)
        score = jnp.ones(px.shape[:-1])
        inputs = estimator_inputs(rig, px, score, est.normalisation)
        feats = assemble_features(inputs, jnp.ones((1, rig.num_cameras), bool))
        out = nnx.merge(est.graphdef, est.params, est.rest)(feats)[0] + est.normalisation[0][None]
        # Exact detections of a point: the network's answer stays near it (the residual is
        # small after a few steps), and the model runs on this rig's camera count.
        assert out.shape == (18, 3) and np.isfinite(np.asarray(out)).all()


def test_fine_tuning_starts_from_the_pretrained_model(tmp_path):
    from mvpose_jax.estimator_training import train_estimator

    train = [_people(*random_rig("ring", [9, i]), [9, i]) for i in range(2)]
    config = EstimatorConfig(
        mlp=TINY,
        train=TrainConfig(learning_rate=1e-3, batch_size=16, max_steps=4, eval_every=1),
        loss_power=1.0,
    )
    pretrain_estimator(train, train, config, checkpoint_dir=tmp_path / "m", progress=False)
    rig = load_rig("panoptic5")
    start = load_estimator(tmp_path / "m", rig)
    people = _people(rig, None, 3)
    tune = dataclasses.replace(config, train=dataclasses.replace(config.train, max_steps=2))
    tuned, fit = train_estimator(
        rig,
        people.xy,
        people.score,
        people.xy,
        people.score,
        tune,
        progress=False,
        start=start,
        checkpoint_dir=tmp_path / "t",
    )
    assert fit.steps == 2
    # Same frame; the parameters moved from the pretrained ones.
    np.testing.assert_allclose(tuned.normalisation[0], start.normalisation[0])
    moved = jax.tree.map(lambda a, b: float(jnp.abs(a - b).max()), tuned.params, start.params)
    assert max(jax.tree.leaves(moved)) > 0
    # The fine-tuned folder loads as a rig-agnostic model again.
    again = load_estimator(tmp_path / "t", rig)
    jax.tree.map(np.testing.assert_allclose, again.params, tuned.params)


def test_pretrain_experiment_smoke(tmp_path):
    """``python -m experiments.pretrain --scale smoke`` on one evaluation rig: a report with the
    rows it promises, the fine-tuning step size chosen on validation scenes, and a model folder
    that loads for a rig it never saw."""
    import json

    from experiments.pretrain import FINETUNE_RATES, main

    main(["--out", str(tmp_path), "--scale", "smoke", "--rigs", "pair", "--no-progress"])
    report = json.loads((tmp_path / "pretrain.json").read_text())
    (rig,) = report["rigs"].values()
    assert rig["cameras"] == 2 and rig["held_out_family"]
    assert rig["finetune_learning_rate"] in FINETUNE_RATES
    assert report["pretraining"]["detectors"] == {"default": {"fitted": False}}
    for split in ("validation", "test"):
        for who in ("per-rig", "pretrained", "fine-tuned"):
            for method in ("mlp", "blend"):
                assert 0 <= rig[split][f"{who}, {method}"]["pcp"] <= 100
    assert "| robust triangulation |" in (tmp_path / "pretrain.md").read_text()
    est = load_estimator(tmp_path / "models" / "pretrained", load_rig("arplab6"))
    assert est.rig_infer.num_cameras == 6
    # Seeds combined: one run twice has no spread, and the differences are the run's own.
    main(["--out", str(tmp_path), "--combine", str(tmp_path), str(tmp_path)])
    text = (tmp_path / "pretrain_seeds.md").read_text()
    diff = rig["test"]["pretrained, blend"]["pcp"] - rig["test"]["per-rig, blend"]["pcp"]
    assert f"| ... minus per-rig, blend | {diff:+.1f} ± 0.0 |" in text


def test_pretraining_rigs_take_the_detectors_in_turn():
    """Rig i's recordings come from detector i mod n; with the default detector alone they are
    the recordings of before (shipped models stay reproducible)."""
    from experiments.pretrain import PRETRAIN_SCALES, rig_people
    from experiments.pretrain_matcher import MATCHER_PRETRAIN_SCALES, rig_recordings
    from experiments.real_detectors import training_detectors

    noisy = DetectorConfig(noise_relative=0.2)
    sc = PRETRAIN_SCALES["smoke"]
    plain = rig_people(2, sc, "train", 0, False)
    mixed = rig_people(2, sc, "train", 0, False, (DetectorConfig(), noisy))
    np.testing.assert_array_equal(plain[0].xy, mixed[0].xy)
    assert not np.array_equal(plain[1].xy, mixed[1].xy, equal_nan=True)
    msc = MATCHER_PRETRAIN_SCALES["smoke"]
    plain = rig_recordings(2, msc, "dev", 0, False)
    mixed = rig_recordings(2, msc, "dev", 0, False, (DetectorConfig(), noisy))
    for a, b in zip(plain[0][1], mixed[0][1], strict=True):
        np.testing.assert_array_equal(a.detections.xy, b.detections.xy)
    assert any(
        not np.array_equal(a.detections.xy, b.detections.xy, equal_nan=True)
        for a, b in zip(plain[1][1], mixed[1][1], strict=True)
    )
    configs, record = training_detectors(("default",))
    assert configs == (DetectorConfig(),) and record == {"default": {"fitted": False}}
    for bad in ((), ("default", "default"), ("elsewhere",)):
        with pytest.raises(ValueError):
            training_detectors(bad)


def test_pretrain_command_line_passes_rigs_and_detectors(tmp_path, monkeypatch):
    """``--rigs none`` compares on no rig (pretraining only, its table says so); ``--detectors``
    reaches the run in order; the default is the simulator's detector alone."""
    import experiments.pretrain as pretrain
    import experiments.pretrain_matcher as pretrain_matcher

    for module in (pretrain, pretrain_matcher):
        calls = []
        monkeypatch.setattr(module, "run", lambda *a: calls.append(a) or {"rigs": {}})
        monkeypatch.setattr(module, "table", lambda report: ["table"])
        module.main(["--out", str(tmp_path), "--rigs", "none", "--detectors", "mvor", "default"])
        module.main(["--out", str(tmp_path), "--rigs", "pair", "arplab6"])
        assert [c[5:] for c in calls] == [
            ((), ("mvor", "default")),
            (("pair", "arplab6"), ("default",)),
        ]
        monkeypatch.undo()
        assert module.table({"rigs": {}}) == [
            "(no evaluation rig: pretraining only, `--rigs none`)"
        ]


# =========================================================================== the rig-agnostic matcher

TINY_GAT = GATConfig(widths=(16, 1), heads=(4, 1), views="pooled", encoder_widths=(32,))


def test_closest_ray_points_closed_form_and_opencv():
    # Skew lines: the x axis, and the line through (5, 0, 1) along y: closest at x = 5, 1 m apart.
    s, t, gap = closest_ray_points(
        jnp.array([0.0, 0, 0]),
        jnp.array([1.0, 0, 0]),
        jnp.array([5.0, 0, 1]),
        jnp.array([0.0, 1, 0]),
    )
    np.testing.assert_allclose([s, t, gap], [5.0, 0.0, 1.0], atol=1e-6)
    # Two cameras' rays through one point's pixels meet where OpenCV triangulates it.
    import cv2

    rig = load_rig("panoptic5")
    rig = rig.select(list(rig.names[:2]))
    point = camera_centres(rig).mean(0) + jnp.array([0.3, -0.2, 0.4])
    px = project_points(rig, point[None])[:, 0]  # (2, 2), no distortion worth the name here
    rays = pixel_rays(rig, px)
    c = camera_centres(rig)
    s, t, gap = closest_ray_points(c[0], rays[0], c[1], rays[1])
    P = [
        np.asarray(rig.K[i]) @ np.hstack([rig.R[i], np.asarray(rig.t[i]).reshape(3, 1)])
        for i in range(2)
    ]
    und = [
        cv2.undistortPoints(
            np.asarray(px[i], np.float64).reshape(1, 1, 2),
            np.asarray(rig.K[i], np.float64),
            np.asarray(rig.dist[i], np.float64),
            P=np.asarray(rig.K[i], np.float64),
        ).reshape(2, 1)
        for i in range(2)
    ]
    X = cv2.triangulatePoints(P[0], P[1], und[0], und[1])
    X = (X[:3] / X[3]).ravel()
    assert float(gap) < 1e-3
    np.testing.assert_allclose(np.asarray(c[0] + s * rays[0]), X, atol=2e-3)
    np.testing.assert_allclose(np.asarray(c[1] + t * rays[1]), X, atol=2e-3)


def _matcher_scores(rig, recs, gat_parts, rng_seed=0, pad_cameras=0, frame=None):
    """{(frame, {(camera name, skeleton), (camera name, skeleton)}): score} of a composed batch."""
    graphdef, rest, params = gat_parts
    matcher = rig_agnostic_matcher(graphdef, rest, params, MatcherConfig(gat=TINY_GAT), rig)
    pool = make_pool(rig, recs, frame)
    batch = sample_batches(pool, np.random.default_rng(rng_seed), 1, 3, subset_probability=0.0)[0]
    if pad_cameras:  # empty camera slots after the rig's own
        det = np.asarray(batch.det_features)
        batch = batch._replace(
            det_features=np.concatenate(
                [
                    det,
                    np.zeros(
                        (det.shape[0], pad_cameras * det.shape[1] // rig.num_cameras), np.float32
                    ),
                ],
                1,
            )
        )
    model = nnx.merge(matcher.graphdef, matcher.params, matcher.rest)
    if frame is not None:
        model.scale[...] = 1.0
    rows, scores = match_table(batch, np.asarray(model(batch)))
    out = {}
    for (f, ca, sa, cb, sb), v in zip(rows.tolist(), scores, strict=True):
        out[(f, frozenset([(rig.names[ca], sa), (rig.names[cb], sb)]))] = float(v)
    return out


@pytest.fixture(scope="module")
def panoptic_people():
    rig = load_rig("panoptic5")
    recs = generate_single_person_recordings(rig, num_recordings=4, num_frames=3, seed=3)
    model = RigAgnosticGAT(recs[0].num_keypoints, TINY_GAT, rngs=nnx.Rngs(0))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    # Non-trivial attention everywhere: random final-layer weights.
    params = jax.tree.map(lambda a: a + 0.3 * jax.random.normal(jax.random.key(1), a.shape), params)
    return rig, recs, (graphdef, rest, params)


def test_rig_agnostic_matcher_ignores_camera_order_and_slots(panoptic_people):
    rig, recs, parts = panoptic_people
    base = _matcher_scores(rig, recs, parts)
    assert len(set(np.round(list(base.values()), 4))) > 10  # not a constant
    # The cameras in another order: every pair scores the same (subset_probability 0 keeps all
    # views, so the same skeletons are drawn).
    permuted = _matcher_scores(rig.select([rig.names[i] for i in (3, 0, 4, 1, 2)]), recs, parts)
    assert permuted.keys() == base.keys()
    np.testing.assert_allclose([permuted[k] for k in base], list(base.values()), atol=1e-5)
    # Empty camera slots beside the rig's (padding to a larger rig's width) change nothing.
    padded = _matcher_scores(rig, recs, parts, pad_cameras=3)
    np.testing.assert_allclose([padded[k] for k in base], list(base.values()), atol=1e-5)
    # Features in metres with scale 1 (pretraining's form) score as rig-normalised ones with
    # the rig's radius (inference's).
    metres = _matcher_scores(rig, recs, parts, frame=rig_agnostic_frame(rig))
    np.testing.assert_allclose([metres[k] for k in base], list(base.values()), atol=1e-4)


def test_rig_agnostic_matcher_turns_the_rigs_up_to_z(panoptic_people):
    """A rig turned about a horizontal axis (its up no longer +z) scores as the upright one."""
    rig, recs, parts = panoptic_people
    upright = dataclasses.replace(rig, up=tuple(float(x) for x in up_vector(rig)))
    q = np.asarray(rotation_to_z_up(up_vector(rig)))  # the panoptic world -> z up
    base = _matcher_scores(dataclasses.replace(_turned(rig, q), up=(0.0, 0.0, 1.0)), recs, parts)
    # The same scene, in the rig's own (y-down) world.
    own = _matcher_scores(upright, recs, parts)
    np.testing.assert_allclose([own[k] for k in base], list(base.values()), atol=1e-4)


def _turned(rig, q):
    """The rig with its world turned by q (points x -> q x): pixels do not change."""
    R = np.asarray(rig.R) @ q.T
    return dataclasses.replace(rig, R=jnp.asarray(R, jnp.float32))


def _rig_recordings(family, seed, n=4, frames=4):
    rig, floor = random_rig(family, seed)
    config = SyntheticConfig().with_scene(up=(0.0, 0.0, 1.0), floor_height=floor)
    recs = generate_single_person_recordings(
        rig, num_recordings=n, num_frames=frames, config=config, seed=seed
    )
    return rig, recs


def test_composed_rig_samples_keep_each_frame_on_one_rig():
    pair = rig_pool(*_rig_recordings("pair", [4, 0]))  # 2 cameras
    ring = rig_pool(*_rig_recordings("ring", [4, 1]))
    feats, valid, identity = compose_rig_samples(
        [pair, ring], np.random.default_rng(0), 40, max_people=3
    )
    assert feats.shape[1] == CAMERA_BUCKETS[-1] and valid.shape == identity.shape
    ring_cams = ring.valid.shape[1]
    seen = valid.any(-1)  # (S, C) views with a skeleton
    on_pair = ~seen[:, 2:].any(1)
    assert on_pair.any() and (~on_pair).any()  # both rigs drawn
    assert not seen[:, ring_cams:].any()  # padding views stay empty
    # A person's skeletons carry the features of one rig's pool: a 2-camera sample's rows are
    # rows of the pair's pool.
    rows = feats[on_pair][valid[on_pair]]
    pool_rows = pair.features[pair.valid]
    assert all(np.isclose(pool_rows, r).all(-1).any() for r in rows[:10])


def test_pretrain_matcher_learns_and_loads_for_any_rig(tmp_path):
    train = [rig_pool(*_rig_recordings(f, [5, i])) for i, f in enumerate(["ring", "arc", "wall"])]
    dev = [rig_pool(*_rig_recordings("corners", [6, 0]))]
    config = MatcherConfig(
        gat=TINY_GAT,
        train=TrainConfig(
            learning_rate=3e-3, batch_size=6, max_steps=80, eval_every=2, patience=100
        ),
        samples_per_epoch=60,
        num_dev_samples=12,
        max_people=4,
    )
    (graphdef, rest, params), fit = pretrain_matcher(
        train, dev, config, checkpoint_dir=tmp_path / "m", progress=False
    )
    assert fit.steps == 80
    losses = [h["val_loss"] for h in fit.history]
    assert min(losses[-2:]) < 0.75 * losses[0], losses
    with pytest.raises(InputError, match="rig-agnostic"):
        pretrain_matcher(train, dev, MatcherConfig(), progress=False)
    # One folder, any rig: set up with the rig's radius and up, and it scores the rig's pairs.
    for name in ("panoptic5", "arplab6"):
        rig = load_rig(name)
        matcher = load_matcher(tmp_path / "m", rig)
        assert matcher.rig.names == rig.names
        np.testing.assert_allclose(
            matcher.rest["rotation"][...] @ up_vector(rig), [0, 0, 1], atol=1e-5
        )
        np.testing.assert_allclose(
            matcher.rest["scale"][...], rig_centre_and_radius(rig)[1], rtol=1e-6
        )
        recs = generate_single_person_recordings(rig, num_recordings=2, num_frames=2, seed=1)
        rows, scores = gat_match_table(matcher, recs[0].detections)
        assert len(rows) and ((scores >= 0) & (scores <= 1)).all()
    # `adapt` fine-tunes it on a multi-person recording's own pseudo-labels, as any matcher.
    from mvpose_jax.adapt import MatcherAdaptConfig, adapt_matcher
    from mvpose_jax.synthetic import generate_recording

    rig = load_rig("panoptic5")
    scene = generate_recording(rig, num_people=2, num_frames=6, seed=2)
    small = MatcherAdaptConfig(
        max_steps=2, check_every=1, batch_frames=2, block_frames=1, holdout_every=3, min_frames=2
    )
    adapted, report = adapt_matcher(
        rig, scene.detections, load_matcher(tmp_path / "m", rig), config=small, progress=False
    )
    assert adapted.config.gat.views == "pooled" and report.steps <= 2
    assert np.isfinite(report.heldout_loss_after)
    # Fine-tuning on a rig starts from it, and writes a rig-agnostic folder again.
    rig, recs = _rig_recordings("two-level", [6, 1])
    start = load_matcher(tmp_path / "m", rig)
    tune = dataclasses.replace(config, train=dataclasses.replace(config.train, max_steps=3))
    tuned, fit = train_matcher(
        rig, recs, recs, tune, progress=False, start=start, checkpoint_dir=tmp_path / "t"
    )
    assert fit.steps == 3
    moved = jax.tree.map(lambda a, b: float(jnp.abs(a - b).max()), tuned.params, start.params)
    assert max(jax.tree.leaves(moved)) > 0
    again = load_matcher(tmp_path / "t", load_rig("panoptic5"))
    assert again.config.gat == TINY_GAT
    with pytest.raises(InputError, match="rig-agnostic"):
        paper = start._replace(config=MatcherConfig())
        train_matcher(rig, recs, recs, tune, progress=False, start=paper)


def test_pretrain_matcher_experiment_smoke(tmp_path):
    """``python -m experiments.pretrain_matcher --scale smoke`` on one evaluation rig: the rows
    it promises, a threshold written beside the model, a folder that loads for another rig."""
    import json

    from experiments.pretrain_matcher import FINETUNE_RATES, ROWS, main

    main(["--out", str(tmp_path), "--scale", "smoke", "--rigs", "tripods", "--no-progress"])
    report = json.loads((tmp_path / "pretrain_matcher.json").read_text())
    (rig,) = report["rigs"].values()
    assert rig["cameras"] == 2 and rig["held_out_family"]
    assert rig["finetune_learning_rate"] in FINETUNE_RATES
    for split in ("validation", "test"):
        for row in ROWS:
            assert -1 <= rig[split][row]["ari"] <= 1 and 0 <= rig[split][row]["pcp"] <= 100
    folder = tmp_path / "models" / "matcher"
    pre = report["pretraining"]
    assert read_proposal_threshold(folder) == pre["threshold"]
    # Every dev rig lands in one camera-count group, and each group's curve is its rigs' mean.
    groups = pre["dev_ari_by_cameras"]
    assert sum(g["rigs"] for g in groups.values()) == pre["rigs"]["dev"]
    for g in groups.values():
        assert g["ari"][str(g["best"])] == max(g["ari"].values())
    if len(groups) == 1:
        (g,) = groups.values()
        assert g["ari"] == pytest.approx(pre["dev_ari_by_threshold"], abs=1e-5)
    assert "per camera count" in (tmp_path / "pretrain_matcher.md").read_text()
    assert load_matcher(folder, load_rig("arplab6")).rig.num_cameras == 6
    main(["--out", str(tmp_path), "--combine", str(tmp_path), str(tmp_path)])
    assert "± 0.0" in (tmp_path / "pretrain_matcher_seeds.md").read_text()


@pytest.mark.slow  # scenes of one rig, the shipped models scored (no training)
def test_pretrained_synthetic_scores_model_folders_without_training(tmp_path):
    """``python -m experiments.pretrained_synthetic``: each named folder at its own threshold and
    at the rig's, the epipolar row, the estimator's rows; names must be distinct pairs."""
    import json

    from experiments.pretrained_synthetic import main, named_folders

    assert named_folders(None) == {"shipped": "pretrained"}
    for bad in (["x"], ["=f"], ["a=f", "a=g"]):
        with pytest.raises(SystemExit):
            named_folders(bad)
    folder = "pretrained"
    argv = ["--out", str(tmp_path), "--scale", "smoke", "--rigs", "pair"]
    assert main([*argv, "--matchers", f"a={folder}", "--estimators", f"b={folder}"]) == 0
    (rig,) = json.loads((tmp_path / "pretrained_synthetic.json").read_text())["rigs"].values()
    assert rig["thresholds"]["a"]["folder"] == read_proposal_threshold(folder)
    for split in ("validation", "test"):
        assert set(rig[split]["matching"]) == {
            "a",
            "a, rig's threshold",
            "epipolar",
            "true_people_per_frame",
        }
        assert set(rig[split]["3d"]) == {"robust triangulation", "b, mlp", "b, blend"}
    assert "| a, rig's threshold |" in (tmp_path / "pretrained_synthetic.md").read_text()
