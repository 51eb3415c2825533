"""The ``view`` job: any pose result as a rerun recording (``.rrd``) beside its cameras and,
optionally, the detections it was made from (`viewer.write_rerun`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from mvpose_jax.errors import InputError
from mvpose_jax.jobs.common import DetectionsSource, RigSource, detections_of, poses_on_rig
from mvpose_jax.viewer import write_rerun


@dataclasses.dataclass(frozen=True)
class ViewConfig:
    """One ``view`` run.

    Attributes:
      poses: ``poses.npz`` / ``poses.json`` (or their folder), as ``infer`` writes them.
      rig: the calibration.
      detections: the detections the poses were made from (read on the poses' cameras), or
        None.
      out: the ``.rrd`` file to write.
      floor_height: the floor's height along the rig's up (None: under the people's lowest
        keypoints).
      fps: the clock when neither the poses nor the detections have timestamps.
      spawn: open rerun's viewer on the file afterwards (needs a display).
    """

    poses: str
    rig: RigSource
    out: str
    detections: DetectionsSource | None = None
    floor_height: float | None = None
    fps: float | None = None
    spawn: bool = False
    progress: bool = True


def run_view(config: ViewConfig) -> Path:
    """Writes the ``.rrd`` file (atomically) and returns its path.

    Raises:
      InputError: an ``out`` that is not a ``.rrd`` file, poses whose cameras are not the rig's,
        detections that do not fit the poses (frames, layout).
    """
    if Path(config.out).suffix.lower() != ".rrd":
        raise InputError("the output is a rerun recording: name it FILE.rrd", field="out")
    poses, rig_all = poses_on_rig(config.poses, config.rig)
    rig = rig_all.select(list(poses.cameras))
    detections = None
    if config.detections is not None:
        detections = detections_of(poses, rig_all, config.detections)
    return write_rerun(
        config.out,
        poses,
        rig,
        detections=detections,
        floor_height=config.floor_height,
        fps=config.fps,
        spawn=config.spawn,
        progress=config.progress,
    )
