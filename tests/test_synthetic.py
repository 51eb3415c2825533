"""Tests of the synthetic-data generator (small configurations; the whole file runs in seconds)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from mvpose_jax import cli
from mvpose_jax.cameras import Rig, make_rig, project_points
from mvpose_jax.data import load_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.checks import check_recording
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import COCO18
from mvpose_jax.synthetic import (
    SyntheticConfig,
    detection_variants,
    generate_recording,
    generate_single_person_recordings,
    scene_geometry,
    simulate,
)
from mvpose_jax.synthetic import body as bm


@pytest.fixture(scope="module")
def panoptic() -> Rig:
    return load_rig("panoptic5")


@pytest.fixture(scope="module")
def scene(panoptic):
    """A crowded small scene: 4 people in Panoptic's small capture area."""
    return simulate(panoptic, num_people=4, num_frames=300, seed=7)[0]


@pytest.fixture(scope="module")
def measured(panoptic):
    """A long two-person recording with high, measurable effect rates."""
    config = SyntheticConfig().with_detector(
        miss_rate=0.2,
        false_positive_rate=0.5,
        occluded_drop_rate=0.5,
        keypoint_drop_rate=0.05,
        swap_rate=0.1,
    )
    return simulate(panoptic, num_people=2, num_frames=600, config=config, seed=3)[
        0
    ], config.detector


def _per_person(rec, values, fill=0.0):
    """Scatters per-row values (F, C, P, ...) to per-person (F, C, G, ...) by identity."""
    F, C, P = rec.identity.shape
    G = rec.ground_truth.xyz.shape[1]
    out = np.full((F, C, G) + values.shape[3:], fill, values.dtype)
    f, c, p = np.nonzero(rec.identity >= 0)
    out[f, c, rec.identity[f, c, p]] = values[f, c, p]
    return out


@pytest.mark.parametrize("preset", ["panoptic5", "arplab6"])
def test_presets_floor_and_capture_area(preset):
    rig = load_rig(preset)
    geo = scene_geometry(rig)
    # Documented floors: panoptic5 y = 0 (up -y), arplab6 z = 0 (up -z).
    assert abs(geo.floor_height) < 0.15
    assert geo.area() > 3.0
    assert np.allclose(geo.up, rig.up)


def test_user_calibration_without_up_is_found(panoptic):
    # The same cameras in an arbitrary world frame (rotated, shifted) without an 'up' entry.
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    d = np.array([3.0, -2.0, 1.5])
    R = np.asarray(panoptic.R, np.float64) @ q.T
    t = np.asarray(panoptic.t, np.float64) - R @ d
    rig = make_rig(panoptic.K, panoptic.dist, R, t, panoptic.size, panoptic.names)
    assert rig.up is None
    rec = generate_recording(rig, num_people=2, num_frames=60, seed=1)
    old = (rec.ground_truth.xyz - d) @ q  # back to Panoptic's frame: x_old = q^T (x_new - d)
    heights = -old[..., 1]  # Panoptic's up is -y, its floor near y = 0
    ankles = heights[:, :, [bm.L_ANKLE, bm.R_ANKLE]].min(-1)
    assert np.all(np.abs(ankles - 0.07) < 0.2)
    assert np.all(heights.max(-1) > 1.2)  # upright: heads well above the floor


def test_bone_lengths_constant_and_heights_realistic(scene):
    xyz = scene.recording.ground_truth.xyz.astype(np.float64)
    # Every layout bone but the torso diagonals (neck-hip), which flex with the spine.
    rigid = [
        b for b in COCO18.bones if bm.NECK not in b or (bm.L_HIP not in b and bm.R_HIP not in b)
    ]
    a, b = np.array(rigid).T
    length = np.linalg.norm(xyz[:, :, a] - xyz[:, :, b], axis=-1)  # (F, G, bones)
    assert np.abs(length - length[0]).max() < 1e-4
    h = scene.bodies.height
    assert np.all((h >= 1.5) & (h <= 1.95))
    # Standing on the floor: the lower ankle is always at ankle height above it.
    geo = scene.geometry
    up = (scene.points - geo.origin) @ geo.up
    ankle = up[..., [bm.L_ANKLE, bm.R_ANKLE]].min(-1)
    np.testing.assert_allclose(
        ankle, np.broadcast_to(scene.bodies.ankle_height, ankle.shape), atol=1e-6
    )


def test_people_never_interpenetrate(scene):
    gap = bm.clearance(scene.points, scene.bodies.radii)
    assert gap.min() > 0.0


def test_reported_keypoints_inside_image(scene, panoptic):
    det = scene.recording.detections
    size = np.asarray(panoptic.size)[None, :, None, None]
    present = det.score > 0
    inside = (det.xy >= 0).all(-1) & (det.xy < size).all(-1)
    assert present.any()
    assert np.all(inside[present])
    # Missing keypoints and padding rows are zero.
    assert np.all(det.xy[~present] == 0)
    rows = np.arange(det.score.shape[2]) < det.count[..., None]
    assert np.all(det.score[~rows] == 0) and np.all(scene.recording.identity[~rows] == -1)


def test_projected_is_projection_of_ground_truth(scene, panoptic):
    rec = scene.recording
    proj = np.asarray(
        project_points(panoptic, jnp.asarray(rec.ground_truth.xyz))
    )  # (C, F, G, K, 2)
    expected = _per_person(rec, rec.projected)  # (F, C, G, K, 2)
    has = _per_person(rec, np.ones(rec.identity.shape, bool), False)
    proj = np.moveaxis(proj, 0, 1)
    seen = has[..., None] & scene.truth.in_image
    assert seen.sum() > 1000
    assert np.abs(proj - expected)[seen].max() < 0.02  # pixels: float32 tolerance
    # Outside the image but within the lens' field of view too (beyond it the distortion
    # polynomial folds and amplifies float32 rounding: pixels there are meaningless).
    p = np.moveaxis(scene.geometry.cameras.to_camera(rec.ground_truth.xyz.astype(np.float64)), 0, 1)
    r2 = (p[..., :2] ** 2).sum(-1) / np.maximum(p[..., 2], 1e-3) ** 2
    fov = (p[..., 2] > 0.1) & (r2 < scene.geometry.cameras.max_radius2[None, :, None, None])
    np.testing.assert_allclose(
        proj[has[..., None] & fov], expected[has[..., None] & fov], rtol=1e-5, atol=0.05
    )


def test_detections_belong_to_their_identity(scene):
    rec = scene.recording
    check_recording(rec)  # counts, padding, identities in range and present
    real = (rec.identity >= 0)[..., None] & (rec.detections.score > 0)
    err = np.linalg.norm(rec.detections.xy - rec.projected, axis=-1)[
        real & ~_swapped_rows(scene)[..., None]
    ]
    # Detector error, relative to the person's size, is a few pixels to tens of pixels.
    assert 2.0 < np.median(err) < 20.0
    assert np.percentile(err, 99) < 120.0
    # Every reported person has exactly one row in its view.
    counts = np.stack([(rec.identity == g).sum(-1) for g in range(4)], -1)
    np.testing.assert_array_equal(counts, scene.truth.reported.astype(int))


def _swapped_rows(scene):
    rec = scene.recording
    sw = scene.truth.swapped  # (F, C, G)
    f, c, p = np.nonzero(rec.identity >= 0)
    out = np.zeros(rec.identity.shape, bool)
    out[f, c, p] = sw[f, c, rec.identity[f, c, p]] > 0
    return out


def test_rates_match_configuration(measured):
    sc, cfg = measured
    rec, tr = sc.recording, sc.truth
    det = rec.detections
    # Miss rate: (frame, camera, person in view) without a detection.
    has = _per_person(rec, np.ones(rec.identity.shape, bool), False)
    miss = 1.0 - has[tr.in_view].mean()
    assert miss == pytest.approx(cfg.miss_rate, rel=0.2)
    # False positives per view and frame.
    rows = np.arange(det.score.shape[2]) < det.count[..., None]
    fp = ((rec.identity < 0) & rows).sum(-1).mean()
    assert fp == pytest.approx(cfg.false_positive_rate, rel=0.2)
    # Occlusion: occluded in-image keypoints of reported, unswapped people are missing at the
    # configured rate (the occlusion itself comes from geometry, so it must be common enough).
    score = _per_person(rec, det.score)  # (F, C, G, K)
    ok = (tr.reported & (tr.swapped == 0))[..., None] & tr.in_image
    occ = ok & tr.occluded
    assert occ.sum() > 1000 and tr.occluded_by_others.sum() > 0
    assert (score[occ] == 0).mean() == pytest.approx(cfg.occluded_drop_rate, rel=0.2)
    assert (score[ok & ~tr.occluded] == 0).mean() == pytest.approx(cfg.keypoint_drop_rate, rel=0.2)
    # Swaps among reported detections; scores lower for occluded keypoints.
    assert (tr.swapped[tr.reported] > 0).mean() == pytest.approx(cfg.swap_rate, rel=0.2)
    kept = score > 0
    assert score[occ & kept].mean() < 0.8 * score[ok & ~tr.occluded & kept].mean()


def test_seed_makes_runs_reproducible(panoptic):
    a = generate_recording(panoptic, num_people=2, num_frames=40, seed=11)
    b = generate_recording(panoptic, num_people=2, num_frames=40, seed=11)
    c = generate_recording(panoptic, num_people=2, num_frames=40, seed=12)
    for x, y in (
        (a.detections.xy, b.detections.xy),
        (a.identity, b.identity),
        (a.ground_truth.xyz, b.ground_truth.xyz),
        (a.projected, b.projected),
    ):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.ground_truth.xyz, c.ground_truth.xyz)


def test_single_person_recordings(panoptic):
    recs = generate_single_person_recordings(panoptic, num_recordings=3, num_frames=50, seed=2)
    assert len(recs) == 3
    heights = set()
    for rec in recs:
        check_recording(rec)
        assert rec.ground_truth.xyz.shape == (50, 1, 18, 3)
        assert set(np.unique(rec.identity)) <= {-1, 0}
        assert (rec.identity == 0).sum() > 0.5 * rec.detections.count.size
        heights.add(round(float(np.ptp(rec.ground_truth.xyz[0, 0] @ np.asarray(panoptic.up))), 4))
    assert len(heights) == 3  # different bodies


def test_detection_variants(scene):
    rec = scene.recording
    v = detection_variants(rec)
    assert v["detected"] is rec
    present = rec.detections.score > 0
    np.testing.assert_allclose(
        v["projected"].detections.xy[present], rec.projected[present], atol=1e-4
    )
    mean = 0.5 * (rec.detections.xy + rec.projected)
    np.testing.assert_allclose(v["average"].detections.xy[present], mean[present], atol=1e-4)
    for name in ("projected", "average"):
        assert np.all(v[name].detections.xy[~present] == 0)
        np.testing.assert_array_equal(v[name].detections.score, rec.detections.score)
    clean = dataclasses.replace(rec, projected=None)
    with pytest.raises(ValueError):
        detection_variants(clean)


def test_clean_detector_reports_exact_projections(panoptic):
    cfg = SyntheticConfig().replace(detector=SyntheticConfig().detector.clean())
    rec = generate_recording(panoptic, num_people=2, num_frames=30, config=cfg, seed=4)
    present = rec.detections.score > 0
    assert (rec.identity >= 0)[
        rows := np.arange(rec.identity.shape[2]) < rec.detections.count[..., None]
    ].all()
    assert rows.any()
    np.testing.assert_allclose(rec.detections.xy[present], rec.projected[present], atol=1e-3)


def test_generate_command(tmp_path):
    out = tmp_path / "scene.json"
    argv = [
        "generate",
        "--rig",
        "panoptic5",
        "--people",
        "2",
        "--frames",
        "12",
        "--seed",
        "1",
        "--out",
        str(out),
        "--false-positive-rate",
        "0",
    ]
    assert cli.main(argv) == 0
    rec = load_recording(out)
    assert rec.detections.score.shape[:2] == (12, 5)
    assert rec.ground_truth.xyz.shape == (12, 2, 18, 3)
    assert np.all(
        rec.identity[np.arange(rec.identity.shape[2]) < rec.detections.count[..., None]] >= 0
    )
    argv = [
        "generate",
        "--rig",
        "panoptic5",
        "--single-person-recordings",
        "2",
        "--frames",
        "8",
        "--out",
        str(tmp_path / "train"),
        "--format",
        "npz",
    ]
    assert cli.main(argv) == 0
    assert sorted(p.name for p in (tmp_path / "train").iterdir()) == [
        "person_0.npz",
        "person_1.npz",
    ]


def test_synthetic_figure_command(tmp_path, capsys):
    out = tmp_path / "frame.png"
    argv = [
        "synthetic-figure",
        "--rig",
        "panoptic5",
        "--people",
        "2",
        "--frames",
        "3",
        "--out",
        str(out),
    ]
    assert cli.main(argv) == 0
    assert capsys.readouterr().out.strip() == str(out)
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_floor_jitter_gives_each_recording_its_own_floor(panoptic):
    base = scene_geometry(panoptic).floor_height
    config = SyntheticConfig(scene=dataclasses.replace(SyntheticConfig().scene, floor_jitter_m=0.3))
    scenes = simulate(panoptic, num_people=1, num_frames=15, num_scenes=8, config=config, seed=2)
    floors = np.array([s.geometry.floor_height for s in scenes])
    assert len(np.unique(floors)) >= 5 and np.abs(floors - base).max() <= 0.3 + 1e-9
    for s in scenes:  # people stand on their own recording's floor (ankles 6-7 cm above it)
        h = np.asarray(s.recording.ground_truth.xyz) @ s.geometry.up - s.geometry.floor_height
        low = np.minimum(h[..., COCO18.index("l_ankle")], h[..., COCO18.index("r_ankle")])
        assert 0.04 < np.median(low) < 0.09
    # No jitter (the default) is the generator as it was: one floor, the same recordings.
    still = dataclasses.replace(config, scene=dataclasses.replace(config.scene, floor_jitter_m=0))
    a = simulate(panoptic, num_people=1, num_frames=15, num_scenes=2, config=still, seed=2)
    b = simulate(panoptic, num_people=1, num_frames=15, num_scenes=2, seed=2)
    np.testing.assert_array_equal(a[1].recording.detections.xy, b[1].recording.detections.xy)
    bad = dataclasses.replace(config, scene=dataclasses.replace(config.scene, floor_jitter_m=-1))
    with pytest.raises(InputError, match="floor_jitter_m"):
        simulate(panoptic, num_people=1, num_frames=5, config=bad)
