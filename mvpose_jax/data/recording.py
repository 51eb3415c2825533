"""`Recording`: detections of a multi-camera recording plus what is known about them.

Host-side container (numpy arrays) that every reader returns and every writer takes. The padded
arrays follow the contracts in `mvpose_jax.skeletons` (letters F, C, P, K, G).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Detections, Poses3D, get_layout


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
                f"detections have {K}", field="layout",
            )  # fmt: skip
        if self.identity is not None and np.shape(self.identity) != (F, C, P):
            raise InputError(f"identity must be {(F, C, P)}, got {np.shape(self.identity)}", field="identity")
        if self.ground_truth is not None:
            gt = self.ground_truth
            G = np.shape(gt.valid)[1] if np.ndim(gt.valid) == 2 else -1
            if np.shape(gt.xyz) != (F, G, K, 3) or np.shape(gt.keypoint_valid) != (F, G, K):
                raise InputError("ground truth shapes do not match the detections", field="ground_truth")
        if self.projected is not None and np.shape(self.projected) != (F, C, P, K, 2):
            raise InputError("projected must have the shape of detections.xy", field="projected")

    @property
    def num_frames(self) -> int:
        return int(np.shape(self.detections.score)[0])

    @property
    def num_keypoints(self) -> int:
        return int(np.shape(self.detections.score)[3])
