"""A synthetic detector that looks like the user's: `synthetic.DetectorConfig` fitted without labels.

From a user's own recording (detections and calibration, no 3D labels), each camera's keypoints
are compared with the consensus of the other cameras: the geometric default
(`inference.run_pipeline(method="robust")`) groups the skeletons into people, and each person's
keypoints are triangulated robustly (`triangulate.triangulate_skeletons_robust`) once without
each camera in turn and reprojected into it. A keypoint's residual to that leave-one-out
consensus is the detector's error plus the consensus's own (smaller) error; systematic offsets
that every view shares (a hip marked high) stay in the consensus and are not counted.

What the residuals say, in `DetectorConfig`'s terms (`DetectorFit.fields` names each one, its
value, the default, how many samples support it and how it was measured):

* ``noise_relative``: the per-axis pixel noise as a fraction of the person's image height, a
  robust standard deviation (1.4826 x the median absolute residual, outliers without weight)
  after the noise floor (``noise_floor_px``, kept) and the consensus's own error are taken out;
  ``keypoint_noise_scale``: the same per keypoint, relative to it.
* ``swap_rate``: detections whose arms or legs fit the consensus much better exchanged left for
  right, among those whose left and right limb lie apart enough in the image to tell.
* ``keypoint_drop_rate``: limb keypoints of a detected person that the consensus puts inside
  the image, in front of their own mirror keypoint, of the rest of their body and of everyone
  else, that the view lacks; ``miss_rate``: people whose consensus shows `MIN_KEYPOINTS_IN_VIEW` keypoints inside a
  camera's image with no skeleton there (nor an ungrouped one on them).
* ``false_positive_rate``: partial skeletons per camera and frame grouped into no person and
  lying on no person's reprojection (a skeleton the grouping missed is not one, nor a whole body
  alone: a person one camera sees).
* ``limb_mix_rate``: lower limbs (elbow and wrist, knee and ankle) far from their own person's
  consensus and on another nearby person's, among limbs with another detected person within
  ``mix_distance`` image heights.
* ``border_margin``: the distance to the image border (fraction of the image height) within which
  keypoints the consensus puts inside the image are mostly missing.
* ``score_beta`` and ``score_max``: a Beta distribution fitted by moments to the reported scores,
  and their 99.9th percentile.

Not fitted (the default is kept, and `DetectorFit` says so): ``occluded_drop_rate`` (without a body
model an occluded keypoint cannot be told from a visible one; the miss rate of keypoints that may
be occluded is given as a note), ``noise_tail_dof`` (swaps and mixed limbs the fit misses widen
the residuals' tails as much as a Student-t's; their shape is given as a note), the offsets and
the noise floor.

Person image height: ``fy x PERSON_HEIGHT_M / depth`` of the person's consensus centre, as the
simulator computes it from the pelvis depth and the person's height.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping

import numpy as np
from scipy.stats import t as student_t

from mvpose_jax.cameras import Rig, project_points_per_camera
from mvpose_jax.errors import InputError
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import group_people
from mvpose_jax.skeletons import Detections, Layout, get_layout
from mvpose_jax.synthetic import DetectorConfig
from mvpose_jax.triangulate import leave_one_view_out, triangulate_skeletons_robust

# The simulator's mean standing height (its people: 1.50-1.95 m), for the person's image height.
PERSON_HEIGHT_M = 1.72
# A keypoint's reprojection error of a triangulation from m views, in a view not used, is about
# the detector's noise times sqrt(1 + CONSENSUS_VARIANCE / m) (measured on simulated panoptic5
# and arplab6 recordings of known noise).
CONSENSUS_VARIANCE = 2.0
# Residuals beyond this many robust standard deviations are outliers (swaps, mixes, grouping).
OUTLIER_SIGMAS = 5.0
# A left/right pair can be told apart when its consensus keypoints lie this far apart (fraction of
# the person's image height); the swapped assignment must halve the error.
MIN_SIDE_SEPARATION = 0.08
SWAP_ERROR_RATIO = 0.5
# The simulator exchanges an arm pair, a leg pair or the whole body (0.4, 0.4, 0.2;
# `synthetic.detector`): a swapped detection has a given part exchanged with probability 0.6.
SWAP_PART_SHARE = 0.6
# Keypoints counted for misses lie at least this far inside the image (fraction of its height);
# a mirror keypoint this much nearer the camera (metres) may hide its partner.
MISS_BORDER = 0.03
SELF_OCCLUSION_M = 0.1
OWN_BODY_RADIUS = 0.07
# A person is in view of a camera with this many consensus keypoints inside its image.
MIN_KEYPOINTS_IN_VIEW = 6
# An ungrouped skeleton lies on a person when its median keypoint distance to the person's
# reprojection is under this fraction of the person's image height.
ON_PERSON = 0.15
# A limb is mixed when its error to its own consensus exceeds this fraction of the image height
# and another person's consensus fits it with under half that error.
MIX_MIN_ERROR = 0.1
# Border bins: the margin is where the detection rate of inside keypoints falls below half the
# interior's (keypoints 0.1-0.3 image heights from the border).
BORDER_BINS = np.linspace(0.0, 0.1, 21)
# Fewer samples than these leave a field at its default.
MIN_SAMPLES = 50
MIN_KEYPOINT_SAMPLES = 30

# A skeleton alone with this many keypoints over the head or shoulders and the hips or legs is
# a person one camera sees, not a false skeleton.
WHOLE_BODY_KEYPOINTS = 10
_UPPER = ("nose", "neck", "l_eye", "r_eye", "l_ear", "r_ear", "l_shoulder", "r_shoulder")
_LOWER = ("l_hip", "r_hip", "l_knee", "r_knee", "l_ankle", "r_ankle")
_ARMS = ("shoulder", "elbow", "wrist")
_LEGS = ("hip", "knee", "ankle")
_LOWER_LIMBS = (("elbow", "wrist"), ("knee", "ankle"))


# Frames `fit_detector` looks at by default, evenly spaced over the recording.
FIT_FRAMES = 600


@dataclasses.dataclass(frozen=True)
class FittedField:
    """One `DetectorConfig` field as fitted.

    Attributes:
      name: the field.
      value: the fitted value (the default where not fitted).
      default: `DetectorConfig`'s default.
      samples: how many samples support it (0: not fitted).
      fitted: whether ``value`` comes from the data.
      note: how it was measured, or why not.
    """

    name: str
    value: object
    default: object
    samples: int
    fitted: bool
    note: str


@dataclasses.dataclass(frozen=True)
class DetectorFit:
    """A detector fitted to a recording (module docstring).

    Attributes:
      config: the `DetectorConfig` with the fitted fields (the others at their defaults).
      fields: each fitted or kept field.
      num_frames: frames looked at; num_people: person-frames the geometric default found.
    """

    config: DetectorConfig
    fields: tuple[FittedField, ...]
    num_frames: int
    num_people: int

    def field(self, name: str) -> FittedField:
        """The entry of field ``name``."""
        return next(f for f in self.fields if f.name == name)

    def describe(self) -> list[str]:
        """One line per field: value, default, samples and how."""
        lines = [f"detector fitted on {self.num_people} person-frames of {self.num_frames} frames:"]
        for f in self.fields:
            state = f"{f.samples} samples" if f.fitted else "not fitted, default kept"
            lines.append(
                f"  {f.name} = {_show(f.value)} (default {_show(f.default)}; {state}; {f.note})"
            )
        return lines

    def to_dict(self) -> dict:
        """A JSON-ready record."""
        return {
            "num_frames": self.num_frames,
            "num_people": self.num_people,
            "fields": {
                f.name: {
                    "value": _plain(f.value),
                    "default": _plain(f.default),
                    "samples": f.samples,
                    "fitted": f.fitted,
                    "note": f.note,
                }
                for f in self.fields
            },
        }


def fit_detector(
    rig: Rig,
    detections: Detections,
    *,
    layout: str | Layout = "coco18",
    max_frames: int = FIT_FRAMES,
    person_height_m: float = PERSON_HEIGHT_M,
) -> DetectorFit:
    """The `DetectorConfig` that behaves like the detector of ``detections`` (module docstring).

    Args:
      rig: the C cameras of the detections, in their order.
      detections: xy (F, C, P, K, 2) pixels, score (F, C, P, K), count (F, C).
      layout: the detections' keypoint layout (fields per keypoint are mapped to the simulator's
        coco18 by name).
      max_frames: at most this many frames, evenly spaced, are used.
      person_height_m: the people's standing height assumed for their image height.
    Returns:
      A `DetectorFit`.
    Raises:
      InputError for fewer than three cameras or no people seen by three or more of them.
    """
    lay = get_layout(layout)
    if rig.num_cameras < 3:
        raise InputError(
            f"needs 3+ cameras to compare each view with the others, not {rig.num_cameras}",
            field="cameras",
        )
    F = int(np.shape(detections.count)[0])
    frames = np.unique(np.linspace(0, max(F - 1, 0), min(F, max_frames)).round().astype(int))
    det = Detections(*(np.asarray(a)[frames] for a in detections))
    res = run_pipeline(rig, det, method="robust", layout=lay.name)
    valid = np.asarray(res.poses.valid)  # (F, G)
    members = np.asarray(res.members)  # (F, G, C)
    identity = np.asarray(res.identity)  # (F, C, P)
    P = identity.shape[-1]
    ungrouped = (identity < 0) & (np.arange(P) < np.asarray(det.count)[..., None])  # (F, C, P)
    xy, score = np.asarray(det.xy), np.asarray(det.score)
    # Swapped, mixed or noisy views are often left out of their person's group: an ungrouped
    # skeleton lying on a person the camera has none of is taken as that person's.
    v = _Views.build(rig, *group_people(xy, score, members), members, valid, person_height_m)
    flip = np.asarray(lay.flip)
    members, attached = _attach(v, members, xy, score, ungrouped, flip)
    ungrouped &= ~attached
    v = _Views.build(rig, *group_people(xy, score, members), members, valid, person_height_m)
    if not (v.has.sum(0) >= 3).any():
        raise InputError(
            "no person is seen by three or more cameras: nothing to compare each view with",
            field="detections",
        )
    on_person, explained = _ungrouped_on_people(v, xy, score, ungrouped, flip)
    g_score = group_people(xy, score, members)[1]

    defaults = DetectorConfig()
    fitted: dict[str, FittedField] = {}
    fitted["swap_rate"], swapped = _swaps(v, lay)
    fitted["limb_mix_rate"], mixed = _limb_mixes(v, lay, defaults.mix_distance)
    noise, kp_scale, tail = _noise(v, lay, defaults, swapped | mixed)
    fitted["noise_relative"] = noise
    fitted["keypoint_noise_scale"] = kp_scale
    fitted["noise_tail_dof"] = tail
    drop, occluded_note = _keypoint_drops(v, lay)
    fitted["keypoint_drop_rate"] = drop
    fitted["occluded_drop_rate"] = _kept("occluded_drop_rate", occluded_note)
    fitted["miss_rate"] = _misses(v, on_person)
    alone = ungrouped & ~explained
    one_view = alone & _whole_body(score, lay)
    fp = int((alone & ~one_view).sum())
    views = int(np.prod(ungrouped.shape[:2]))
    fitted["false_positive_rate"] = FittedField(
        "false_positive_rate",
        round(fp / max(views, 1), 4),
        defaults.false_positive_rate,
        views,
        True,
        f"{fp} partial skeletons in no person and on no person's reprojection, per camera and "
        f"frame ({int(one_view.sum())} whole bodies alone, people one camera sees, and "
        f"{int((ungrouped & explained).sum())} ungrouped skeletons on a person not counted)",
    )
    fitted["border_margin"] = _border(v)
    beta, smax = _scores(g_score[valid])
    fitted["score_beta"] = beta
    fitted["score_max"] = smax
    for name, field in fitted.items():
        if field.default != getattr(defaults, name):
            fitted[name] = dataclasses.replace(field, default=getattr(defaults, name))
    config = dataclasses.replace(defaults, **{n: f.value for n, f in fitted.items() if f.fitted})
    return DetectorFit(config, tuple(fitted.values()), len(frames), int(valid.sum()))


@dataclasses.dataclass(frozen=True)
class _Views:
    """Every person-frame's views, cameras first: (C, F, G, K, ...) arrays.

    det: detected pixels (C, F, G, K, 2); seen: the keypoint is reported (C, F, G, K);
    has: the camera holds a skeleton of the person (C, F, G); loo: the other views' consensus
    reprojected (C, F, G, K, 2), loo_ok where it exists and lies in front (C, F, G, K), loo_views:
    views it used; full: the all-view consensus reprojected, full_ok; depth (C, F, G, K) metres
    of the full consensus keypoints; centre_depth (C, F, G); h: the person's image height
    (C, F, G) pixels; size: (C, 2) image width and height; valid: (F, G) the person exists.
    """

    det: np.ndarray
    seen: np.ndarray
    has: np.ndarray
    loo: np.ndarray
    loo_ok: np.ndarray
    loo_views: np.ndarray
    full: np.ndarray
    full_ok: np.ndarray
    depth: np.ndarray
    centre_depth: np.ndarray
    h: np.ndarray
    size: np.ndarray
    valid: np.ndarray
    floor_px: np.ndarray  # (C,) the simulator's noise floor in each camera, pixels

    @staticmethod
    def build(rig, g_xy, g_score, members, valid, person_height_m) -> _Views:
        C = rig.num_cameras
        px = np.moveaxis(np.asarray(g_xy, np.float64), 2, 0)  # (C, F, G, K, 2)
        w = np.moveaxis(np.asarray(g_score, np.float64), 2, 0)  # (C, F, G, K)
        has = np.moveaxis(members, 2, 0) >= 0
        has &= valid[None]
        w = np.where(has[..., None], w, 0.0)
        xyz, ok, _ = (np.array(a) for a in triangulate_skeletons_robust(rig, px, w))
        ok &= valid[..., None]
        loo_xyz, loo_ok, loo_views = (np.array(a) for a in leave_one_view_out(rig, px, w))
        loo_xyz = loo_xyz.astype(np.float64)
        loo_ok = loo_ok & (loo_views >= 2) & valid[None, ..., None]
        R, t = np.asarray(rig.R, np.float64), np.asarray(rig.t, np.float64)
        cam_full = np.einsum("cij,fgkj->cfgki", R, xyz) + t[:, None, None, None]
        cam_loo = np.einsum("cij,cfgkj->cfgki", R, loo_xyz) + t[:, None, None, None]
        full = np.asarray(project_points_per_camera(rig, np.broadcast_to(xyz, (C, *xyz.shape))))
        loo = np.asarray(project_points_per_camera(rig, loo_xyz))
        depth = cam_full[..., 2]
        n = ok.sum(-1)  # (F, G)
        centre = (xyz * ok[..., None]).sum(-2) / np.maximum(n, 1)[..., None]  # (F, G, 3)
        centre_depth = (np.einsum("cij,fgj->cfgi", R, centre) + t[:, None, None])[..., 2]
        fy = np.asarray(rig.K, np.float64)[:, 1, 1][:, None, None]
        h = np.where(centre_depth > 0.1, fy * person_height_m / np.maximum(centre_depth, 0.1), 0.0)
        size = np.asarray(rig.size, np.float64)
        floor = (
            DetectorConfig().noise_floor_px
            * np.hypot(size[:, 0], size[:, 1])
            / np.hypot(1920, 1080)
        )
        usable = (n >= 4)[None] & (h > 0)
        return _Views(
            det=px,
            seen=w > 0,
            has=has & usable,
            loo=loo,
            loo_ok=loo_ok & (cam_loo[..., 2] > 0.1) & usable[..., None],
            loo_views=loo_views,
            full=full,
            full_ok=ok[None] & (depth > 0.1) & usable[..., None],
            depth=depth,
            centre_depth=centre_depth,
            h=h,
            size=size,
            valid=valid & (n >= 4),
            floor_px=floor,
        )

    def inside(self, points: np.ndarray, margin: float) -> np.ndarray:
        """Whether pixels (C, ..., 2) lie ``margin`` image heights inside each camera's image."""
        shape = (len(self.size),) + (1,) * (points.ndim - 2)
        w, h = self.size[:, 0].reshape(shape), self.size[:, 1].reshape(shape)
        m = margin * h
        x, y = points[..., 0], points[..., 1]
        return (x >= m) & (x < w - m) & (y >= m) & (y < h - m)


def _noise(
    v: _Views, lay: Layout, defaults: DetectorConfig, wrong: np.ndarray
) -> tuple[FittedField, FittedField, FittedField]:
    """noise_relative, keypoint_noise_scale and noise_tail_dof's note from the leave-one-out residuals
    (``wrong``: (C, F, G, K) keypoints of swapped or mixed parts, left out)."""
    # Occluded keypoints are noisier (the simulator's occluded_noise_factor): keypoints that
    # may be hidden are left out.
    use = v.seen & v.has[..., None] & v.loo_ok & _unhidden(v, lay) & ~wrong  # (C, F, G, K)
    r = np.abs(v.det - v.loo)[use]  # (M, 2)
    h = np.broadcast_to(v.h[..., None], use.shape)[use]
    floor = np.broadcast_to(v.floor_px[:, None, None, None], use.shape)[use]
    inflate = np.sqrt(1.0 + CONSENSUS_VARIANCE / np.maximum(v.loo_views[use], 1))
    kp = np.broadcast_to(np.arange(use.shape[-1]), use.shape)[use]
    if len(r) < MIN_SAMPLES:
        return (
            _kept("noise_relative", "too few keypoints seen by a camera and 2+ others"),
            _kept("keypoint_noise_scale", "too few samples"),
            _kept("noise_tail_dof", "too few samples"),
        )

    def z(a: float) -> np.ndarray:
        return r / ((a * h + floor) * inflate)[:, None]

    lo, hi = 0.0, 0.5  # median |z| = 0.6745 (a normal's) by bisection on the relative noise
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.median(z(mid)) > 0.6745 else (lo, mid)
    a = 0.5 * (lo + hi)
    zs = z(a)
    inlier = (zs < OUTLIER_SIGMAS).all(-1)
    tail = _tail(zs)
    noise = FittedField(
        "noise_relative",
        round(float(a), 5),
        defaults.noise_relative,
        len(r),
        True,
        "robust std per axis of the residuals to the other views' consensus, the noise floor "
        f"and the consensus's own error taken out; {100 * (1 - inlier.mean()):.1f}% of keypoints "
        f"beyond {OUTLIER_SIGMAS:g} std",
    )
    coco = get_layout("coco18")
    scale = np.ones(coco.num_keypoints)
    counts = np.bincount(kp, minlength=lay.num_keypoints)
    measured = 0
    for k, name in enumerate(lay.keypoints):  # a few dozen keypoints
        if name not in coco.keypoints or counts[k] < MIN_KEYPOINT_SAMPLES:
            continue
        scale[coco.index(name)] = np.median(zs[kp == k]) / 0.6745
        measured += 1
    samples = int(sum(counts[k] for k, n in enumerate(lay.keypoints) if n in coco.keypoints))
    if not measured:
        return noise, _kept("keypoint_noise_scale", "no coco18 keypoint with enough samples"), tail
    return (
        noise,
        FittedField(
            "keypoint_noise_scale",
            tuple(round(float(s), 3) for s in scale),
            defaults.keypoint_noise_scale,
            samples,
            True,
            f"per coco18 keypoint, robust std / the overall ({measured} of "
            f"{coco.num_keypoints} keypoints measured, 1 for the rest)",
        ),
        tail,
    )


def _tail(z: np.ndarray) -> FittedField:
    """noise_tail_dof, not fitted: the shape of the normalised residuals |z| (M, 2) as a note,
    their 90th percentile over their median (a normal's 2.44) and the Student-t it matches.
    Swaps and mixed limbs the fit does not single out widen the tails as much as a Student-t of
    3 degrees does (a simulated normal detector with the rates of `tests/test_detector_fit.py`
    matches 2.5 degrees, one of 3 degrees without them 3.5), so the tails are not fitted."""
    ratio = float(np.quantile(z, 0.9) / np.median(z))
    dofs = np.arange(2.0, 30.5, 0.5)
    ratios = student_t.ppf(0.95, dofs) / student_t.ppf(0.75, dofs)
    match = f"a Student-t of {dofs[np.argmin(np.abs(ratios - ratio))]:g} degrees"
    return _kept(
        "noise_tail_dof",
        f"90th percentile / median of |residual| {ratio:.2f} (a normal's 2.44; {match}): swaps "
        "and mixed limbs the fit misses widen the tails as much as a Student-t's",
    )


def _pairs(lay: Layout, parts: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray] | None:
    left = [f"l_{p}" for p in parts]
    right = [f"r_{p}" for p in parts]
    if not all(k in lay.keypoints for k in left + right):
        return None
    return np.array([lay.index(k) for k in left]), np.array([lay.index(k) for k in right])


def _swaps(v: _Views, lay: Layout) -> tuple[FittedField, np.ndarray]:
    """swap_rate: arms and legs that fit the consensus better exchanged left for right; and
    their keypoints (C, F, G, K)."""
    rates, told, swapped = [], 0, 0
    wrong = np.zeros(v.seen.shape, bool)
    for parts in (_ARMS, _LEGS):
        pair = _pairs(lay, parts)
        if pair is None:
            continue
        L, R = pair
        ok = v.seen[..., L] & v.seen[..., R] & v.loo_ok[..., L] & v.loo_ok[..., R]  # (C,F,G,3)
        dL, dR, qL, qR = v.det[..., L, :], v.det[..., R, :], v.loo[..., L, :], v.loo[..., R, :]
        dist = lambda a, b: np.linalg.norm(a - b, axis=-1)  # noqa: E731
        n = ok.sum(-1)
        mean = lambda e: (e * ok).sum(-1) / np.maximum(n, 1)  # noqa: E731
        direct = mean(dist(dL, qL) + dist(dR, qR))
        exchanged = mean(dist(dL, qR) + dist(dR, qL))
        separation = mean(dist(qL, qR))
        can = v.has & (n >= 2) & (separation > MIN_SIDE_SEPARATION * v.h)
        is_swapped = can & (exchanged < SWAP_ERROR_RATIO * direct)
        wrong[..., L] |= is_swapped[..., None]
        wrong[..., R] |= is_swapped[..., None]
        if can.sum() >= MIN_SAMPLES:
            rates.append(is_swapped.sum() / can.sum())
        told += int(can.sum())
        swapped += int(is_swapped.sum())
    if not rates:
        return _kept("swap_rate", "too few arms and legs with both sides seen apart"), wrong
    field = FittedField(
        "swap_rate",
        round(float(np.mean(rates) / SWAP_PART_SHARE), 4),
        None,
        told,
        True,
        f"{swapped} of {told} arm and leg pairs fit better exchanged; the simulator exchanges "
        f"a given pair in {SWAP_PART_SHARE:g} of its swaps",
    )
    return field, wrong


def _in_front_of_others(v: _Views, points: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Whether no other person's consensus box (its reprojected keypoints, grown by 5% of its
    image height) covers each point (C, F, G, K, 2) while nearer the camera."""
    big = 1e9
    lo = np.where(v.full_ok[..., None], v.full, big).min(-2)  # (C, F, G, 2)
    hi = np.where(v.full_ok[..., None], v.full, -big).max(-2)
    pad = 0.05 * v.h[..., None]
    lo, hi = lo - pad, hi + pad
    p = points[:, :, :, None]  # (C, F, G, 1, K, 2) against the others (C, F, 1, G', 1, 2)
    inside = ((p >= lo[:, :, None, :, None]) & (p <= hi[:, :, None, :, None])).all(-1)
    nearer = v.centre_depth[:, :, None, :, None] < depth[:, :, :, None]  # (C, F, G, G', K)
    # The other person need not be detected in the view: being hidden is why one is missed.
    other = v.valid[:, :, None] & ~np.eye(v.valid.shape[1], dtype=bool)  # (F, G, G')
    covered = inside & nearer & other[None, ..., None]
    return ~covered.any(3)


def _unhidden(v: _Views, lay: Layout) -> np.ndarray:
    """(C, F, G, K) keypoints no one may hide: not `SELF_OCCLUSION_M` behind their mirror
    keypoint, covered by no nearer part of their own body, and by no nearer person."""
    flip = np.asarray(lay.flip)
    self_hidden = v.depth[..., flip] < v.depth - SELF_OCCLUSION_M
    return ~self_hidden & ~_behind_own_body(v, lay) & _in_front_of_others(v, v.loo, v.depth)


def _behind_own_body(v: _Views, lay: Layout) -> np.ndarray:
    """(C, F, G, K) keypoints within `OWN_BODY_RADIUS` image heights of a part of their own body
    (another keypoint, a bone's midpoint, the torso's centre) `SELF_OCCLUSION_M` nearer the
    camera: the body's volume around its skeleton, coarsely."""
    K = lay.num_keypoints
    bones = np.array([b for b in lay.bones], int).reshape(-1, 2)
    torso = [
        lay.index(k) for k in ("l_shoulder", "r_shoulder", "l_hip", "r_hip") if k in lay.keypoints
    ]
    # Sample points as weights over keypoints (S, K): keypoints, bone midpoints, torso centre.
    w = [np.eye(K)]
    if len(bones):
        mid = np.zeros((len(bones), K))
        mid[np.arange(len(bones)), bones[:, 0]] += 0.5
        mid[np.arange(len(bones)), bones[:, 1]] += 0.5
        w.append(mid)
    if len(torso) == 4:
        centre = np.zeros((1, K))
        centre[0, torso] = 0.25
        w.append(centre)
    weights = np.concatenate(w)  # (S, K)
    # A sample exists where all its keypoints do; it cannot hide a keypoint it is made of.
    parts = weights > 0
    exists = (v.full_ok[..., None, :] | ~parts).all(-1)  # (C, F, G, S)
    pts = np.einsum("sk,cfgkd->cfgsd", weights, v.full)
    depth = np.einsum("sk,cfgk->cfgs", weights, v.depth)
    hidden = np.zeros(v.depth.shape, bool)
    for c in range(len(hidden)):  # one camera at a time: (F, G, K, S) pairs, not C times that
        near = np.linalg.norm(v.full[c, ..., :, None, :] - pts[c, ..., None, :, :], axis=-1)
        near = near < OWN_BODY_RADIUS * v.h[c, ..., None, None]
        front = depth[c, ..., None, :] < v.depth[c, ..., :, None] - SELF_OCCLUSION_M
        hidden[c] = (near & front & exists[c, ..., None, :] & ~parts.T).any(-1)
    return hidden


def _keypoint_drops(v: _Views, lay: Layout) -> tuple[FittedField, str]:
    """keypoint_drop_rate from keypoints no one may hide; the note on the others' misses."""
    limbs = [
        k for k, n in enumerate(lay.keypoints) if n[2:] in _ARMS + _LEGS and n[:2] in ("l_", "r_")
    ]
    if not limbs:
        return _kept("keypoint_drop_rate", "the layout has no limb keypoints"), "not measured"
    use = v.has[..., None] & v.loo_ok & v.full_ok & v.inside(v.loo, MISS_BORDER)
    clear = use & _unhidden(v, lay)
    clear[..., np.setdiff1d(np.arange(lay.num_keypoints), limbs)] = False
    rest = use & ~clear
    missing = ~v.seen
    n, m = int(clear.sum()), int((clear & missing).sum())
    note = (
        f"keypoints that may be hidden (behind their mirror keypoint, their own body or another "
        f"person, and the face) miss in {(rest & missing).sum() / max(rest.sum(), 1):.3f} of {int(rest.sum())}; "
        "an occluded keypoint cannot be told from a visible one without a body model"
    )
    if n < MIN_SAMPLES:
        return _kept("keypoint_drop_rate", "too few unoccluded limb keypoints"), note
    field = FittedField(
        "keypoint_drop_rate",
        round(m / n, 4),
        None,
        n,
        True,
        f"{m} of {n} limb keypoints the consensus puts inside the image, in front of their "
        "mirror keypoint, their own body and everyone else, missing",
    )
    return field, note


def _misses(v: _Views, on_person: np.ndarray) -> FittedField:
    """miss_rate: people in view of a camera with no skeleton there, nor an ungrouped one."""
    in_view = (v.full_ok & v.inside(v.full, 0.0)).sum(-1) >= MIN_KEYPOINTS_IN_VIEW  # (C, F, G)
    in_view &= v.valid[None]
    missed = in_view & ~v.has & ~on_person
    n = int(in_view.sum())
    if n < MIN_SAMPLES:
        return _kept("miss_rate", "too few people in view")
    return FittedField(
        "miss_rate",
        round(int(missed.sum()) / n, 4),
        None,
        n,
        True,
        f"{int(missed.sum())} of {n} person-views with {MIN_KEYPOINTS_IN_VIEW}+ consensus "
        "keypoints inside the image have no skeleton there",
    )


def _whole_body(score: np.ndarray, lay: Layout) -> np.ndarray:
    """(F, C, P) skeletons with `WHOLE_BODY_KEYPOINTS`+ keypoints, the head or shoulders and the
    hips or legs among them: a person (one camera alone may see), not a detector's false
    skeleton, which shows a part of a body (the simulator's: an upper body, legs, a limb, or
    scattered keypoints)."""
    seen = score > 0
    upper = [k for k, n in enumerate(lay.keypoints) if n in _UPPER]
    lower = [k for k, n in enumerate(lay.keypoints) if n in _LOWER]
    return (
        (seen.sum(-1) >= WHOLE_BODY_KEYPOINTS) & seen[..., upper].any(-1) & seen[..., lower].any(-1)
    )


def _ungrouped_on_people(
    v: _Views, xy: np.ndarray, score: np.ndarray, ungrouped: np.ndarray, flip: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(C, F, G): a person has an ungrouped skeleton on its reprojection; (F, C, P): an ungrouped
    skeleton lies on a person's reprojection."""
    on_person = np.zeros(v.has.shape, bool)
    explained = np.zeros(ungrouped.shape, bool)
    f, c, p = np.nonzero(ungrouped)
    if not len(f):
        return on_person, explained
    near = _median_distances(v, xy, score, f, c, p, flip) < ON_PERSON
    explained[f, c, p] = near.any(-1)
    m, g = np.nonzero(near)
    on_person[c[m], f[m], g] = True
    return on_person, explained


def _attach(v: _Views, members, xy, score, ungrouped, flip) -> tuple[np.ndarray, np.ndarray]:
    """members (F, G, C) with each ungrouped skeleton that lies on a person the camera has no
    skeleton of added (the nearest person; the nearest skeleton of several), and which
    skeletons (F, C, P) were added."""
    members = members.copy()
    attached = np.zeros(ungrouped.shape, bool)
    f, c, p = np.nonzero(ungrouped)
    if not len(f):
        return members, attached
    med = _median_distances(v, xy, score, f, c, p, flip)  # (M, G) image heights
    med = np.where(v.has[c, f], np.inf, med)  # only people the camera has none of
    g = np.argmin(med, -1)
    best = med[np.arange(len(f)), g]
    ok = best < ON_PERSON
    order = np.argsort(-best[ok])  # nearest last: it wins a person several skeletons lie on
    f, c, p, g = (a[ok][order] for a in (f, c, p, g))
    members[f, g, c] = p
    attached[f, c, p] = members[f, g, c] == p
    return members, attached


def _median_distances(v: _Views, xy, score, f, c, p, flip) -> np.ndarray:
    """Median keypoint distance (M, G) of skeletons (f, c, p) to each person's reprojection in
    their camera, as they are or mirrored (``flip``: the layout's), in the person's image heights (inf: fewer than 3 keypoints in common, or no
    person)."""
    both = (score[f, c, p] > 0)[:, None] & v.full_ok[c, f]  # (M, G, K)
    meds = []
    for order in (np.arange(len(flip)), flip):  # as is, and left for right (a whole-body swap)
        d = np.linalg.norm(xy[f, c, p][:, None, order] - v.full[c, f], axis=-1)  # (M, G, K)
        ok = both & (score[f, c, p][:, None, order] > 0)
        with warnings.catch_warnings():  # all-NaN rows (nothing in common) are not near
            warnings.simplefilter("ignore", RuntimeWarning)
            meds.append(np.nanmedian(np.where(ok, d, np.nan), axis=-1))
    med = np.fmin(*meds)
    ok = (both.sum(-1) >= 3) & v.valid[f] & (v.h[c, f] > 0)
    return np.where(ok, med / np.maximum(v.h[c, f], 1e-9), np.inf)


def _limb_mixes(v: _Views, lay: Layout, mix_distance: float) -> tuple[FittedField, np.ndarray]:
    """limb_mix_rate: lower limbs far from their own consensus and on another person's; and
    their keypoints (C, F, G, K)."""
    wrong = np.zeros(v.seen.shape, bool)
    centre = (v.full * v.full_ok[..., None]).sum(-2) / np.maximum(v.full_ok.sum(-1), 1)[..., None]
    gap = np.linalg.norm(centre[:, :, :, None] - centre[:, :, None], axis=-1)  # (C, F, G, G')
    other = v.valid[:, :, None] & v.valid[:, None] & ~np.eye(v.valid.shape[1], dtype=bool)
    gap = np.where(other[None] & v.has[:, :, :, None] & v.has[:, :, None], gap, np.inf)
    nearest = np.argmin(gap, -1)  # (C, F, G): the simulator mixes with the nearest person
    near = np.take_along_axis(gap, nearest[..., None], -1)[..., 0] < mix_distance * v.h
    C, F, G = nearest.shape
    ci, fi = np.arange(C)[:, None, None], np.arange(F)[None, :, None]
    eligible_limbs, mixed_limbs = 0, 0
    for side in ("l", "r"):
        for a, b in _LOWER_LIMBS:
            if f"{side}_{a}" not in lay.keypoints or f"{side}_{b}" not in lay.keypoints:
                continue
            k = np.array([lay.index(f"{side}_{a}"), lay.index(f"{side}_{b}")])
            theirs = v.loo[ci, fi, nearest][..., k, :]  # (C, F, G, 2, 2)
            theirs_ok = v.loo_ok[ci, fi, nearest][..., k].all(-1)
            mine = v.loo[..., k, :]
            dist = lambda a, b: np.linalg.norm(a - b, axis=-1).mean(-1)  # noqa: E731
            # Only limbs apart from the other's can be told mixed.
            apart = dist(mine, theirs) > 2 * MIX_MIN_ERROR * v.h
            seen = v.seen[..., k].all(-1) & v.loo_ok[..., k].all(-1) & theirs_ok
            eligible = seen & near & apart
            own, to_other = dist(v.det[..., k, :], mine), dist(v.det[..., k, :], theirs)
            mixed = eligible & (own > MIX_MIN_ERROR * v.h) & (to_other < 0.5 * own)
            wrong[..., k] |= mixed[..., None]
            eligible_limbs += int(eligible.sum())
            mixed_limbs += int(mixed.sum())
    if eligible_limbs < MIN_SAMPLES:
        return _kept("limb_mix_rate", "too few lower limbs with another person near"), wrong
    field = FittedField(
        "limb_mix_rate",
        round(mixed_limbs / eligible_limbs, 4),
        None,
        eligible_limbs,
        True,
        f"{mixed_limbs} of {eligible_limbs} forearms and shins with the nearest other detected "
        f"person within {mix_distance:g} image heights (and their limb apart) lie on its "
        "consensus",
    )
    return field, wrong


def _border(v: _Views) -> FittedField:
    """border_margin: how far inside the image border keypoints are mostly missing."""
    use = v.has[..., None] & v.loo_ok & v.inside(v.loo, 0.0)
    shape = (len(v.size), 1, 1, 1)
    w, h = v.size[:, 0].reshape(shape), v.size[:, 1].reshape(shape)
    x, y = v.loo[..., 0], v.loo[..., 1]
    d = (np.minimum(np.minimum(x, w - x), np.minimum(y, h - y)) / h)[use]
    seen = v.seen[use]
    interior = (d >= 0.1) & (d < 0.3)
    edge = d < BORDER_BINS[-1]
    if interior.sum() < MIN_SAMPLES or edge.sum() < MIN_SAMPLES:
        return _kept("border_margin", "too few keypoints near the image border")
    rate = seen[interior].mean()
    b = np.digitize(d[edge], BORDER_BINS) - 1
    n = np.bincount(b, minlength=len(BORDER_BINS) - 1)
    k = np.bincount(b, weights=seen[edge], minlength=len(BORDER_BINS) - 1)
    low = (k < 0.5 * rate * n) | (n == 0)
    first_ok = int(np.argmin(low)) if not low.all() else len(low)
    margin = float(BORDER_BINS[first_ok])
    return FittedField(
        "border_margin",
        round(margin, 4),
        None,
        int(edge.sum()),
        True,
        f"keypoints within {margin:g} image heights of the border are reported less than half "
        f"as often as inside ({rate:.3f}); bins of {BORDER_BINS[1]:g}",
    )


def _scores(score: np.ndarray) -> tuple[FittedField, FittedField]:
    """score_beta by moments of the reported scores over score_max, their 99.9th percentile."""
    s = np.asarray(score, np.float64)
    s = s[s > 0]
    if len(s) < MIN_SAMPLES:
        return _kept("score_beta", "too few scores"), _kept("score_max", "too few scores")
    top = float(np.quantile(s, 0.999))
    u = np.clip(s / top, 1e-6, 1 - 1e-6)
    mean, var = float(u.mean()), float(u.var())
    common = mean * (1 - mean) / max(var, 1e-9) - 1
    beta = (round(mean * common, 3), round((1 - mean) * common, 3))
    return (
        FittedField(
            "score_beta",
            beta,
            None,
            len(s),
            True,
            f"moments of the reported scores / score_max (mean {mean:.3f}, std {var**0.5:.3f})",
        ),
        FittedField(
            "score_max", round(top, 4), None, len(s), True, "99.9th percentile of the scores"
        ),
    )


def _kept(name: str, why: str) -> FittedField:
    default = getattr(DetectorConfig(), name)
    return FittedField(name, default, default, 0, False, why)


def _show(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, tuple) and value and isinstance(value[0], float):
        return "(" + ", ".join(f"{x:.3g}" for x in value) + ")"
    return str(value)


def _plain(value):
    if isinstance(value, tuple):
        return [_plain(x) for x in value]
    if isinstance(value, Mapping):
        return {k: _plain(x) for k, x in value.items()}
    return value
