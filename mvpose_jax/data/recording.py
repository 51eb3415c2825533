"""`Recording`: detections of a multi-camera recording plus what is known about them.

Host-side container (numpy arrays) that every reader returns and every writer takes. The padded
arrays follow the contracts in `mvpose_jax.skeletons` (letters F, C, P, K, G). Two edits that
every format and caller may need: `select_cameras` and `convert_layout`; `slice_frames` cuts a
range of frames.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Detections, Poses3D, convert_keypoints, get_layout


@dataclasses.dataclass(frozen=True)
class Recording:
    """A recording: per-frame 2D skeletons of C cameras, optional 3D ground truth and identities.

    Attributes:
      detections: `Detections` (numpy) with xy (F, C, P, K, 2), score (F, C, P, K), count (F, C).
      cameras: C camera names, the order of the camera axis (they must exist in the rig used).
      layout: keypoint layout name (``"coco18"`` …); K = its number of keypoints.
      ground_truth: optional `Poses3D` (numpy), xyz (F, G, K, 3) metres, valid (F, G),
        keypoint_valid (F, G, K).
      identity: optional (F, C, P) int32: the ground-truth person (index on the G axis) of each
        detection; -1 for a false positive or unknown, and for padding rows.
      timestamps: optional (F,) float64 seconds.
      image_names: optional (F, C) str, the image file of each view (the original format has them).
      projected: optional (F, C, P, K, 2): the noise-free projections of the ground truth for each
        detection (the paper's D-projected variant; synthetic recordings have them).
    """

    detections: Detections
    cameras: tuple[str, ...]
    layout: str = "coco18"
    ground_truth: Poses3D | None = None
    identity: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    image_names: np.ndarray | None = None
    projected: np.ndarray | None = None

    def __post_init__(self):
        F, C, P, K = np.shape(self.detections.score)
        if len(self.cameras) != C:
            raise InputError(f"{len(self.cameras)} camera names for {C} cameras", field="cameras")
        if get_layout(self.layout).num_keypoints != K:
            raise InputError(
                f"layout {self.layout!r} has {get_layout(self.layout).num_keypoints} keypoints, "
                f"detections have {K}",
                field="layout",
            )
        if self.identity is not None and np.shape(self.identity) != (F, C, P):
            raise InputError(
                f"identity must be {(F, C, P)}, got {np.shape(self.identity)}", field="identity"
            )
        if self.ground_truth is not None:
            gt = self.ground_truth
            G = np.shape(gt.valid)[1] if np.ndim(gt.valid) == 2 else -1
            if np.shape(gt.xyz) != (F, G, K, 3) or np.shape(gt.keypoint_valid) != (F, G, K):
                raise InputError(
                    "ground truth shapes do not match the detections", field="ground_truth"
                )
        if self.projected is not None and np.shape(self.projected) != (F, C, P, K, 2):
            raise InputError("projected must have the shape of detections.xy", field="projected")

    @property
    def num_frames(self) -> int:
        return int(np.shape(self.detections.score)[0])

    @property
    def num_keypoints(self) -> int:
        return int(np.shape(self.detections.score)[3])


# --------------------------------------------------------------------------- recording edits


def select_cameras(rec: Recording, cameras: Sequence[str], *, file: object = None) -> Recording:
    """The recording restricted to ``cameras`` (names, in this order); P shrinks to fit."""
    cameras = [str(c) for c in cameras]
    for name in cameras:
        if name not in rec.cameras:
            raise InputError(
                f"unknown camera; the recording has {list(rec.cameras)}",
                file=file,
                camera=name,
                field="cameras",
            )
    if len(set(cameras)) != len(cameras):
        raise InputError(f"duplicate camera names {cameras}", file=file, field="cameras")
    idx = np.array([rec.cameras.index(c) for c in cameras], np.int64)
    det = rec.detections
    count = np.asarray(det.count)[:, idx]
    P = max(1, int(count.max(initial=0)))
    take = lambda a: None if a is None else np.asarray(a)[:, idx, :P]  # noqa: E731
    return Recording(
        detections=Detections(take(det.xy), take(det.score), count),
        cameras=tuple(cameras),
        layout=rec.layout,
        ground_truth=rec.ground_truth,
        identity=take(rec.identity),
        timestamps=rec.timestamps,
        image_names=None if rec.image_names is None else np.asarray(rec.image_names)[:, idx],
        projected=take(rec.projected),
    )


def convert_layout(rec: Recording, layout: str) -> Recording:
    """The recording with its keypoints converted to another layout (see `convert_keypoints`)."""
    src, dst = get_layout(rec.layout), get_layout(layout)
    det = rec.detections
    xy, score = convert_keypoints(np.asarray(det.xy), np.asarray(det.score), src, dst)
    gt = rec.ground_truth
    if gt is not None:
        xyz, kvalid = convert_keypoints(np.asarray(gt.xyz), np.asarray(gt.keypoint_valid), src, dst)
        gt = Poses3D(xyz, np.asarray(gt.valid), kvalid & np.asarray(gt.valid)[..., None])
    projected = rec.projected
    if projected is not None:
        ones = np.ones(np.shape(projected)[:-1], bool)
        projected, _ = convert_keypoints(np.asarray(projected), ones, src, dst)
    return Recording(
        detections=Detections(xy, score, np.asarray(det.count)),
        cameras=rec.cameras,
        layout=dst.name,
        ground_truth=gt,
        identity=rec.identity,
        timestamps=rec.timestamps,
        image_names=rec.image_names,
        projected=projected,
    )


def slice_frames(rec: Recording, start: int, stop: int) -> Recording:
    """Frames ``start`` to ``stop`` (exclusive) of a recording, every per-frame field sliced."""
    cut = lambda a: None if a is None else np.asarray(a)[start:stop]  # noqa: E731
    det, gt = rec.detections, rec.ground_truth
    return Recording(
        detections=Detections(cut(det.xy), cut(det.score), cut(det.count)),
        cameras=rec.cameras,
        layout=rec.layout,
        ground_truth=None
        if gt is None
        else Poses3D(cut(gt.xyz), cut(gt.valid), cut(gt.keypoint_valid)),
        identity=cut(rec.identity),
        timestamps=cut(rec.timestamps),
        image_names=cut(rec.image_names),
        projected=cut(rec.projected),
    )


def recording_fps(timestamps) -> float:
    """Frames per second from a recording's timestamps (their median step); 30 without them."""
    if timestamps is None or len(timestamps) < 2:
        return 30.0
    step = float(np.median(np.diff(np.asarray(timestamps, np.float64))))
    return 1.0 / step if step > 0 else 30.0
