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
from mvpose_jax.synthetic.detector import MIX_LIMBS, behind_boxes
from mvpose_jax.synthetic.shifts import SHIFTS, perturb_rig


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


# --------------------------------------------------------------------------- domain shifts


def _digest(recordings) -> str:
    """A hash of recordings' arrays, rounded well below the generator's precision (so that a
    different BLAS's last bits do not change it)."""
    import hashlib

    h = hashlib.sha256()
    for r in recordings:
        for a in (
            np.round(np.asarray(r.detections.xy, np.float64), 2),
            np.round(np.asarray(r.detections.score, np.float64), 4),
            np.asarray(r.detections.count),
            np.asarray(r.identity),
            np.round(np.asarray(r.ground_truth.xyz, np.float64), 4),
        ):
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def test_default_recordings_unchanged_by_the_shift_settings(panoptic):
    # Hashes of the default generator's output taken before the domain-shift settings existed
    # (commit 544c729): every new setting is off by default and draws no random numbers then.
    scene = generate_recording(panoptic, num_people=4, num_frames=40, seed=[0, 5, 4])
    train = generate_single_person_recordings(
        panoptic, num_recordings=3, num_frames=20, seed=[0, 1]
    )
    assert _digest([scene]) == DEFAULT_SCENE_DIGEST
    assert _digest(train) == DEFAULT_TRAIN_DIGEST


DEFAULT_SCENE_DIGEST = "fb174ab1e4c46c7ddc4dd209fccbb44123548c2f4af3368d3684c3cb9308ed23"
DEFAULT_TRAIN_DIGEST = "c629826205ce52642af8af87c7e77ff4840140d2d36735a2392e76e4385dfa8b"


@pytest.mark.filterwarnings("ignore::mvpose_jax.data.checks.ScoreClippedWarning")
@pytest.mark.parametrize("name", sorted(SHIFTS))
def test_shifts_reproduce_from_the_seed(panoptic, name):
    def make():
        rig, config = SHIFTS[name].apply(panoptic, seed=[1, 2])
        return generate_recording(rig, num_people=3, num_frames=8, config=config, seed=5)

    a, b = make(), make()
    np.testing.assert_array_equal(a.detections.xy, b.detections.xy)
    np.testing.assert_array_equal(a.detections.score, b.detections.score)
    np.testing.assert_array_equal(a.identity, b.identity)
    check_recording(a)


def _quiet(config: SyntheticConfig) -> SyntheticConfig:
    """Only pixel noise (and the effect under test): no offsets, swaps, false positives."""
    return config.with_detector(
        offset_scale=0.0,
        noise_floor_px=0.0,
        occluded_noise_factor=1.0,
        swap_rate=0.0,
        false_positive_rate=0.0,
        miss_rate=0.0,
    )


def test_coco_sigmas_heavy_tailed_noise_per_keypoint(panoptic):
    from scipy import stats

    config = _quiet(SHIFTS["coco-sigmas"].config(SyntheticConfig()))
    sc = simulate(panoptic, num_people=2, num_frames=400, config=config, seed=11)[0]
    tr, rec = sc.truth, sc.recording
    xy = _per_person(rec, rec.detections.xy)
    has = _per_person(rec, rec.detections.score) > 0
    scale = np.asarray(config.detector.keypoint_noise_scale)
    # Normalised errors: (reported - projection) / (noise_relative * image height * scale_k).
    sigma = config.detector.noise_relative * tr.height_px[..., None] * scale
    z = (xy - tr.projected) / sigma[..., None]
    # Truncation at the image border removes a few large errors; keep keypoints well inside.
    size = np.asarray(panoptic.size)[None, :, None, None]
    central = has & (tr.projected > 50).all(-1) & (tr.projected < size - 50).all(-1)
    z = z[central].ravel()
    assert z.size > 20000
    q = np.array([0.5, 0.9, 0.99, 0.999])
    np.testing.assert_allclose(np.quantile(np.abs(z), q), stats.t.ppf(0.5 + q / 2, df=3), rtol=0.08)
    # Heavier tails than a Gaussian's: 1 in 1000 beyond 12.9 scales, not 3.3.
    assert np.quantile(np.abs(z), 0.999) > 2.5 * stats.norm.ppf(0.9995)
    # The sigmas' order survives: hips are noisier than eyes by their ratio 1.07 / 0.25.
    raw = np.abs(xy - tr.projected) / tr.height_px[..., None, None]
    ratio = np.median(raw[..., 11, :][central[..., 11]]) / np.median(
        raw[..., 1, :][central[..., 1]]
    )
    assert ratio == pytest.approx(0.107 / 0.025, rel=0.1)


def test_part_mixing_takes_the_nearest_persons_limb(panoptic):
    config = _quiet(SyntheticConfig()).with_detector(
        limb_mix_rate=0.3, mix_distance=1.0, duplicate_rate=0.1, fragment_rate=0.1
    )
    sc = simulate(panoptic, num_people=4, num_frames=150, config=config, seed=4)[0]
    tr, rec = sc.truth, sc.recording
    xy = _per_person(rec, rec.detections.xy)
    mixed = tr.mixed
    assert mixed.sum() > 300
    f, c, g, limb = np.nonzero(mixed)
    kps = MIX_LIMBS[limb]  # (n, 2)
    fi, ci, gi = f[:, None], c[:, None], g[:, None]
    reported = xy[fi, ci, gi, kps]  # (n, 2, 2)
    present = _per_person(rec, rec.detections.score)[fi, ci, gi, kps] > 0
    # Each mixed limb lies on another person's true projection, not on the person's own.
    proj = tr.projected[f, c]  # (n, G, K, 2)
    limb_proj = np.take_along_axis(proj, kps[:, None, :, None], axis=2)  # (n, G, 2, 2)
    dist = np.linalg.norm(reported[:, None] - limb_proj, axis=-1)  # (n, G, 2)
    own = dist[np.arange(len(g)), g]  # (n, 2)
    dist[np.arange(len(g)), g] = np.inf
    other = dist.min(1)
    assert present.sum() > 300
    assert np.mean(other[present] < 20) > 0.95
    assert np.mean(own[present] > other[present]) > 0.95
    # The rate among the eligible (reported, another person near) is the setting; it cannot be
    # read back exactly without the eligibility, so: at most the rate, and not far below it.
    rate = mixed.any(-1).mean() / tr.reported.mean()
    assert 0.05 < rate < 1 - (1 - 0.3) ** 4 + 0.02
    # Duplicates and fragments: extra rows with identity -1, at their rates.
    for flag, p in ((tr.duplicated, 0.1), (tr.fragmented, 0.1)):
        assert flag[tr.reported].mean() == pytest.approx(
            p, rel=0.2 if flag is tr.duplicated else 0.4
        )
    extra = tr.duplicated.sum(-1) + tr.fragmented.sum(-1)
    rows_minus_one = (rec.identity == -1).sum(-1) - (
        np.arange(rec.identity.shape[-1]) >= rec.detections.count[..., None]
    ).sum(-1)
    np.testing.assert_array_equal(rows_minus_one, extra + sc.num_false_positives)


def test_behind_boxes_closed_form():
    # A unit box at the origin; cameras at z = 5 (above) and x = 5 (beside), points at z = -3.
    origins = np.array([[0.0, 0.0, 5.0], [5.0, 0.0, -3.0]])
    points = np.array([[0.0, 0.0, -3.0], [3.0, 0.0, -3.0], [0.3, 0.2, 0.1], [0.0, 0.0, 0.6]])
    points = points[None, None]  # (F=1, G=1, K=4, 3)
    centre, axes, half = np.zeros((1, 1, 3)), np.eye(3)[None, None], np.full((1, 1, 3), 0.5)
    hidden = behind_boxes(origins, points, centre, axes, half)[:, 0, 0]  # (C, K)
    # Above: straight through the box; beside the box's x range at x = 3 (the ray from (0, 0, 5)
    # to (3, 0, -3) crosses z = 0.5 at x = 1.69); inside the box; just above its top face.
    np.testing.assert_array_equal(hidden[0], [True, False, True, False])
    # Beside: the rays at z = -3 pass below the box (z in [-0.5, 0.5]); the point inside it is
    # hidden; the ray rising to (0, 0, 0.6) enters the box at x = 0.5, z = 0.24.
    np.testing.assert_array_equal(hidden[1], [False, False, True, True])
    # Rotating the box about z by 45 degrees keeps the vertical ray's answers.
    c45 = np.sqrt(0.5)
    rot = np.array([[c45, c45, 0], [-c45, c45, 0], [0, 0, 1]])[None, None]
    np.testing.assert_array_equal(
        behind_boxes(origins[:1], points, centre, rot, half)[0, 0, 0], hidden[0]
    )


def test_occluders_hide_keypoints_behind_boxes(panoptic):
    config = SHIFTS["occluders"].config(SyntheticConfig())
    sc = simulate(panoptic, num_people=3, num_frames=120, config=config, seed=2)[0]
    tr, rec, occ = sc.truth, sc.recording, sc.occluders
    assert occ is not None and occ.centre.shape == (3, 3)
    behind = tr.behind_occluder
    assert 0.002 < behind[tr.in_image].mean() < 0.6
    # Hidden keypoints are never reported.
    has = _per_person(rec, rec.detections.score) > 0
    assert not (has & behind).any()
    # Independent check: points sampled along camera-to-keypoint segments fall inside a box.
    rng = np.random.default_rng(0)
    f, c, g, k = (a[:400] for a in np.nonzero(tr.in_image))
    pick = rng.permutation(len(f))[:400]
    f, c, g, k = f[pick], c[pick], g[pick], k[pick]
    cam = sc.geometry.cameras.centres[c]  # (n, 3)
    kp = sc.points[f, g, k]
    s = np.linspace(0, 1, 2001)[None, :, None]
    path = cam[:, None] + s * (kp - cam)[:, None]  # (n, S, 3)
    local = np.einsum("oij,nsoj->nsoi", occ.axes, path[:, :, None] - occ.centre)
    inside = (np.abs(local) <= occ.half).all(-1).any((-1, -2))
    np.testing.assert_array_equal(inside, behind[f, c, g, k])
    # Boxes stand on the floor outside the capture area.
    geo = sc.geometry
    rel = occ.centre - geo.origin
    np.testing.assert_allclose(rel @ geo.up, occ.half[:, 2], atol=1e-9)
    assert not geo.contains(np.stack([rel @ geo.e1, rel @ geo.e2], -1)).any()
    # Border margin: nothing reported within 5 % of the image height of the border.
    xy = np.asarray(rec.detections.xy)
    size = np.asarray(panoptic.size)[None, :, None, None]
    m = 0.05 * size[..., 1]
    present = (rec.detections.score > 0) & (rec.identity >= 0)[..., None]  # not false positives
    assert ((xy[..., 0] >= m) & (xy[..., 0] < size[..., 0] - m) & (xy[..., 1] >= m))[present].all()


def test_score_shift_distribution(panoptic):
    from scipy import stats

    config = SHIFTS["scores"].config(SyntheticConfig()).with_detector(false_positive_rate=0.0)
    rec = generate_recording(panoptic, num_people=3, num_frames=100, config=config, seed=9)
    s = np.asarray(rec.detections.score)
    s = s[s > 0]
    assert 1.0 < s.max() <= 1.04 + 1e-6
    # Scores are 1.04 Beta(4, 1.5), clipped below at 0.05 (a negligible mass), whatever the
    # keypoint's occlusion or the person's size.
    ks = stats.kstest(s / 1.04, stats.beta(4.0, 1.5).cdf)
    assert ks.statistic < 0.02


def test_world_shift_children_and_poses(panoptic):
    config = SHIFTS["world"].config(SyntheticConfig())
    sc = simulate(panoptic, num_people=1, num_frames=60, num_scenes=40, config=config, seed=3)
    h = np.array([s.bodies.height[0] for s in sc])
    child = h < 1.45
    assert 0.3 < child.mean() < 0.7
    assert np.all((h[child] >= 1.1) & (h[child] <= 1.4))
    # Bones stay rigid for children too, and feet stay on the floor.
    geo = sc[0].geometry
    for s in sc[:5]:
        up = (s.points - geo.origin) @ geo.up
        ankle = up[..., [bm.L_ANKLE, bm.R_ANKLE]].min(-1)
        np.testing.assert_allclose(
            ankle, np.broadcast_to(s.bodies.ankle_height, ankle.shape), atol=1e-6
        )
    # Wrists above the top of the head happen (arms straight up).
    wrist_up = max(
        (((s.points - geo.origin) @ geo.up)[..., [9, 10]].max() - s.bodies.height[0]) for s in sc
    )
    assert wrist_up > 0.1


@pytest.mark.parametrize("offset", [0.3, -0.6])
def test_floor_shift_moves_the_scene(panoptic, offset):
    base = scene_geometry(panoptic).floor_height
    rig, config = SHIFTS[f"floor{offset:+.1f}"].apply(panoptic)
    sc = simulate(rig, num_people=2, num_frames=30, config=config, seed=1)[0]
    assert sc.geometry.floor_height == pytest.approx(base + offset)
    up = sc.points @ sc.geometry.up - sc.geometry.floor_height
    ankle = up[..., [bm.L_ANKLE, bm.R_ANKLE]].min(-1)
    np.testing.assert_allclose(
        ankle, np.broadcast_to(sc.bodies.ankle_height, ankle.shape), atol=1e-6
    )


def test_calibration_shift_size(panoptic):
    bad = perturb_rig(panoptic, rotation_px=(0.5, 1.0), translation_m=0.01, seed=[0, 1])
    R0, R1 = np.asarray(panoptic.R, np.float64), np.asarray(bad.R, np.float64)
    fx = np.asarray(panoptic.K)[:, 0, 0]
    delta = np.einsum("cij,ckj->cik", R1, R0)  # R1 R0^T
    axis = np.stack(
        [
            delta[:, 2, 1] - delta[:, 1, 2],
            delta[:, 0, 2] - delta[:, 2, 0],
            delta[:, 1, 0] - delta[:, 0, 1],
        ],
        -1,
    )  # 2 sin(angle) times the unit axis (float32 rotations: no arccos of the trace)
    angle = np.arcsin(np.linalg.norm(axis, axis=-1) / 2)
    assert np.all((angle * fx > 0.5 - 0.05) & (angle * fx < 1.0 + 0.05))
    c0 = -np.einsum("cji,cj->ci", R0, np.asarray(panoptic.t, np.float64))
    c1 = -np.einsum("cji,cj->ci", R1, np.asarray(bad.t, np.float64))
    np.testing.assert_allclose(np.linalg.norm(c1 - c0, axis=-1), 0.01, atol=2e-4)
    # In pixels: a far point on each optical axis moves by fx * angle * sin(axis, optical axis).
    far = c0 + 1e4 * R0[:, 2]  # (C, 3)
    p0 = np.asarray(project_points(panoptic, jnp.asarray(far, jnp.float32)))  # (C, C, 2)
    p1 = np.asarray(project_points(bad, jnp.asarray(far, jnp.float32)))
    moved = np.linalg.norm(p1 - p0, axis=-1).diagonal()
    # delta = R1 R0^T is the rotation in the camera's frame: its axis is in camera coordinates.
    axis_cam = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    sin = np.linalg.norm(axis_cam[:, :2], axis=-1)
    np.testing.assert_allclose(moved, fx * angle * sin, atol=0.05)
    assert np.all(moved <= 1.0 + 0.05)
