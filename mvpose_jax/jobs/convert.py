"""A recording converted between the formats the tools read (native, original, npz, OpenPose)."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple


@dataclasses.dataclass(frozen=True)
class ConvertConfig:
    """Attributes:
    detections: the recording to convert (any readable format).
    out: output file (a folder for the OpenPose format).
    format: "native", "original", "npz" or "openpose" (None: npz for a .npz ``out``, else native).
    layout: keypoint layout to write (None: the recording's).
    cameras: write only these cameras, in this order (None: all).
    missing_frames, source_layout: how an OpenPose folder is read.
    """

    detections: str
    out: str
    format: str | None = None
    layout: str | None = None
    cameras: tuple[str, ...] | None = None
    missing_frames: str | None = None
    source_layout: str | None = None


class Converted(NamedTuple):
    """What was written: frames, camera names and keypoint layout."""

    frames: int
    cameras: tuple[str, ...]
    layout: str


def convert(config: ConvertConfig) -> Converted:
    """Reads the recording and writes it in the format asked for."""
    from mvpose_jax.data import load_recording, save_recording, select_cameras
    from mvpose_jax.data.files import check_writable

    check_writable(config.out, folder=config.format == "openpose")
    kwargs = {"missing_frames": config.missing_frames} if config.missing_frames else {}
    if config.source_layout:
        kwargs["source_layout"] = config.source_layout
    rec = load_recording(config.detections, layout=config.layout, **kwargs)
    if config.cameras:
        rec = select_cameras(rec, list(config.cameras), file=config.detections)
    save_recording(rec, config.out, format=config.format)
    return Converted(rec.num_frames, tuple(rec.cameras), rec.layout)
