"""A 2D skeleton detector model: what an OpenPose-like detector reports for the true 3D poses.

Effects, each configured in `DetectorConfig` and on by default at realistic levels:

* Systematic offsets: detectors do not mark the joint centres a motion-capture ground truth
  holds (hips sit higher and wider, shoulders higher, knees on the kneecap …). A per-keypoint
  offset in the person's body frame (`SYSTEMATIC_OFFSETS`, varied per person) moves each keypoint
  in 3D before projection, so it is consistent across views, like a real detector's bias.
* Pixel noise: per axis, ``noise_relative * h + noise_floor`` pixels, with h the person's height
  in the image; the floor makes the relative error grow as people get small. Occluded keypoints
  are noisier (the detector guesses them).
* Occlusion, from geometry: body volumes are capsules (limbs, torso sides and centre, head
  sphere). A keypoint is occluded when a capsule of its own body (not one it belongs to) or of
  someone else covers it in the image and lies in front of it; face keypoints turned away from
  the camera are occluded by the head. Occluded keypoints are dropped at ``occluded_drop_rate``
  and otherwise reported with lower scores.
* Truncation: keypoints outside the image (or behind the camera) are never reported.
* Scores fall with occlusion and with the person's image size, plus noise.
* Missed people (``miss_rate``), false-positive skeletons (partial bodies off the people, Poisson
  ``false_positive_rate`` per view and frame) and left/right swaps (``swap_rate``).

Everything is vectorised over frames, cameras and people (frames are processed in chunks to bound
memory, never one at a time).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from mvpose_jax.synthetic import body as bm
from mvpose_jax.synthetic.config import DetectorConfig
from mvpose_jax.synthetic.scene import MIN_DEPTH, CameraModel, SceneGeometry

K = bm.NUM_KEYPOINTS

# Systematic offsets (metres for a 1.75 m person) in the body frame: forward, outward (away from
# the body's midline; mirrored for the right side), up. Typical of COCO-trained detectors against
# joint-centre ground truth (e.g. CMU Panoptic): hips placed high and wide at the trochanters,
# shoulders on the acromion, knees on the kneecap; 0.6-3.2 cm, 1.3 cm on average.
SYSTEMATIC_OFFSETS = np.array(
    [
        [0.008, 0.000, 0.000],  # nose
        [0.004, 0.000, 0.004],
        [0.004, 0.000, 0.004],  # eyes
        [0.008, -0.008, 0.000],
        [0.008, -0.008, 0.000],  # ears
        [0.000, 0.008, 0.015],
        [0.000, 0.008, 0.015],  # shoulders
        [0.000, 0.008, 0.000],
        [0.000, 0.008, 0.000],  # elbows
        [0.008, 0.000, 0.000],
        [0.008, 0.000, 0.000],  # wrists
        [0.000, 0.020, 0.025],
        [0.000, 0.020, 0.025],  # hips
        [0.015, 0.000, 0.000],
        [0.015, 0.000, 0.000],  # knees
        [0.000, 0.000, 0.010],
        [0.000, 0.000, 0.010],  # ankles
        [0.008, 0.000, 0.015],  # neck
    ]
)
_SIDE = np.array([0, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 0], np.float64)

# Score of a clearly visible keypoint of a large person: faces and the neck are easy, wrists,
# hips and ankles hard.
BASE_SCORES = np.array(
    [
        0.90,
        0.88,
        0.88,
        0.80,
        0.80,
        0.85,
        0.85,
        0.80,
        0.80,
        0.72,
        0.72,
        0.72,
        0.72,
        0.78,
        0.78,
        0.72,
        0.72,
        0.90,
    ]
)
# Facing test of face keypoints: visible when cos(normal, direction to the camera) exceeds this.
_FACE_COS = np.array([-0.1, -0.1, -0.1, -0.35, -0.35])

# Left/right swaps: arms, legs, the whole body.
_L_ARM, _R_ARM = [5, 7, 9], [6, 8, 10]
_L_LEG, _R_LEG = [11, 13, 15], [12, 14, 16]


def _swap_permutations() -> np.ndarray:
    perms = np.tile(np.arange(K), (4, 1))
    for row, (a, b) in ((1, (_L_ARM, _R_ARM)), (2, (_L_LEG, _R_LEG))):
        perms[row, a], perms[row, b] = b, a
    perms[3] = [0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15, 17]
    return perms


_SWAPS = _swap_permutations()

# Parts a false positive can show (masks over coco18), plus "random".
_PARTS = np.zeros((7, K), bool)
_PARTS[0, [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 17]] = True  # upper body
_PARTS[1, [11, 12, 13, 14, 15, 16]] = True  # legs
_PARTS[2, [5, 7, 9, 17]] = True  # an arm
_PARTS[3, [6, 8, 10, 17]] = True
_PARTS[4, [0, 1, 2, 3, 4, 5, 6, 17]] = True  # head and shoulders
_PARTS[5, [11, 13, 15]] = True  # a leg
_PARTS[6, [12, 14, 16]] = True


# Lower limbs that bottom-up part mixing exchanges between people: forearms (elbow, wrist) and
# shins (knee, ankle), left and right.
MIX_LIMBS = np.array([[7, 9], [8, 10], [13, 15], [14, 16]])


class Occluders(NamedTuple):
    """Static boxes of B scenes, O per scene (world coordinates, metres)."""

    centre: np.ndarray  # (B, O, 3)
    axes: np.ndarray  # (B, O, 3, 3) rows: the box's width, depth and height directions
    half: np.ndarray  # (B, O, 3) half the width, depth and height


@dataclasses.dataclass(frozen=True)
class DetectorOutput:
    """Per-person detector results, F frames, C cameras, G people (before assembly into rows)."""

    xy: np.ndarray  # (F, C, G, K, 2) reported pixels (after swaps); 0 where missing
    score: np.ndarray  # (F, C, G, K) 0 = missing
    reported: np.ndarray  # (F, C, G) bool: the person has a detection in this view
    projected: np.ndarray  # (F, C, G, K, 2) noise-free projection of the ground truth
    in_image: np.ndarray  # (F, C, G, K) bool: the true keypoint projects inside the image
    occluded: np.ndarray  # (F, C, G, K) bool: by the own body or someone else
    occluded_by_others: np.ndarray  # (F, C, G, K) bool
    in_view: np.ndarray  # (F, C, G) bool: >= min_keypoints_in_view keypoints in the image
    missed: np.ndarray  # (F, C, G) bool: dropped by the miss rate
    swapped: np.ndarray  # (F, C, G) int: 0 none, 1 arms, 2 legs, 3 whole body
    height_px: np.ndarray  # (F, C, G) the person's height in the image, pixels
    behind_occluder: np.ndarray  # (F, C, G, K) bool: the keypoint is hidden by a static box
    mixed: np.ndarray  # (F, C, G, 4) bool: the lower limb (`MIX_LIMBS`) is another person's
    duplicated: np.ndarray  # (F, C, G) bool: the detection is reported twice
    fragmented: np.ndarray  # (F, C, G) bool: the detection comes with a fragment skeleton


def detect_people(
    cams: CameraModel,
    points: np.ndarray,
    axes: np.ndarray,
    heights: np.ndarray,
    radii: np.ndarray,
    group: np.ndarray,
    config: DetectorConfig,
    rng: np.random.Generator,
    occluders: Occluders | None = None,
) -> DetectorOutput:
    """Runs the detector model on the true poses.

    Args:
      cams: the cameras.
      points: (F, G, NUM_POINTS, 3) world points (keypoints, pelvis and head centres), metres.
      axes: (F, G, 3, 3) each person's heading frame in the world (rows forward, left, up).
      heights: (G,) standing heights, metres.
      radii: (G, S) capsule radii, metres.
      group: (G,) scene of each person; people occlude only people of their own scene.
      config: detector settings.
      rng: random generator.
      occluders: static boxes of each scene (indexed by ``group``); None: none.
    """
    F, G = points.shape[:2]
    C = cams.num_cameras
    # Person-level systematic offsets in the body frame, scaled by height, mirrored by side.
    table = SYSTEMATIC_OFFSETS * np.stack([np.ones(K), _SIDE, np.ones(K)], -1)
    person_off = (
        table[None]
        * (1 + config.offset_person_std * rng.standard_normal((G, K, 3)))
        * (heights / 1.75)[:, None, None]
        * config.offset_scale
    )  # (G, K, 3)
    offsets = np.einsum("gkj,fgjd->fgkd", person_off, axes)  # (F, G, K, 3) world
    exempt = bm.capsule_exempt()
    # Bound temporaries to about 4 M entries per (C, frames, G, K, S) array.
    chunk = max(1, int(4e6 // (C * G * K * bm.NUM_CAPSULES)))
    parts = [
        _detect_chunk(
            cams,
            points[s : s + chunk],
            offsets[s : s + chunk],
            heights,
            radii,
            group,
            exempt,
            config,
            rng,
            occluders,
        )
        for s in range(0, F, chunk)
    ]
    return DetectorOutput(
        *(np.concatenate(a, axis=0) for a in zip(*(_fields(p) for p in parts), strict=True))
    )


def _detect_chunk(
    cams, points, offsets, heights, radii, group, exempt, config: DetectorConfig, rng, occluders
):
    F, G = points.shape[:2]
    C = cams.num_cameras
    pc = cams.to_camera(points)  # (C, F, G, NP, 3)
    px_true, z, in_img = cams.project_camera_points(pc[..., :K, :])
    px_bias, _, _ = cams.project(points[..., :K, :] + offsets)

    occluded, by_others = _occlusion(pc, radii, group, exempt)

    # Person height in the image from the pelvis depth: robust to truncation.
    z_pelvis = pc[..., bm.PELVIS, 2]
    fy = cams.K[:, 1, 1].reshape(C, 1, 1)
    height_px = np.where(
        z_pelvis > MIN_DEPTH, fy * heights[None, None] / np.maximum(z_pelvis, MIN_DEPTH), 0.0
    )
    img_h = cams.size[:, 1].reshape(C, 1, 1)
    diag = np.hypot(cams.size[:, 0], cams.size[:, 1]).reshape(C, 1, 1)

    # Pixel noise: relative to the person's image height, plus a floor scaled by image size.
    sigma = config.noise_relative * height_px + config.noise_floor_px * diag / np.hypot(1920, 1080)
    sigma = sigma[..., None] * np.where(occluded, config.occluded_noise_factor, 1.0)
    if config.keypoint_noise_scale is not None:
        sigma = sigma * np.asarray(config.keypoint_noise_scale, np.float64)
    noise = (
        rng.standard_normal(px_bias.shape)
        if config.noise_tail_dof is None
        else rng.standard_t(config.noise_tail_dof, px_bias.shape)
    )
    xy = px_bias + sigma[..., None] * noise
    w, h = cams.size[:, 0].reshape(C, 1, 1, 1), cams.size[:, 1].reshape(C, 1, 1, 1)
    m = config.border_margin * h  # 0 by default: only keypoints outside the image are lost
    inside = (
        in_img & (xy[..., 0] >= m) & (xy[..., 0] < w - m) & (xy[..., 1] >= m) & (xy[..., 1] < h - m)
    )
    behind = np.zeros_like(inside)
    if occluders is not None and occluders.centre.shape[1]:
        behind = behind_boxes(
            cams.centres,
            points[..., :K, :],
            occluders.centre[group],
            occluders.axes[group],
            occluders.half[group],
        )

    # Scores: fall with size (half at size_half_score of the image height) and with occlusion.
    size_factor = 1.0 / (1.0 + (config.size_half_score * img_h / np.maximum(height_px, 1e-6)) ** 2)
    quality = rng.uniform(0.85, 1.0, (C, F, G, 1))
    score = (
        BASE_SCORES
        * size_factor[..., None]
        * quality
        * np.where(occluded, config.occluded_score_factor, 1.0)
    )
    score = np.clip(score + config.score_noise * rng.standard_normal(score.shape), 0.05, 1.0)
    if config.score_beta is not None:
        # Another detector's calibration: scores from a Beta distribution, up to score_max
        # (OpenPose's reach about 1.04), that know nothing of size (and, with
        # occluded_score_factor 1, nothing of occlusion).
        score = config.score_max * rng.beta(*config.score_beta, score.shape)
        score = score * np.where(occluded, config.occluded_score_factor, 1.0)
        score = np.clip(score, 0.05, config.score_max)

    u = rng.random(score.shape)
    dropped = np.where(occluded, u < config.occluded_drop_rate, u < config.keypoint_drop_rate)
    kept = inside & ~dropped & ~behind
    n_in = in_img.sum(-1)
    in_view = n_in >= config.min_keypoints_in_view
    candidate = n_in >= max(config.min_keypoints, 1)
    missed = candidate & (rng.random((C, F, G)) < config.miss_rate)
    reported = candidate & ~missed & (kept.sum(-1) >= config.min_keypoints)

    # Left/right swaps of reported detections.
    swap = np.where(
        reported & (rng.random((C, F, G)) < config.swap_rate),
        rng.choice([1, 2, 3], (C, F, G), p=[0.4, 0.4, 0.2]),
        0,
    )
    sw = np.nonzero(swap)
    if sw[0].size:
        perm = _SWAPS[swap[sw]]  # (n, K)
        rows = np.arange(perm.shape[0])[:, None]
        xy[sw] = xy[sw][rows, perm]
        score[sw] = score[sw][rows, perm]
        kept[sw] = kept[sw][rows, perm]
    kept &= reported[..., None]
    score = np.where(kept, score, 0.0)
    xy = np.where(kept[..., None], xy, 0.0)

    tr = lambda a: np.swapaxes(a, 0, 1)  # noqa: E731  (C, F, ...) -> (F, C, ...)
    return DetectorOutput(
        tr(xy).astype(np.float32),
        tr(score).astype(np.float32),
        tr(reported),
        tr(px_true),
        tr(in_img),
        tr(occluded),
        tr(by_others),
        tr(in_view),
        tr(missed),
        tr(swap),
        tr(height_px),
        tr(behind),
        np.zeros((F, C, G, len(MIX_LIMBS)), bool),
        np.zeros((F, C, G), bool),
        np.zeros((F, C, G), bool),
    )


def behind_boxes(
    origins: np.ndarray,
    points: np.ndarray,
    centre: np.ndarray,
    axes: np.ndarray,
    half: np.ndarray,
) -> np.ndarray:
    """Whether the segment from each camera centre to each point passes through a box.

    Slab test in each box's frame: the segment's parameter intervals inside the three slabs
    overlap somewhere in [0, 1] (a point inside a box counts as hidden).

    Args:
      origins: (C, 3) camera centres, world.
      points: (F, G, K, 3) world points.
      centre, axes, half: each person's boxes, (G, O, 3), (G, O, 3, 3) (rows: box axes in the
        world), (G, O, 3).
    Returns:
      (C, F, G, K) bool.
    """
    # Box frames: a the camera centre, d the segment, (C, F, G, K, O, 3).
    a = np.einsum("goij,cgoj->cgoi", axes, origins[:, None, None] - centre[None])
    a = a[:, None, :, None]  # (C, 1, G, 1, O, 3)
    d = np.einsum("goij,cfgkj->cfgkoi", axes, points[None] - origins[:, None, None, None])
    h = half[None, None, :, None]  # (1, 1, G, 1, O, 3)
    parallel = np.abs(d) < 1e-12
    d_safe = np.where(parallel, 1.0, d)
    t1, t2 = (-h - a) / d_safe, (h - a) / d_safe
    # A segment parallel to a slab is inside it everywhere or nowhere.
    inside_slab = np.abs(a) <= h
    lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    t_in, t_out = lo.max(-1), hi.min(-1)  # (C, F, G, K, O)
    return ((t_in <= t_out) & (t_out >= 0.0) & (t_in <= 1.0)).any(-1)


def place_occluders(
    geometry: SceneGeometry, num_scenes: int, config: DetectorConfig, rng: np.random.Generator
) -> Occluders:
    """Boxes on the floor just outside the capture area, each between a camera and the people.

    Each box: pick a camera and a capture-area cell, walk from the cell towards the camera's
    floor point until leaving the capture area, and stand the box 0.3 m further on, facing the
    camera. People walk in the capture area, so they do not walk into the boxes (a crowd can
    push someone out of the area; their keypoints inside a box count as hidden).
    """
    B, per_scene = num_scenes, config.num_occluders
    cams = geometry.cameras
    n = B * per_scene
    cam = rng.integers(0, cams.num_cameras, n)
    cell = geometry.cells[rng.integers(0, len(geometry.cells), n)]  # (n, 2)
    rel = cams.centres[cam] - geometry.origin
    cam_ab = np.stack([rel @ geometry.e1, rel @ geometry.e2], -1)
    toward = cam_ab - cell
    toward /= np.maximum(np.linalg.norm(toward, axis=-1, keepdims=True), 1e-9)
    steps = np.arange(0, 15.0, 0.5 * geometry.cell_size)  # metres
    path = cell[:, None] + steps[None, :, None] * toward[:, None]  # (n, S, 2)
    outside = ~geometry.contains(path)
    leave = steps[np.argmax(outside, axis=-1)]  # first step out of the area (0 if never)
    (w_lo, w_hi), (d_lo, d_hi), (h_lo, h_hi) = config.occluder_size
    width, depth, height = (
        rng.uniform(lo, hi, n) for lo, hi in ((w_lo, w_hi), (d_lo, d_hi), (h_lo, h_hi))
    )
    ab = cell + (leave + 0.5 * depth + 0.3)[:, None] * toward
    centre = geometry.to_world(np.concatenate([ab, 0.5 * height[:, None]], -1))
    side = np.stack([-toward[:, 1], toward[:, 0]], -1)
    to_world = lambda v: v[:, :1] * geometry.e1 + v[:, 1:] * geometry.e2  # noqa: E731
    axes = np.stack([to_world(side), to_world(toward), np.broadcast_to(geometry.up, (n, 3))], 1)
    half = 0.5 * np.stack([width, depth, height], -1)
    return Occluders(
        centre.reshape(B, per_scene, 3),
        axes.reshape(B, per_scene, 3, 3),
        half.reshape(B, per_scene, 3),
    )


def mix_parts(
    det: DetectorOutput, group: np.ndarray, config: DetectorConfig, rng: np.random.Generator
) -> DetectorOutput:
    """Bottom-up part mixing: lower limbs taken from the nearest other person of the view.

    Per reported detection and lower limb (`MIX_LIMBS`), with probability ``limb_mix_rate``,
    the limb's keypoints (pixels and scores, missing ones too) become those of the nearest other
    reported person of the same scene in that view, when that person's skeleton centre (mean of
    the reported keypoints) lies within ``mix_distance`` image heights of the person's.
    """
    xy, score = det.xy, det.score  # (F, C, G, K, 2), (F, C, G, K)
    F, C, G = det.reported.shape
    present = score > 0
    centre = (xy * present[..., None]).sum(-2) / np.maximum(present.sum(-1), 1)[..., None]
    dist = np.linalg.norm(centre[:, :, :, None] - centre[:, :, None], axis=-1)  # (F, C, G, G)
    other = (
        det.reported[:, :, None, :] & (group[:, None] == group[None, :]) & ~np.eye(G, dtype=bool)
    )
    dist = np.where(other, dist, np.inf)
    nearest = np.argmin(dist, axis=-1)  # (F, C, G)
    near = det.reported & (
        np.take_along_axis(dist, nearest[..., None], -1)[..., 0]
        < config.mix_distance * det.height_px
    )
    mixed = near[..., None] & (rng.random((F, C, G, len(MIX_LIMBS))) < config.limb_mix_rate)
    f, c, g, limb = np.nonzero(mixed)
    new_xy, new_score = xy.copy(), score.copy()
    if f.size:
        kps = MIX_LIMBS[limb]  # (n, 2)
        src = nearest[f, c, g]
        new_xy[f[:, None], c[:, None], g[:, None], kps] = xy[
            f[:, None], c[:, None], src[:, None], kps
        ]
        new_score[f[:, None], c[:, None], g[:, None], kps] = score[
            f[:, None], c[:, None], src[:, None], kps
        ]
    return dataclasses.replace(det, xy=new_xy, score=new_score, mixed=mixed)


def extra_skeletons(
    det: DetectorOutput, config: DetectorConfig, rng: np.random.Generator
) -> tuple[DetectorOutput, np.ndarray, np.ndarray, np.ndarray]:
    """Duplicate and fragmentary skeletons of reported people (bottom-up grouping failures).

    Returns:
      det with ``duplicated`` and ``fragmented`` set, and the extra rows: xy (F, C, G, 2, K, 2),
      score (F, C, G, 2, K), valid (F, C, G, 2): slot 0 the duplicate, slot 1 the fragment.
    """
    xy, score = det.xy, det.score
    F, C, G, K_ = score.shape
    present = score > 0
    h = det.height_px[..., None, None]
    dup = det.reported & (rng.random((F, C, G)) < config.duplicate_rate)
    dup_xy = xy + config.duplicate_noise * h * rng.standard_normal(xy.shape)
    dup_score = score * rng.uniform(0.5, 0.9, (F, C, G, 1))
    # Fragments: an arm or a leg (the body-part masks of false positives), or a few random
    # keypoints, of the person's reported ones; at least two keypoints.
    frag = det.reported & (rng.random((F, C, G)) < config.fragment_rate)
    limbs = _PARTS[[2, 3, 5, 6]]
    kind = rng.integers(0, len(limbs) + 1, (F, C, G))
    mask = (
        np.where(
            (kind < len(limbs))[..., None],
            limbs[np.minimum(kind, len(limbs) - 1)],
            rng.random((F, C, G, K_)) < 0.25,
        )
        & present
    )
    frag &= mask.sum(-1) >= 2
    frag_xy = xy + config.duplicate_noise * h * rng.standard_normal(xy.shape)
    frag_score = np.where(mask, score * rng.uniform(0.3, 0.7, (F, C, G, 1)), 0.0)
    valid = np.stack([dup, frag], 3)
    ex_score = np.stack([np.where(present, dup_score, 0.0), frag_score], 3)
    ex_score = np.where(valid[..., None], ex_score, 0.0).astype(np.float32)
    ex_xy = np.where((ex_score > 0)[..., None], np.stack([dup_xy, frag_xy], 3), 0.0)
    det = dataclasses.replace(det, duplicated=dup, fragmented=frag)
    return det, ex_xy.astype(np.float32), ex_score, valid


def _occlusion(pc: np.ndarray, radii: np.ndarray, group: np.ndarray, exempt: np.ndarray):
    """Occlusion of every keypoint in every view by body capsules.

    Args:
      pc: (C, F, G, NP, 3) points in the camera frames.
      radii: (G, S) capsule radii.
      group: (G,) scene ids.
      exempt: (K, S) capsules of the own body that cannot occlude a keypoint.
    Returns:
      occluded (C, F, G, K) and occluded_by_others (C, F, G, K), bool.
    """
    C, F, G = pc.shape[:3]
    f32 = np.float32
    z = np.maximum(pc[..., 2], MIN_DEPTH).astype(f32)
    x = (pc[..., 0] / z).astype(f32)  # pinhole image coordinates, (C, F, G, NP)
    y = (pc[..., 1] / z).astype(f32)
    ia = np.array([a for a, _, _ in bm.CAPSULES])
    ib = np.array([b for _, b, _ in bm.CAPSULES])
    r = radii.astype(f32)  # (G, S)

    # Own body: only the (keypoint, capsule) pairs that can occlude, (C, F, G, pairs).
    kk, ss = np.nonzero(~exempt)
    hit = _covers(
        x[..., kk],
        y[..., kk],
        z[..., kk],
        x[..., ia[ss]],
        y[..., ia[ss]],
        z[..., ia[ss]],
        x[..., ib[ss]],
        y[..., ib[ss]],
        z[..., ib[ss]],
        r[:, ss],
    )
    # Any hit of each keypoint over its capsules (pairs are sorted by keypoint, none is empty).
    bounds = np.searchsorted(kk, np.arange(K))
    occluded = np.add.reduceat(hit.astype(np.int8), bounds, axis=-1) > 0

    # Faces turned away from the camera are hidden by the head (the camera sits at the origin).
    face = list(bm.FACE_KEYPOINTS)
    normal = pc[..., face, :] - pc[..., bm.HEAD : bm.HEAD + 1, :]
    view = -pc[..., face, :]
    cos = np.einsum("...i,...i->...", normal, view) / np.maximum(
        np.linalg.norm(normal, axis=-1) * np.linalg.norm(view, axis=-1), 1e-9
    )
    occluded[..., face] |= cos < _FACE_COS

    # Other people: only pairs whose image boxes overlap and whose occluder is nearer.
    by_others = np.zeros_like(occluded)
    same = (group[:, None] == group[None, :]) & ~np.eye(G, dtype=bool)
    if same.any():
        zc = z[..., : bm.NUM_POINTS]
        rad = r[None, None] / np.minimum(zc[..., ia], zc[..., ib])  # (C, F, G, S)
        xs = np.concatenate([x[..., ia], x[..., ib]], -1)
        ys = np.concatenate([y[..., ia], y[..., ib]], -1)
        rr = np.concatenate([rad, rad], -1)
        x_lo, x_hi = (xs - rr).min(-1), (xs + rr).max(-1)  # (C, F, G)
        y_lo, y_hi = (ys - rr).min(-1), (ys + rr).max(-1)
        near = np.minimum(zc[..., ia], zc[..., ib]).min(-1)
        far = z[..., :K].max(-1)
        overlap = (
            (x_lo[..., None, :] < x_hi[..., :, None])
            & (x_hi[..., None, :] > x_lo[..., :, None])
            & (y_lo[..., None, :] < y_hi[..., :, None])
            & (y_hi[..., None, :] > y_lo[..., :, None])
            & (near[..., None, :] < far[..., :, None])
            & same
        )  # (C, F, G[target], G[occluder])
        c, f, g, o = np.nonzero(overlap)
        if c.size:
            q = lambda a: a[c, f, g][:, :K, None]  # noqa: E731  (n, K, 1)
            s_ = lambda a, idx: a[c, f, o][:, None, idx]  # noqa: E731  (n, 1, S)
            hit = _covers(
                q(x),
                q(y),
                q(z),
                s_(x, ia),
                s_(y, ia),
                s_(z, ia),
                s_(x, ib),
                s_(y, ib),
                s_(z, ib),
                r[o][:, None, :],
            ).any(-1)
            counts = np.zeros((C * F * G, K), np.int32)
            np.add.at(counts, np.ravel_multi_index((c, f, g), (C, F, G)), hit)
            by_others = counts.reshape(C, F, G, K) > 0
            occluded |= by_others
    return occluded, by_others


def _covers(qx, qy, qz, ax, ay, az, bx, by, bz, r):
    """Whether a capsule (a-b, radius r) covers image point q and lies in front of it.

    Points in pinhole image coordinates (x, y) with depths z (metres). Broadcasts.
    """
    dx, dy = bx - ax, by - ay
    wx, wy = qx - ax, qy - ay
    dd = dx * dx + dy * dy
    t = np.clip((wx * dx + wy * dy) / np.maximum(dd, 1e-12), 0.0, 1.0)
    ex, ey = wx - t * dx, wy - t * dy
    zc = az + t * (bz - az)
    # Covered: within the radius seen at that depth; in front: the capsule's back surface is
    # nearer than the keypoint. Written without divisions: dist^2 zc^2 < r^2.
    return ((ex * ex + ey * ey) * (zc * zc) < r * r) & (zc + r < qz)


def false_positives(
    cams: CameraModel,
    local_poses: np.ndarray,
    reported: np.ndarray,
    det_xy: np.ndarray,
    height_px: np.ndarray,
    config: DetectorConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """False-positive skeletons for every view of every frame of B scenes.

    Args:
      cams: the cameras.
      local_poses: (N, K, 3) body-frame poses (forward, left, up; metres, pelvis at 0) to shape
        false positives from.
      reported: (F, C, B, Gp) bool, real detections (to place "leftover limb" false positives).
      det_xy: (F, C, B, Gp, K, 2) reported pixels of the real detections.
      height_px: (F, C, B, Gp) image heights of the people.
    Returns:
      xy (F, C, B, M, K, 2), score (F, C, B, M, K) and valid (F, C, B, M), M the most false
      positives of any view (0 when the rate is 0).
    """
    F, C, B, Gp = reported.shape
    rate = config.false_positive_rate
    n = rng.poisson(rate, (F, C, B)) if rate > 0 else np.zeros((F, C, B), np.int64)
    M = int(n.max()) if n.size else 0
    out_xy = np.zeros((F, C, B, M, K, 2), np.float32)
    out_score = np.zeros((F, C, B, M, K), np.float32)
    valid = np.arange(M) < n[..., None]
    if M == 0:
        return out_xy, out_score, valid
    # Only the false positives that exist are computed: N of them, flat.
    fi, ci, bi, mi = np.nonzero(valid)
    N = fi.size
    # Shape: a random pose seen from a random side, orthographic, upright.
    src = local_poses[rng.integers(0, len(local_poses), N)]  # (N, K, 3)
    yaw = rng.uniform(-np.pi, np.pi, N)[:, None]
    lateral = np.cos(yaw) * src[..., 1] - np.sin(yaw) * src[..., 0]
    shape2d = np.stack([lateral, -src[..., 2]], -1)  # (N, K, 2) metres, image y down
    span = shape2d[..., 1].max(-1) - shape2d[..., 1].min(-1)
    wh = cams.size[ci]  # (N, 2)
    size = rng.uniform(0.12, 0.5, N) * wh[:, 1]  # pixels for a whole body
    centre = rng.random((N, 2)) * wh
    # "Leftover limbs": next to a real detection of the view, at a similar scale.
    rep = reported[fi, ci, bi]  # (N, Gp)
    use = rep.any(-1) & (rng.random(N) < config.false_positive_near_fraction)
    if Gp and use.any():
        pick = np.argmax(np.where(rep, rng.random((N, Gp)), -1.0), axis=-1)
        ref_pts = det_xy[fi, ci, bi, pick]  # (N, K, 2)
        ref_h = height_px[fi, ci, bi, pick]
        nz = np.abs(ref_pts).sum(-1) > 0
        ref_c = (ref_pts * nz[..., None]).sum(-2) / np.maximum(nz.sum(-1, keepdims=True), 1)
        side = np.where(rng.random(N) < 0.5, -1.0, 1.0)
        offset = np.stack([side * rng.uniform(0.5, 1.1, N), rng.uniform(-0.3, 0.3, N)], -1)
        centre = np.where(use[:, None], ref_c + offset * ref_h[:, None], centre)
        size = np.where(use, ref_h * rng.uniform(0.5, 1.0, N), size)
    xy = shape2d * (size / np.maximum(span, 1e-6))[:, None, None]
    part = rng.integers(0, len(_PARTS) + 1, N)
    mask = np.where(
        (part < len(_PARTS))[:, None],
        _PARTS[np.minimum(part, len(_PARTS) - 1)],
        rng.random((N, K)) < 0.4,
    )
    mask[mask.sum(-1) < 2] = _PARTS[4]
    # Centre the shown keypoints' box on the chosen spot, kept inside the image.
    lo = np.where(mask[..., None], xy, np.inf).min(-2)
    hi = np.where(mask[..., None], xy, -np.inf).max(-2)
    c = np.clip(centre, (hi - lo) / 2 + 1, wh - (hi - lo) / 2 - 1)
    xy = xy - ((lo + hi) / 2)[:, None] + c[:, None]
    xy = xy + (0.01 * size)[:, None, None] * rng.standard_normal(xy.shape)
    inside = (xy >= 0).all(-1) & (xy < wh[:, None]).all(-1)
    mask &= inside
    out_xy[fi, ci, bi, mi] = np.where(mask[..., None], xy, 0.0)
    out_score[fi, ci, bi, mi] = np.where(mask, rng.uniform(0.05, 0.45, (N, K)), 0.0)
    valid[fi, ci, bi, mi] = mask.sum(-1) >= 1
    return out_xy, out_score, valid


def _fields(obj) -> tuple:
    """The fields of a dataclass, shallow (dataclasses.astuple deep-copies arrays)."""
    return tuple(getattr(obj, f.name) for f in dataclasses.fields(obj))
