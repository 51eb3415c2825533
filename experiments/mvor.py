"""MVOR days 1-2 (the CAMMA operating room): its files as the package's arrays, and its protocol.

One dataset's format, so it lives here and not in the package (issue 36). The files and their
conventions are described in ``../shared/real/mvor-days12/README.md``; in short:

* three RGB-D cameras used as RGB (640 x 480); ``extrinsics[i]`` maps camera i to camera 1,
  ``firstCamToRoomRef`` camera 1 to the room; every 3D number is in millimetres;
* the 3D ground truth (``annotations3D``) is in CAMERA 1's frame whatever ``ref_camera`` says;
  10 upper-body joints (then two hand points, unused here), flag 2 annotated, 1 estimated
  (often a placeholder: treated as not annotated);
* the 2D annotations fit a distortion-FREE camera better than the stored coefficients in any
  order (README), so the rig here has no distortion unless asked (``distortion=True`` reads the
  coefficients as [k1, k2, k3, p1, p2]);
* the OpenPose detections' ``coco_keypoints`` are in COCO-17 order.

Arrays use the package's letters: F multi-view frames, C = 3 cameras, P detections per view
(padded), H annotated people per frame (padded: every person with a 2D or 3D annotation in the
frame, those with 3D ground truth first), K keypoints, J = 10 MVOR joints.

The protocol (`mvor_protocol.evaluate`): per frame, predicted people are matched to true ones by the Hungarian
method on the mean distance over the joints both have, pairs farther than ``GATE_MM`` apart never
matched; MPJPE (mm) over the matched people's annotated joints that the prediction produced; PCK3D
at 100 and 150 mm over EVERY annotated joint of every true person (a missed person's joints and a
joint not produced are wrong); missed people counted; upper-body PCP on 6 limbs; per day and
overall.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mvpose_jax.cameras import Rig, make_rig, point_depths, project_points
from mvpose_jax.data.checks import ClippedScores, check_keypoints, load_json
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Detections, Poses3D, convert_keypoints, get_layout

# Where the data lies beside the repository (a checkout at /work/<tree>: /work/shared/...).
DEFAULT_ROOT = Path(__file__).resolve().parents[2] / "shared" / "real" / "mvor-days12"
ANNOTATIONS = Path("annotations") / "camma_mvor_2018.json"
DETECTIONS = Path("detections_results") / "openpose_kps.json"
CAMERAS = ("cam1", "cam2", "cam3")
# MVOR's joints in its `categories` order (its names with our l_/r_ prefixes).
JOINTS = (
    "head",
    "neck",
    "l_shoulder",
    "r_shoulder",
    "l_hip",
    "r_hip",
    "l_elbow",
    "r_elbow",
    "l_wrist",
    "r_wrist",
)
# Each MVOR joint from our layout's keypoints: the mean of the first alternative whose keypoints
# all exist. The head is the ears' midpoint first: of the detector's points it lies closest to
# MVOR's annotated head (41 mm median, the eyes' midpoint 87 mm, the nose 93 mm; README), then
# the eyes' midpoint, then the nose. The neck is coco18's (the shoulders' midpoint; MVOR's is about
# 88 mm away, mostly above). Shoulders, elbows, wrists and hips are the same names; MVOR's hips
# sit 130-140 mm higher than COCO's (README), an offset of the definitions we leave visible.
JOINT_SOURCES: dict[str, tuple[tuple[str, ...], ...]] = {
    "head": (("l_ear", "r_ear"), ("l_eye", "r_eye"), ("nose",)),
    "neck": (("neck",), ("l_shoulder", "r_shoulder")),
    **{j: ((j,),) for j in JOINTS[2:]},
}
# MVOR's 3D flags: 2 annotated, 1 estimated or a placeholder (README: not to be trusted).
ANNOTATED = 2
# The protocol's settings (stated in the report).
GATE_MM = 500.0
PCK_MM = (100.0, 150.0)
PCP_RATIO = 0.5
# Upper-body PCP: (limb, one end, other end); "mid_hip" is the hips' midpoint.
UPPER_BODY_LIMBS = (
    ("head", "head", "neck"),
    ("torso", "neck", "mid_hip"),
    ("l_upper_arm", "l_shoulder", "l_elbow"),
    ("r_upper_arm", "r_shoulder", "r_elbow"),
    ("l_lower_arm", "l_elbow", "l_wrist"),
    ("r_lower_arm", "r_elbow", "r_wrist"),
)
# Detections are assigned to people (the true groupings, `true_identity`) when their mean
# distance over shared joints is at most this share of the reference joints' box diagonal, with
# this many shared joints at least. Measured on days 1-2, each reference's nearest detection (as
# a share of that diagonal): 2D annotations 832 below 0.1, 268 in 0.1-0.2, 17 in 0.2-0.3, 62 in
# 0.3-0.5, 354 beyond (the person's detection is missing, the nearest is someone else's);
# projected 3D truth 13, 78, 29, 25, 214. No clean valley for distant people (a small box, and
# MVOR's hips 130-140 mm from COCO's), so the gate is generous; the table's true-group rows move
# little with it (gate 0.3 / 0.4 / 0.5: 187 / 175 / 162 of 572 people missed, PCK3D@150 48.4 /
# 48.8 / 48.8 % with DLT).
GROUPING_GATE = 0.4
GROUPING_MIN_JOINTS = 3


@dataclasses.dataclass(frozen=True)
class MvorData:
    """MVOR's multi-view frames as arrays (see the module docstring for the letters).

    Attributes:
      rig: the three cameras; world = MVOR's room frame (z up), metres.
      frame_ids: (F,) the multi-view ids ``"<cam1 id>_<cam2 id>_<cam3 id>"``.
      day: (F,) int, the recording day.
      detections: OpenPose's skeletons, xy (F, C, P, K, 2) px, score (F, C, P, K), count (F, C),
        in ``layout``.
      layout: the detections' keypoint layout ("coco18": COCO's 17 and the shoulders' midpoint).
      gt: the 3D ground truth in MVOR's joints: xyz (F, H, J, 3) metres; valid (F, H) the person
        has 3D ground truth; keypoint_valid (F, H, J) the joint is annotated (flag 2).
      gt_flag: (F, H, J) int, MVOR's 3D flags (0 where no 3D).
      person_id: (F, H) int, MVOR's ``person_id`` of each slot, -1 for padding.
      annotation_xy: (F, C, H, J, 2) px, each person's 2D annotation per camera.
      annotation_flag: (F, C, H, J) int, 2 visible, 1 occluded, 0 not annotated or no annotation.
      annotation_box: (F, C, H, 4) the annotation's bbox (x, y, w, h) px, 0 where none.
      num_records_3d: 3D records in the file (one duplicate record is dropped, see `load_mvor`).
      num_detections: detections in the file.
      clipped_scores: detection scores above 1 clipped to 1 (OpenPose's heatmap peaks).
    """

    rig: Rig
    frame_ids: tuple[str, ...]
    day: np.ndarray
    detections: Detections
    layout: str
    gt: Poses3D
    gt_flag: np.ndarray
    person_id: np.ndarray
    annotation_xy: np.ndarray
    annotation_flag: np.ndarray
    annotation_box: np.ndarray
    num_records_3d: int
    num_detections: int
    clipped_scores: int

    @property
    def num_frames(self) -> int:
        return len(self.frame_ids)


def load_mvor(
    root: str | Path = DEFAULT_ROOT, *, layout: str = "coco18", distortion: bool = False
) -> MvorData:
    """Reads MVOR's annotation and detection files into arrays.

    A 3D record identical to another of the same frame and person (MVOR holds one: ids 718 and
    719) is kept once.

    Args:
      root: the folder holding ``annotations/`` and ``detections_results/``.
      layout: the detections' layout (converted from COCO-17 by keypoint name).
      distortion: use the stored distortion coefficients (read as [k1, k2, k3, p1, p2]); default
        a distortion-free camera, which the annotations fit best (README).
    Raises:
      InputError naming file, frame (multi-view id), camera and field of the first bad value: a
      missing file or key, a multi-view record without one of the three cameras, a non-finite or
      malformed number, an unknown image id, a 3D record of an unknown frame.
    """
    root = Path(root)
    ann_file, det_file = root / ANNOTATIONS, root / DETECTIONS
    doc = load_json(ann_file)
    dets = load_json(det_file)
    if not isinstance(doc, dict):
        raise InputError("expected a JSON object", file=ann_file)
    rig, room_from_cam1 = _rig(
        _key(doc, "cameras_info", ann_file, "cameras_info"), ann_file, distortion
    )
    frame_ids, image_frame = _frames(_list(doc, "multiview_images", ann_file), ann_file)
    image_day = {}
    for i, im in enumerate(_list(doc, "images", ann_file)):
        field = f"images[{i}]"
        image_day[_int(im, "id", ann_file, field)] = _int(im, "day_id", ann_file, field)
    day = np.zeros(len(frame_ids), np.int32)
    for image, (f, c) in image_frame.items():
        if image not in image_day:
            raise InputError(
                f"image {image} of the multi-view record is not among `images`",
                file=ann_file,
                frame=frame_ids[f],
                camera=CAMERAS[c],
                field="images",
            )
        day[f] = image_day[image]
    people = _people(doc, ann_file, frame_ids, image_frame, room_from_cam1)
    det, clipped = _detections(dets, det_file, frame_ids, image_frame, layout)
    return MvorData(
        rig, frame_ids, day, det, layout, num_detections=len(dets), clipped_scores=clipped, **people
    )


def select_frames(data: MvorData, frames: Sequence[int] | np.ndarray) -> MvorData:
    """The same data on a subset of frames (indices, in the given order)."""
    idx = np.asarray(frames, np.int64)
    d = data.detections
    return dataclasses.replace(
        data,
        frame_ids=tuple(data.frame_ids[i] for i in idx),
        day=data.day[idx],
        detections=Detections(d.xy[idx], d.score[idx], d.count[idx]),
        gt=Poses3D(*(a[idx] for a in data.gt)),
        gt_flag=data.gt_flag[idx],
        person_id=data.person_id[idx],
        annotation_xy=data.annotation_xy[idx],
        annotation_flag=data.annotation_flag[idx],
        annotation_box=data.annotation_box[idx],
    )


def to_joints(
    values: np.ndarray, present: np.ndarray, layout: str = "coco18"
) -> tuple[np.ndarray, np.ndarray]:
    """MVOR's 10 joints from keypoints of ``layout`` (`JOINT_SOURCES`).

    Args:
      values: (..., K, D) keypoints (pixels or metres); present: (..., K) bool or scores (> 0).
    Returns:
      values (..., J, D) and present (..., J) bool; a joint none of whose alternatives exists is
      absent (values 0).
    """
    lay = get_layout(layout)
    values = np.asarray(values, np.float64)
    have = np.asarray(present) > 0
    out = np.zeros(values.shape[:-2] + (len(JOINTS), values.shape[-1]))
    ok = np.zeros(values.shape[:-2] + (len(JOINTS),), bool)
    for j, joint in enumerate(JOINTS):
        for names in reversed(JOINT_SOURCES[joint]):  # the first alternative is written last
            if not all(n in lay.keypoints for n in names):
                continue
            idx = [lay.index(n) for n in names]
            there = have[..., idx].all(-1)
            out[..., j, :] = np.where(
                there[..., None], values[..., idx, :].mean(-2), out[..., j, :]
            )
            ok[..., j] |= there
    return out, ok


def poses_to_joints(poses: Poses3D, layout: str = "coco18") -> Poses3D:
    """A `Poses3D` of ``layout`` as MVOR's joints (a non-finite keypoint counts as absent)."""
    xyz = np.asarray(poses.xyz)
    kv = np.asarray(poses.keypoint_valid, bool) & np.isfinite(xyz).all(-1)
    kv &= np.asarray(poses.valid, bool)[..., None]
    joints, ok = to_joints(np.where(kv[..., None], xyz, 0.0), kv, layout)
    return Poses3D(joints, np.asarray(poses.valid, bool), ok)


def true_identity(data: MvorData) -> np.ndarray:
    """Each detection's annotated person, for the ground-truth groupings.

    A person's reference in a view is their 2D annotation there; where they have none (99 of the
    572 people with 3D ground truth are annotated in one view only), the projection of their
    annotated 3D joints. Per frame and camera, detections (as MVOR joints, `to_joints`) and
    references are paired by the Hungarian method on their mean pixel distance over the joints
    both have; a pair is kept when it shares `GROUPING_MIN_JOINTS` joints and the distance is at
    most `GROUPING_GATE` of the diagonal of the reference joints' bounding box.

    Returns:
      (F, C, P) int32: the person slot (the H axis of ``data``) of each detection, -1 for none.
    """
    from scipy.optimize import linear_sum_assignment

    ref_xy, ref_ok = _references(data)  # (F, C, H, J, 2), (F, C, H, J)
    det = data.detections
    F, C, P = np.shape(det.score)[:3]
    xy, have = to_joints(det.xy, det.score, data.layout)  # (F, C, P, J, 2), (F, C, P, J)
    identity = np.full((F, C, P), -1, np.int32)
    for f in range(F):
        for c in range(C):
            n = int(det.count[f, c])
            people = np.flatnonzero(ref_ok[f, c].any(-1))
            if n == 0 or len(people) == 0:
                continue
            ok_h, xy_h = ref_ok[f, c][people], ref_xy[f, c][people]  # (h, J), (h, J, 2)
            both = have[f, c, :n, None] & ok_h[None]  # (n, h, J)
            d = np.linalg.norm(xy[f, c, :n, None] - xy_h[None], axis=-1)
            shared = both.sum(-1)
            mean = np.where(both, d, 0).sum(-1) / np.maximum(shared, 1)
            lo = np.where(ok_h[..., None], xy_h, np.inf).min(-2)
            hi = np.where(ok_h[..., None], xy_h, -np.inf).max(-2)
            diagonal = np.linalg.norm(hi - lo, axis=-1)  # (h,)
            ok = (shared >= GROUPING_MIN_JOINTS) & (mean <= GROUPING_GATE * diagonal[None])
            rows, cols = linear_sum_assignment(np.where(ok, mean, 1e9))
            keep = ok[rows, cols]
            identity[f, c, rows[keep]] = people[cols[keep]]
    return identity


def _references(data: MvorData) -> tuple[np.ndarray, np.ndarray]:
    """Each person's 2D reference per view: the annotation, else the projected 3D truth (flag 2,
    in front of the camera). Returns xy (F, C, H, J, 2) px and ok (F, C, H, J)."""
    xyz = np.asarray(data.gt.xyz, np.float32)
    px = np.moveaxis(np.asarray(project_points(data.rig, xyz)), 0, 1)  # (F, C, H, J, 2)
    depth = np.moveaxis(np.asarray(point_depths(data.rig, xyz)), 0, 1)  # (F, C, H, J)
    projected_ok = np.asarray(data.gt.keypoint_valid)[:, None] & (depth > 0.1)
    annotated_ok = data.annotation_flag > 0
    annotated = annotated_ok.any(-1)  # (F, C, H)
    return (
        np.where(annotated[..., None, None], data.annotation_xy, px),
        np.where(annotated[..., None], annotated_ok, projected_ok),
    )


def reprojection_of_truth(data: MvorData) -> dict:
    """The 3D ground truth projected into each camera against the 2D annotations (px).

    Pairs: the same person, a 3D joint with flag > 0 and a 2D joint with flag > 0 (the README's
    check). Returns {"overall": stats, "day<d>": {"all": stats, camera: stats}} with stats
    {"median", "p90", "count"}.
    """
    px = np.asarray(project_points(data.rig, np.asarray(data.gt.xyz, np.float32)))  # (C,F,H,J,2)
    px = np.moveaxis(px, 0, 1)  # (F, C, H, J, 2)
    err = np.linalg.norm(px - data.annotation_xy, axis=-1)
    use = (data.gt_flag > 0)[:, None] & (data.annotation_flag > 0)

    def stats(sel: np.ndarray) -> dict:
        e = err[sel]
        if e.size == 0:
            return {"median": float("nan"), "p90": float("nan"), "count": 0}
        return {
            "median": float(np.median(e)),
            "p90": float(np.percentile(e, 90)),
            "count": int(e.size),
        }

    out = {"overall": stats(use)}
    for d in np.unique(data.day):
        on_day = (data.day == d)[:, None, None, None]
        out[f"day{int(d)}"] = {"all": stats(use & on_day)} | {
            name: stats(use & on_day & (np.arange(len(CAMERAS)) == c)[None, :, None, None])
            for c, name in enumerate(CAMERAS)
        }
    return out


# =========================================================================== reading


def _key(record, key: str, file: Path, field: str, **loc):
    """``record[key]``, else InputError naming ``field``."""
    if not isinstance(record, dict) or key not in record:
        raise InputError(f"missing key {key!r}", file=file, field=field, **loc)
    return record[key]


def _list(doc: dict, key: str, file: Path) -> list:
    value = _key(doc, key, file, key)
    if not isinstance(value, list):
        raise InputError("expected a list", file=file, field=key)
    return value


def _int(record, key: str, file: Path, where: str, **loc) -> int:
    """An integer (or a string of one: MVOR writes some ids as strings) at ``where.key``."""
    field = f"{where}.{key}"
    value = _key(record, key, file, field, **loc)
    if isinstance(value, (int, str)) and not isinstance(value, bool):
        try:
            return int(value)
        except ValueError:
            pass
    raise InputError(f"expected an integer, got {value!r}", file=file, field=field, **loc)


def _numbers(value, count: int, file: Path, field: str, **loc) -> np.ndarray:
    """``value`` as ``count`` finite numbers (a flat list), else InputError at the first bad
    entry."""
    if not isinstance(value, list) or len(value) != count:
        got = f"{len(value)} entries" if isinstance(value, list) else type(value).__name__
        raise InputError(
            f"expected a list of {count} numbers, got {got}", file=file, field=field, **loc
        )
    for i, v in enumerate(value):
        if not (_is_number(v) and math.isfinite(v)):
            raise InputError(
                f"{v!r} is not a finite number", file=file, field=f"{field}[{i}]", **loc
            )
    return np.asarray(value, np.float64)


def _numbers_at(record, key: str, count: int, file: Path, where: str, **loc) -> np.ndarray:
    """``record[key]`` as ``count`` finite numbers (`_numbers`); ``where`` names the record."""
    field = f"{where}.{key}"
    return _numbers(_key(record, key, file, field, **loc), count, file, field, **loc)


def _flags(values: np.ndarray, file: Path, field: str, *, stride: int, **loc) -> np.ndarray:
    """MVOR's flags (0, 1 or 2) as integers: the last of every ``stride`` numbers of the flat list
    ``field``. values: (J,) -> (J,) int64."""
    bad = ~np.isin(values, (0, 1, 2))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"flag {values[i]:g} is not 0, 1 or 2",
            file=file,
            field=f"{field}[{stride * i + stride - 1}]",
            **loc,
        )
    return values.astype(np.int64)


def _rig(info, file: Path, distortion: bool) -> tuple[Rig, np.ndarray]:
    """The three cameras, world = the room frame (metres), and room_from_cam1 (4, 4) mm."""
    where = "cameras_info.camParams"
    params = _key(info, "camParams", file, where)
    intrinsics = _key(params, "intrinsics", file, f"{where}.intrinsics")
    extrinsics = _key(params, "extrinsics", file, f"{where}.extrinsics")
    for name, value in (("intrinsics", intrinsics), ("extrinsics", extrinsics)):
        if not isinstance(value, list) or len(value) != len(CAMERAS):
            raise InputError(
                f"expected one entry per camera ({len(CAMERAS)})",
                file=file,
                field=f"{where}.{name}",
            )
    room_from_cam1 = _numbers_at(params, "firstCamToRoomRef", 16, file, where).reshape(4, 4)
    K, dist, R, t, size = [], [], [], [], []
    for c, cam in enumerate(CAMERAS):
        at = f"{where}.intrinsics[{c}]"
        fx, fy = _numbers_at(intrinsics[c], "focallength", 2, file, at, camera=cam)
        cx, cy = _numbers_at(intrinsics[c], "principalpoint", 2, file, at, camera=cam)
        size.append(_numbers_at(intrinsics[c], "imagesize", 2, file, at, camera=cam))
        k1, k2, k3, p1, p2 = _numbers_at(intrinsics[c], "distortion", 5, file, at, camera=cam)
        dist.append([k1, k2, p1, p2, k3] if distortion else [0.0] * 5)
        K.append([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        field = f"{where}.extrinsics[{c}]"
        cam1_from_cam = _numbers(extrinsics[c], 16, file, field, camera=cam).reshape(4, 4)
        # Room from camera c (millimetres); its inverse is cam_from_world.
        cam_from_room = np.linalg.inv(room_from_cam1 @ cam1_from_cam)
        R.append(cam_from_room[:3, :3])
        t.append(cam_from_room[:3, 3] / 1000.0)
    rig = make_rig(
        np.array(K),
        np.array(dist),
        np.array(R),
        np.array(t),
        np.array(size),
        CAMERAS,
        up=(0.0, 0.0, 1.0),
        file=file,
    )
    return rig, room_from_cam1


def _frames(records: list, file: Path) -> tuple[tuple[str, ...], dict[int, tuple[int, int]]]:
    """The multi-view frames' ids and each image's (frame, camera)."""
    ids, image_frame = [], {}
    for f, rec in enumerate(records):
        where = f"multiview_images[{f}]"
        mv_id = str(_key(rec, "id", file, f"{where}.id"))
        images = _key(rec, "images", file, f"{where}.images", frame=mv_id)
        if not isinstance(images, list):
            raise InputError(
                "expected a list of image records", file=file, frame=mv_id, field=f"{where}.images"
            )
        cams = {}
        for i, im in enumerate(images):
            at = f"{where}.images[{i}]"
            cam_id = _int(im, "cam_id", file, at, frame=mv_id)
            if not 1 <= cam_id <= len(CAMERAS) or cam_id in cams:
                reason = "repeated" if cam_id in cams else f"not 1-{len(CAMERAS)}"
                raise InputError(
                    f"cam_id {cam_id} is {reason}", file=file, frame=mv_id, field=f"{at}.cam_id"
                )
            cams[cam_id] = _int(im, "id", file, at, frame=mv_id)
        for c, cam in enumerate(CAMERAS):
            if c + 1 not in cams:
                raise InputError(
                    f"the multi-view record has no image of {cam} (it has cam_id {sorted(cams)})",
                    file=file,
                    frame=mv_id,
                    camera=cam,
                    field=f"{where}.images",
                )
            image_frame[cams[c + 1]] = (f, c)
        ids.append(mv_id)
    if len(set(ids)) != len(ids):
        raise InputError("repeated multi-view ids", file=file, field="multiview_images")
    return tuple(ids), image_frame


def _people(doc: dict, file: Path, frame_ids, image_frame, room_from_cam1: np.ndarray) -> dict:
    """The annotated people of every frame: 3D ground truth and 2D annotations per camera."""
    F, C, J = len(frame_ids), len(CAMERAS), len(JOINTS)
    frame_of = {mv: f for f, mv in enumerate(frame_ids)}
    # Each frame's person slots by person_id: people with 3D ground truth first, in file order.
    slots: list[dict[int, int]] = [{} for _ in range(F)]
    gt3d: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    records_3d = _list(doc, "annotations3D", file)
    for i, rec in enumerate(records_3d):
        where = f"annotations3D[{i}]"
        mv = str(_key(rec, "image_ids", file, f"{where}.image_ids"))
        if mv not in frame_of:
            raise InputError(
                "not a multi-view id of `multiview_images`",
                file=file,
                frame=mv,
                field=f"{where}.image_ids",
            )
        f = frame_of[mv]
        pid = _int(rec, "person_id", file, where, frame=mv)
        values = _numbers_at(rec, "keypoints3D", 48, file, where, frame=mv).reshape(12, 4)
        flag = _flags(values[:J, 3], file, f"{where}.keypoints3D", stride=4, frame=mv)
        # In camera 1's frame whatever ref_camera says (README); millimetres -> the room, metres.
        xyz = (values[:J, :3] @ room_from_cam1[:3, :3].T + room_from_cam1[:3, 3]) / 1000.0
        if (f, pid) in gt3d:
            old_xyz, old_flag = gt3d[(f, pid)]
            if np.array_equal(old_xyz, xyz) and np.array_equal(old_flag, flag):
                continue  # MVOR's ids 718 and 719: one person stored twice
            raise InputError(
                f"person {pid} has two different 3D records", file=file, frame=mv, field=where
            )
        gt3d[(f, pid)] = (xyz, flag)
        slots[f].setdefault(pid, len(slots[f]))
    anns = []
    for i, rec in enumerate(_list(doc, "annotations", file)):
        where = f"annotations[{i}]"
        image = _int(rec, "image_id", file, where)
        if image not in image_frame:
            raise InputError(
                f"image {image} is in no multi-view record", file=file, field=f"{where}.image_id"
            )
        f, c = image_frame[image]
        loc = dict(frame=frame_ids[f], camera=CAMERAS[c])
        if _key(rec, "only_bbox", file, f"{where}.only_bbox", **loc):
            continue  # a box without keypoints (and without a person id)
        pid = _int(rec, "person_id", file, where, **loc)
        kp = _numbers_at(rec, "keypoints", 3 * J, file, where, **loc).reshape(J, 3)
        flag = _flags(kp[:, 2], file, f"{where}.keypoints", stride=3, **loc)
        box = _numbers_at(rec, "bbox", 4, file, where, **loc)
        slots[f].setdefault(pid, len(slots[f]))
        anns.append((f, c, pid, kp[:, :2], flag, box, where))
    H = max([1] + [len(s) for s in slots])
    xyz = np.zeros((F, H, J, 3))
    gt_flag = np.zeros((F, H, J), np.int64)
    valid = np.zeros((F, H), bool)
    person_id = np.full((F, H), -1, np.int64)
    for f, frame_slots in enumerate(slots):
        for pid, h in frame_slots.items():
            person_id[f, h] = pid
    for (f, pid), (x, flag) in gt3d.items():
        h = slots[f][pid]
        xyz[f, h], gt_flag[f, h], valid[f, h] = x, flag, True
    ann_xy = np.zeros((F, C, H, J, 2))
    ann_flag = np.zeros((F, C, H, J), np.int64)
    ann_box = np.zeros((F, C, H, 4))
    seen = set()
    for f, c, pid, xy, flag, box, where in anns:
        h = slots[f][pid]
        if (f, c, h) in seen:
            raise InputError(
                f"person {pid} is annotated twice in this image",
                file=file,
                frame=frame_ids[f],
                camera=CAMERAS[c],
                field=where,
            )
        seen.add((f, c, h))
        ann_xy[f, c, h], ann_flag[f, c, h], ann_box[f, c, h] = xy, flag, box
    return dict(
        gt=Poses3D(xyz, valid, valid[..., None] & (gt_flag == ANNOTATED)),
        gt_flag=gt_flag,
        person_id=person_id,
        annotation_xy=ann_xy,
        annotation_flag=ann_flag,
        annotation_box=ann_box,
        num_records_3d=len(records_3d),
    )


def _detections(dets, file: Path, frame_ids, image_frame, layout: str) -> tuple[Detections, int]:
    """OpenPose's skeletons per frame and camera, converted from COCO-17 to ``layout``; also the
    number of scores clipped to 1."""
    if not isinstance(dets, list):
        raise InputError("expected a list of detections", file=file)
    F, C, K = len(frame_ids), len(CAMERAS), 17
    keypoints, where = [], []
    for i, rec in enumerate(dets):
        image = _int(rec, "image_id", file, f"[{i}]")
        if image not in image_frame:
            raise InputError(
                f"image {image} is in no multi-view record", file=file, field=f"[{i}].image_id"
            )
        f, c = image_frame[image]
        kp = _key(rec, "coco_keypoints", file, f"[{i}].coco_keypoints")
        if not isinstance(kp, list) or len(kp) != 3 * K or not all(_is_number(v) for v in kp):
            raise InputError(
                f"expected {K} x (x, y, score) numbers",
                file=file,
                frame=frame_ids[f],
                camera=CAMERAS[c],
                field=f"[{i}].coco_keypoints",
            )
        keypoints.append(np.asarray(kp, np.float64).reshape(K, 3))
        where.append((i, f, c))
    stacked = np.stack(keypoints) if keypoints else np.zeros((0, K, 3))
    clipped = ClippedScores()
    # THE package's keypoint check: finite coordinates (NaN with score 0 = missing), scores in
    # [0, 1.5], those above 1 clipped (OpenPose's heatmap peaks), errors located.
    xy, score = check_keypoints(
        stacked[..., :2],
        stacked[..., 2],
        num_keypoints=K,
        locate=lambda n: (frame_ids[where[n][1]], CAMERAS[where[n][2]], where[n][0]),
        file=file,
        field="[{p}].coco_keypoints[{k}]",
        score_field="[{p}].coco_keypoints[{k}].score",
        count_field="[{p}].coco_keypoints",
        reading=True,
        clipped=clipped,
    )
    count = np.zeros((F, C), np.int32)
    for _, f, c in where:
        count[f, c] += 1
    P = max(1, int(count.max()) if count.size else 1)
    out_xy = np.zeros((F, C, P, K, 2), np.float32)
    out_score = np.zeros((F, C, P, K), np.float32)
    row = np.zeros((F, C), np.int32)
    for n, (_, f, c) in enumerate(where):
        out_xy[f, c, row[f, c]], out_score[f, c, row[f, c]] = xy[n], score[n]
        row[f, c] += 1
    # A missing keypoint's coordinates are 0 (the `Detections` convention).
    out_xy = np.where(out_score[..., None] > 0, out_xy, 0.0).astype(np.float32)
    conv_xy, conv_score = convert_keypoints(out_xy, out_score, "coco17", layout)
    return Detections(conv_xy, conv_score, count), clipped.count


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)
