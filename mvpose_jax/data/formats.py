"""Detection recordings on disk: one entry point per direction (`load_recording`, `save_recording`).

Formats (each module documents its schema):
  * ``native`` (`mvpose_jax.data.native`): the project's JSON, ``{"format": "mvpose-jax.detections",
    "frames": [...]}``; identities, ground truth, projections and the calibration travel with it.
  * ``original`` (`mvpose_jax.data.original`): the original repository's dataset JSON, a list of
    frames, so its users can bring their recordings unchanged.
  * ``npz`` (`mvpose_jax.data.npz`): the `Recording` arrays, compressed; the fastest to load.
  * ``openpose`` (`mvpose_jax.data.openpose`): a FOLDER with one subfolder per camera, each
    holding one OpenPose JSON file per frame (``{"people": [{"pose_keypoints_2d": [...]}]}``), as
    OpenPose, Pose2Sim and many detectors write; detections only.

`open_recording` opens a recording to be read a range of frames at a time
(`mvpose_jax.data.stream`): npz files and OpenPose folders are then read range by range, the JSON
formats are loaded whole (one JSON document each).

`load_recording` picks the format from the path: a folder is OpenPose, a ``.npz`` suffix npz, and
for JSON the content decides (an object with ``"frames"`` is native, a list is original);
`save_recording` picks it from the suffix (``.npz``; anything else is native JSON) unless
``format=`` says otherwise.

The checks every format shares (keypoint values, padding, JSON) are in `mvpose_jax.data.checks`;
the readers import them from there, so this module can import the readers.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mvpose_jax.data import native, npz, openpose, original
from mvpose_jax.data.checks import load_json
from mvpose_jax.data.recording import Recording, convert_layout, select_cameras
from mvpose_jax.data.stream import InMemoryStream, RecordingStream
from mvpose_jax.errors import InputError

FORMATS = ("native", "original", "npz", "openpose")


def load_recording(
    path: str | os.PathLike,
    *,
    layout: str | None = None,
    cameras: Sequence[str] | None = None,
    rig: Any = None,
    source_layout: str | None = None,
    missing_frames: str = "error",
    camera_map: Mapping[str, str] | None = None,
) -> Recording:
    """Loads a recording in any supported format.

    Args:
      path: a ``.npz`` file, a JSON file in the native or the original format, or a folder of
        OpenPose JSON files (one subfolder per camera).
      layout: keypoint layout. The original format does not record it (default ``"coco18"``); for
        the others, a layout different from the file's converts the keypoints
        (`mvpose_jax.skeletons.convert_keypoints`: derived keypoints such as the neck are built,
        keypoints the file lacks are missing). OpenPose folders are converted to ``coco18`` when
        it is not given.
      cameras: optional camera names to keep, in this order (the camera axis follows it).
      rig: optional `Rig`: every camera of the recording must be one of its cameras (an OpenPose
        folder's cameras also follow its order when ``cameras`` is not given).
      source_layout: OpenPose folders only: the files' layout, instead of detecting it from the
        keypoint count (`mvpose_jax.data.openpose`).
      missing_frames: OpenPose folders only: ``"error"`` or ``"empty"``, what a frame missing in
        some cameras means (`mvpose_jax.data.openpose.read_openpose`).
      camera_map: OpenPose folders only: folder name -> camera name (see `read_openpose`, which
        also strips suffixes such as ``_json`` when a rig is given).
    Returns:
      The `Recording`.
    Raises:
      InputError naming the file, frame, camera and field of the first problem.
    """
    path = Path(path)
    if path.is_dir():
        return openpose.read_openpose(
            path,
            layout=layout or "coco18",
            source_layout=source_layout,
            cameras=cameras,
            rig=rig,
            missing_frames=missing_frames,
            camera_map=camera_map,
        )
    _only_for_folders(path, source_layout, missing_frames, camera_map)
    rec = _load_file(path, layout=layout, cameras=cameras)
    _check_rig_cameras(rec.cameras, rig, path)
    return rec


def open_recording(
    path: str | os.PathLike,
    *,
    layout: str | None = None,
    cameras: Sequence[str] | None = None,
    rig: Any = None,
    source_layout: str | None = None,
    missing_frames: str = "error",
    camera_map: Mapping[str, str] | None = None,
) -> RecordingStream:
    """Opens a recording in any supported format to be read a range of frames at a time.

    Arguments as `load_recording`; camera selection and layout conversion apply to every range,
    and a range holds what `load_recording` would hold for those frames (its person axis may be
    shorter: the most people in a view of the range). ``.npz`` files and OpenPose folders are
    read range by range (memory bounded by the range); native and original JSON are one JSON
    document each and are loaded whole (memory grows with the recording).

    Returns:
      A `RecordingStream` (close it, or use it in a ``with`` block).
    Raises:
      InputError naming the file, frame, camera and field of the first problem; problems in the
      values of a frame are found when its range is read.
    """
    path = Path(path)
    if path.is_dir():
        return openpose.OpenPoseStream(
            path,
            layout=layout or "coco18",
            source_layout=source_layout,
            cameras=cameras,
            rig=rig,
            missing_frames=missing_frames,
            camera_map=camera_map,
        )
    if path.suffix.lower() != ".npz":
        return InMemoryStream(
            load_recording(
                path,
                layout=layout,
                cameras=cameras,
                rig=rig,
                source_layout=source_layout,
                missing_frames=missing_frames,
                camera_map=camera_map,
            ),
            path,
        )
    _only_for_folders(path, source_layout, missing_frames, camera_map)
    stream = npz.NpzStream(path)
    try:
        if cameras is not None:
            # Checked as select_cameras checks them, before any frame is read.
            select_cameras(_empty_like(stream), cameras, file=path)
        _check_rig_cameras(tuple(cameras) if cameras is not None else stream.cameras, rig, path)
    except BaseException:
        stream.close()
        raise
    return _EditedStream(stream, cameras=cameras, layout=layout)


class _EditedStream(RecordingStream):
    """A stream with `select_cameras` and `convert_layout` applied to every range."""

    def __init__(self, inner: RecordingStream, *, cameras, layout):
        super().__init__(
            inner.path,
            cameras=tuple(cameras) if cameras is not None else inner.cameras,
            layout=layout or inner.layout,
            num_frames=inner.num_frames,
            streamed=inner.streamed,
        )
        self.inner = inner
        self._select = None if cameras is None else [str(c) for c in cameras]

    def read_frames(self, start: int, stop: int) -> Recording:
        rec = self.inner.read_frames(start, stop)
        if self._select is not None:
            rec = select_cameras(rec, self._select, file=self.path)
        if rec.layout != self.layout:
            rec = convert_layout(rec, self.layout)
        return rec

    def report(self):
        return self.inner.report()

    def finish(self) -> None:
        self.inner.finish()

    def close(self) -> None:
        self.inner.close()


def _empty_like(stream: RecordingStream) -> Recording:
    from mvpose_jax.skeletons import Detections, get_layout

    K = get_layout(stream.layout).num_keypoints
    C = len(stream.cameras)
    return Recording(
        detections=Detections(
            np.zeros((0, C, 1, K, 2), np.float32),
            np.zeros((0, C, 1, K), np.float32),
            np.zeros((0, C), np.int32),
        ),
        cameras=stream.cameras,
        layout=stream.layout,
    )


def _only_for_folders(path: Path, source_layout, missing_frames, camera_map) -> None:
    for name, value, default in (
        ("source_layout", source_layout, None),
        ("missing_frames", missing_frames, "error"),
        ("camera_map", camera_map or None, None),
    ):
        if value != default:
            raise InputError(
                f"{name} applies to OpenPose folders only; this is a file", file=path, field=name
            )


def _check_rig_cameras(cameras: Sequence[str], rig: Any, path: Path) -> None:
    if rig is None:
        return
    unknown = [name for name in cameras if name not in rig.names]
    if unknown:
        raise InputError(
            f"cameras {unknown} are not cameras of the rig. Recording: {list(cameras)}; "
            f"rig: {list(rig.names)}",
            file=path,
            camera=unknown[0],
            field="cameras",
        )


def _load_file(path: Path, *, layout: str | None, cameras: Sequence[str] | None) -> Recording:
    """`load_recording` for the single-file formats."""
    if path.suffix.lower() == ".npz":
        rec = npz.read_npz(path)
    else:
        data = load_json(path)
        if isinstance(data, dict) and "frames" in data:
            rec = native.native_from_json(data, file=path)
        elif isinstance(data, list):
            return original.original_from_json(
                data, file=path, layout=layout or "coco18", cameras=cameras
            )
        else:
            raise InputError(
                "not a detections file: expected a JSON object with 'frames' (native format) or a "
                "JSON list of frames (original format)",
                file=path,
            )
    if cameras is not None:
        rec = select_cameras(rec, cameras, file=path)
    if layout is not None and layout != rec.layout:
        rec = convert_layout(rec, layout)
    return rec


def save_recording(
    recording: Recording,
    path: str | os.PathLike,
    *,
    rig: Any = None,
    format: str | None = None,
) -> None:
    """Writes a recording atomically (an OpenPose folder: each of its files atomically).

    Args:
      recording: the `Recording` to write.
      path: output file (the root folder for ``format="openpose"``).
      rig: optional `Rig` to embed (native format only; the others have no place for it).
      format: ``"native"``, ``"original"``, ``"npz"`` or ``"openpose"`` (``path`` is then a
        folder, see `mvpose_jax.data.openpose.save_openpose`); default ``"npz"`` for a ``.npz``
        suffix and ``"native"`` otherwise.
    Raises:
      InputError: an unknown format, a rig for a format that cannot hold it, or invalid values in
        the recording (nothing is written then).
    """
    if format is None:
        format = "npz" if Path(path).suffix.lower() == ".npz" else "native"
    if format not in FORMATS:
        raise InputError(f"unknown format {format!r}; formats: {list(FORMATS)}", field="format")
    if rig is not None and format != "native":
        # Dropping the calibration silently would lose data the caller asked to keep.
        raise InputError(
            f"the {format} format cannot hold a calibration; save it with save_rig or use the "
            "native format",
            file=path,
            field="rig",
        )
    if format == "native":
        native.write_native(recording, path, rig=rig)
    elif format == "original":
        original.write_original(recording, path)
    elif format == "openpose":
        openpose.save_openpose(recording, path)
    else:
        npz.write_npz(recording, path)
