"""Pose results for OpenSim and motion-capture tools: TRC, C3D and a tidy CSV.

``mvpose-jax export`` and ``infer --export`` write them; `export_poses` is the library call.

People over time. A pose result's slot ``g`` is a place within one frame, not a person: the same
person may sit in slot 0 in one frame and slot 2 in the next. ``track`` (F, G) says who each
slot is, and the exports are per track. Without ``track`` every slot is taken for a track, with
a `MvposeWarning`, since the files then join different people.

Axes. OpenSim wants Y up, X forward and Z to the right (right-handed). Unless the axes are kept
(``axes="world"``), every point is rotated, ``p_file = R @ p_world`` with R =
`opensim_from_world` (up): Y = up; X = the world axis most orthogonal to up (the first of x, y, z
on a tie), projected onto the floor plane and normalised; Z = X x Y. The origin stays the
world's. For up +Z, R = [[1, 0, 0], [0, 0, 1], [0, -1, 0]] (x, z, -y); for up -Y (CMU Panoptic),
R = diag(1, -1, -1); for up +Y, the identity. The C3D files carry R as ``MVPOSE:ROTATION``.

Units: millimetres (``"mm"``, what OpenSim marker files usually carry) or metres (``"m"``); the
TRC ``Units`` field and C3D ``POINT:UNITS`` say which.

Files (``stem`` is a path without suffix):

* per track (the default, as Pose2Sim writes one file per person and OpenSim scales one model
  per file): ``<stem>_track<id>.trc`` / ``.c3d`` with markers named after the layout's
  keypoints, from the track's first to its last frame (frame numbers and times stay the
  recording's);
* one file: ``<stem>.trc`` / ``.c3d`` with markers ``t<id>_<keypoint>`` over every frame; a track
  absent from a frame leaves its markers missing there;
* CSV, always one file ``<stem>.csv``: ``frame,time,track,keypoint,x,y,z,filled``, one row per
  keypoint with a position (``frame`` counts from 0 as in ``poses.json``, ``filled`` is 1 for a
  keypoint interpolated over a gap, else 0).

Missing keypoints: TRC leaves their X, Y and Z fields empty (the TRC convention; every data row
ends with a tab, as OpenSim writes them, because OpenSim's reader drops a last empty field and
then miscounts the columns); C3D gives them residual -1 (invalid). Filled keypoints: C3D gives
them residual 0, which the C3D format defines as "processed, not the original measured value";
measured keypoints carry the least positive residual (one step, ``|POINT:SCALE|``), as
mvpose-jax has no per-keypoint residual to give. TRC has no such flag: a filled keypoint is an
ordinary marker there.

Timing: the frame rate is ``fps`` or, without it, 1 / the median step of the timestamps; times
are seconds from the first frame (``fps`` given: frame / fps). C3D assumes a constant rate, so
uneven timestamps are warned about. TRC and C3D number frames from 1.

C3D is written with ``c3d`` (py-c3d): pure Python, so it installs wherever mvpose-jax does (the
C++ ``ezc3d`` has no wheel for Linux on ARM), and its residual/camera word follows the C3D
manual's layout (ezc3d's float-format residuals do not: pyomeca/ezc3d#386). Points are stored
as floats (POINT:SCALE negative, its size from the largest coordinate as the manual asks), more
than 255 labels go to POINT:LABELS2, LABELS3, ... (the C3D convention; a parameter dimension
is one byte).

Every file is written atomically (temporary file, then rename).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from mvpose_jax.data.files import atomic_open
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.progress import progress_bar
from mvpose_jax.skeletons import get_layout

if TYPE_CHECKING:
    from mvpose_jax.data.poses import PoseResults

EXPORT_FORMATS = ("trc", "c3d", "csv")
# Output units: name -> per metre.
UNITS = {"mm": 1000.0, "m": 1.0}
# Decimals of a coordinate: 0.1 micrometre either way (float32 metres hold about 0.5 um at 5 m).
_DECIMALS = {"mm": 4, "m": 7}
# Rows formatted at a time (TRC frames, CSV keypoints): bounds the memory of the text.
_ROWS_PER_BLOCK = 4096
# The C3D labels and descriptions parameters hold at most 255 entries each (one-byte dimension).
_C3D_LABELS_PER_PARAMETER = 255


@dataclasses.dataclass(frozen=True)
class ExportConfig:
    """How `export_poses` writes (see the module docstring for the conventions).

    Attributes:
      formats: some of ``"trc"``, ``"c3d"``, ``"csv"``.
      units: ``"mm"`` or ``"m"``.
      per_track: one TRC/C3D file per track; False: one file with every track (CSV is always
        one file).
      fps: frames per second; None: from the poses' timestamps (an error without them).
      axes: ``"opensim"`` (Y up, needs ``up``) or ``"world"`` (the rig's axes, unrotated).
      up: (3,) the world's up direction (``cameras.up_vector(rig)``), for ``axes="opensim"``.
    """

    formats: tuple[str, ...] = ("trc",)
    units: str = "mm"
    per_track: bool = True
    fps: float | None = None
    axes: str = "opensim"
    up: tuple[float, float, float] | None = None


class TrackedKeypoints(NamedTuple):
    """Keypoints per track instead of per frame slot. T tracks, F frames, K keypoints."""

    ids: np.ndarray  # (T,) int64, the track ids, ascending
    xyz: np.ndarray  # (T, F, K, 3) float64 metres, world axes; 0 where not present
    present: np.ndarray  # (T, F, K) bool: the keypoint has a position
    in_frame: np.ndarray  # (T, F) bool: the track is in the frame
    filled: np.ndarray  # (T, F, K) bool: interpolated over a gap (a subset of present)


def opensim_from_world(up: Sequence[float] | np.ndarray) -> np.ndarray:
    """The rotation from the world's axes to OpenSim's (Y up), see the module docstring.

    Args:
      up: (3,) the world's up direction (any length).
    Returns:
      (3, 3) rotation R (det +1), ``p_opensim = R @ p_world``; its rows are OpenSim's X, Y, Z
      in world coordinates, ``R[1]`` = up / |up|.
    Raises:
      InputError when ``up`` is zero or not finite.
    """
    up = np.asarray(up, np.float64).reshape(3)
    norm = float(np.linalg.norm(up))
    if not np.isfinite(norm) or norm < 1e-9:
        raise InputError(f"up must be a non-zero finite vector, got {up.tolist()}", field="up")
    y = up / norm
    # Rounded so that an up read from a file as (0, -1, 1e-17) ties like (0, -1, 0).
    axis = int(np.argmin(np.round(np.abs(y), 9)))
    x = np.eye(3)[axis] - y[axis] * y
    x /= np.linalg.norm(x)
    return np.stack([x, y, np.cross(x, y)])


def tracked_keypoints(results: PoseResults) -> TrackedKeypoints:
    """Regroups the per-frame slots of ``results`` by track (``results.track``).

    Without ``track`` each slot is taken for a track, with a `MvposeWarning`; people with
    track -1 are left out, with a `MvposeWarning` saying how many.

    Raises:
      InputError naming the frame when one track holds two slots of a frame.
    """
    valid = np.asarray(results.poses.valid, bool)
    F, G = valid.shape
    if results.track is None:
        warnings.warn(
            "the poses have no tracks, so each per-frame slot is exported as a track; a slot "
            "is not the same person over time (track the poses for one file per person)",
            MvposeWarning,
            stacklevel=2,
        )
        track = np.where(valid, np.arange(G)[None, :], -1)
    else:
        track = np.asarray(results.track, np.int64)
    untracked = int((valid & (track < 0)).sum())
    if untracked:
        warnings.warn(
            f"{untracked} people (frame slots) have no track (-1) and are not exported",
            MvposeWarning,
            stacklevel=2,
        )
    tracked = valid & (track >= 0)
    ids = np.unique(track[tracked])
    K = np.shape(results.poses.keypoint_valid)[2]
    if len(ids) == 0:
        return TrackedKeypoints(
            ids,
            np.zeros((0, F, K, 3)),
            np.zeros((0, F, K), bool),
            np.zeros((0, F), bool),
            np.zeros((0, F, K), bool),
        )
    # (T, F, G): does slot g hold track t in frame f?
    holds = tracked[None] & (track[None] == ids[:, None, None])
    twice = holds.sum(axis=-1) > 1
    if twice.any():
        t, f = np.argwhere(twice)[0]
        raise InputError(
            f"track {ids[t]} is in two slots of one frame", frame=int(f), field="track"
        )
    in_frame = holds.any(axis=-1)  # (T, F)
    slot = holds.argmax(axis=-1)  # (T, F), 0 where absent (masked below)
    frames = np.arange(F)[None, :]
    present = np.asarray(results.poses.keypoint_valid, bool)[frames, slot] & in_frame[..., None]
    xyz = np.asarray(results.poses.xyz, np.float64)[frames, slot]  # (T, F, K, 3)
    xyz = np.where(present[..., None], xyz, 0.0)
    filled = (
        np.zeros_like(present)
        if results.filled is None
        else np.asarray(results.filled, bool)[frames, slot] & present
    )
    return TrackedKeypoints(ids, xyz, present, in_frame, filled)


def frame_times(
    timestamps: np.ndarray | None, num_frames: int, fps: float | None = None
) -> tuple[float, np.ndarray]:
    """The frame rate and every frame's time.

    Args:
      timestamps: (F,) seconds, or None.
      num_frames: F.
      fps: frames per second; given, it replaces the timestamps.
    Returns:
      (rate in Hz, (F,) float64 seconds from the first frame).
    Raises:
      InputError when neither gives a rate (no timestamps, one frame, or not increasing).
    """
    if fps is not None:
        if not (np.isfinite(fps) and fps > 0):
            raise InputError(
                f"must be a positive number of frames per second, got {fps}", field="fps"
            )
        return float(fps), np.arange(num_frames) / float(fps)
    if timestamps is None:
        raise InputError(
            "the poses have no timestamps, so the frame rate is unknown: give it (--fps)",
            field="fps",
        )
    ts = np.asarray(timestamps, np.float64)
    if len(ts) < 2:
        raise InputError(
            f"{len(ts)} timestamp(s) give no frame rate: give it (--fps)", field="timestamps"
        )
    steps = np.diff(ts)
    step = float(np.median(steps))
    if not step > 0:
        raise InputError(
            "timestamps do not increase, so they give no frame rate: give it (--fps)",
            field="timestamps",
        )
    uneven = int((np.abs(steps - step) > 0.5 * step).sum())
    if uneven:
        warnings.warn(
            f"{uneven} of {len(steps)} timestamp steps differ from the median step "
            f"({step:.6g} s) by more than half: C3D assumes a constant rate "
            f"({1 / step:.6g} Hz), so there its frames are not at their timestamps (TRC's "
            "Time column and the CSV keep them)",
            MvposeWarning,
            stacklevel=2,
        )
    return 1.0 / step, ts - ts[0]


def export_paths(stem: str | Path, config: ExportConfig, track_ids: Sequence[int]) -> list[Path]:
    """The files `export_poses` writes for these tracks, in writing order."""
    stem = Path(stem)
    paths = []
    for fmt in config.formats:
        if fmt != "csv" and config.per_track:
            paths += [stem.with_name(f"{stem.name}_track{int(t)}.{fmt}") for t in track_ids]
        else:
            paths.append(stem.with_name(f"{stem.name}.{fmt}"))
    return paths


def export_poses(
    results: PoseResults, stem: str | Path, config: ExportConfig, *, progress: bool = False
) -> list[Path]:
    """Writes ``results`` as TRC, C3D and/or CSV (see the module docstring); returns the paths.

    Everything is checked before the first file is written.

    Args:
      results: the poses (``track`` says who is who over time).
      stem: output path without suffix: ``out/poses`` gives ``out/poses_track3.trc`` ...
      config: formats, units, files, rate and axes.
      progress: show a progress bar over the files.
    Raises:
      InputError for an unknown format or unit, no frame rate, or OpenSim axes without ``up``.
    """
    unknown = [f for f in config.formats if f not in EXPORT_FORMATS]
    if unknown or not config.formats:
        raise InputError(
            f"unknown export format {unknown[0] if unknown else '(none)'!r}; choose from "
            + ", ".join(EXPORT_FORMATS),
            field="format",
        )
    if config.units not in UNITS:
        raise InputError(f"unknown unit {config.units!r}; choose from mm, m", field="units")
    if config.axes == "opensim":
        if config.up is None:
            raise InputError("the OpenSim axes need the world's up direction", field="up")
        rotation = opensim_from_world(config.up)
    elif config.axes == "world":
        rotation = None
    else:
        raise InputError(f"unknown axes {config.axes!r}; choose from opensim, world", field="axes")
    F = len(results.poses.valid)
    rate, times = frame_times(results.timestamps, F, config.fps)
    tracks = tracked_keypoints(results)
    if len(tracks.ids) == 0:
        warnings.warn(
            "no tracked person in any frame: nothing exported", MvposeWarning, stacklevel=2
        )
        return []
    # (T, F, K, 3) in the file's axes and units.
    xyz = tracks.xyz if rotation is None else tracks.xyz @ rotation.T
    xyz = xyz * UNITS[config.units]
    keypoints = get_layout(results.layout).keypoints

    series = []  # one per TRC/C3D file of a format, in `export_paths` order
    if config.per_track:
        for t, track_id in enumerate(tracks.ids):
            frames = np.nonzero(tracks.in_frame[t])[0]
            span = slice(frames[0], frames[-1] + 1)  # the track's first to last frame
            series.append(
                _Series(
                    xyz[t, span],
                    tracks.present[t, span],
                    tracks.filled[t, span],
                    list(keypoints),
                    [f"track {track_id}: {k}" for k in keypoints],
                    times[span],
                    int(span.start) + 1,
                )
            )
    else:
        T, _, K = tracks.present.shape
        series.append(
            _Series(
                # (F, T * K, ...): the markers of the first track, then the second ...
                xyz.transpose(1, 0, 2, 3).reshape(F, T * K, 3),
                tracks.present.transpose(1, 0, 2).reshape(F, T * K),
                tracks.filled.transpose(1, 0, 2).reshape(F, T * K),
                [f"t{i}_{k}" for i in tracks.ids for k in keypoints],
                [f"track {i}: {k}" for i in tracks.ids for k in keypoints],
                times,
                1,
            )
        )
    jobs = []  # (format, series or None for the CSV)
    for fmt in config.formats:
        jobs += [(fmt, None)] if fmt == "csv" else [(fmt, s) for s in series]
    paths = export_paths(stem, config, tracks.ids)
    for path, (fmt, s) in progress_bar(
        list(zip(paths, jobs, strict=True)), desc="export", unit="file", disable=not progress
    ):
        if fmt == "trc":
            write_trc(
                path,
                xyz=s.xyz,
                present=s.present,
                names=s.names,
                rate=rate,
                times=s.times,
                first_frame=s.first_frame,
                units=config.units,
            )
        elif fmt == "c3d":
            write_c3d(
                path,
                xyz=s.xyz,
                present=s.present,
                filled=s.filled,
                names=s.names,
                descriptions=s.descriptions,
                rate=rate,
                first_frame=s.first_frame,
                units=config.units,
                rotation=rotation,
                layout=results.layout,
            )
        else:
            write_csv(path, **_csv_rows(tracks, xyz, times, keypoints), units=config.units)
    return paths


def write_trc(
    path: str | Path,
    *,
    xyz: np.ndarray,
    present: np.ndarray,
    names: Sequence[str],
    rate: float,
    times: np.ndarray,
    first_frame: int,
    units: str,
) -> None:
    """Writes one TRC file (PathFileType 4, tab-separated) atomically.

    Args:
      xyz: (N, M, 3) marker positions in ``units``, N frames, M markers.
      present: (N, M) bool; absent markers get empty X/Y/Z fields.
      names: M marker names.
      rate: frames per second (DataRate, CameraRate, OrigDataRate).
      times: (N,) seconds (the Time column).
      first_frame: the first row's Frame# (numbering from 1).
      units: ``"mm"`` or ``"m"`` (the Units field).
    """
    path = Path(path)
    N, M = np.shape(present)
    rate_text = f"{rate:.10g}"
    header = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame"
        "\tOrigNumFrames",
        f"{rate_text}\t{rate_text}\t{N}\t{M}\t{units}\t{rate_text}\t{first_frame}\t{N}",
        "Frame#\tTime\t" + "".join(f"{n}\t\t\t" for n in names),
        "\t\t" + "".join(f"X{m}\tY{m}\tZ{m}\t" for m in range(1, M + 1)),
        "",
    ]
    xyz = np.asarray(xyz, np.float64).reshape(N, 3 * M)
    shown = np.repeat(np.asarray(present, bool), 3, axis=1)  # (N, 3M)
    with atomic_open(path, "w", newline="\n") as f:
        f.write("\n".join(header) + "\n")
        for start in range(0, N, _ROWS_PER_BLOCK):  # blocks: the text of hours stays small
            block = slice(start, start + _ROWS_PER_BLOCK)
            # (rows, 3M) text, empty where the marker is absent.
            fields = np.char.mod(f"%.{_DECIMALS[units]}f", xyz[block])
            fields = np.where(shown[block], fields, "").tolist()
            for n, t, row in zip(range(start, N), times[block], fields, strict=False):
                # The trailing tab keeps a row whose last marker is absent readable by OpenSim.
                f.write(f"{first_frame + n}\t{t:.6f}\t" + "".join(v + "\t" for v in row) + "\n")


def write_c3d(
    path: str | Path,
    *,
    xyz: np.ndarray,
    present: np.ndarray,
    filled: np.ndarray,
    names: Sequence[str],
    descriptions: Sequence[str] | None = None,
    rate: float,
    first_frame: int,
    units: str,
    rotation: np.ndarray | None = None,
    layout: str | None = None,
) -> None:
    """Writes one C3D file (Intel, float points, no analog channels) atomically.

    Args:
      xyz: (N, M, 3) marker positions in ``units``.
      present: (N, M) bool; absent markers get residual -1 (invalid).
      filled: (N, M) bool; filled markers get residual 0 (processed, not measured).
      names: M labels (POINT:LABELS, LABELS2 ... 255 each).
      descriptions: M descriptions (POINT:DESCRIPTIONS ...); default empty.
      rate: frames per second (POINT:RATE).
      first_frame: the first frame's number (header and TRIAL:ACTUAL_START_FIELD).
      units: ``"mm"`` or ``"m"`` (POINT:UNITS).
      rotation: (3, 3) ``p_file = rotation @ p_world``, kept as MVPOSE:ROTATION when given;
        then the axes are OpenSim's (POINT:X_SCREEN +X, Y_SCREEN +Y: Y up).
      layout: the keypoint layout, kept as MVPOSE:LAYOUT when given.
    """
    import c3d

    xyz = np.asarray(xyz, np.float64)
    present = np.asarray(present, bool)
    N, M = present.shape
    largest = float(np.abs(xyz[present]).max(initial=0.0))
    # Float storage (negative scale); its size is what an integer file would need, as the
    # C3D manual asks, and sets the residual's unit.
    scale = max(largest, 1.0) / 32000.0
    writer = c3d.Writer(point_rate=float(rate), point_scale=-scale, point_units=units)
    point = writer.point_group
    descriptions = list(descriptions) if descriptions is not None else [""] * M
    for i, start in enumerate(range(0, max(M, 1), _C3D_LABELS_PER_PARAMETER)):
        suffix = "" if i == 0 else str(i + 1)
        for name, values, what in (
            ("LABELS", names, "Point labels"),
            ("DESCRIPTIONS", descriptions, "Point descriptions"),
        ):
            chunk = list(values[start : start + _C3D_LABELS_PER_PARAMETER]) or [""]
            width = max(1, *(len(v) for v in chunk))
            point.add_str(
                name + suffix, what, "".join(v.ljust(width) for v in chunk), width, len(chunk)
            )
    if rotation is not None:
        point.set_str("X_SCREEN", "Horizontal axis of the default view", "+X", 2)
        point.set_str("Y_SCREEN", "Vertical axis of the default view", "+Y", 2)
    software = writer.get_create("MANUFACTURER")
    software.add_str("SOFTWARE", "Software that wrote this file", "mvpose-jax", len("mvpose-jax"))
    ours = writer.get_create("MVPOSE")
    if rotation is not None:
        # C3D arrays are column-major: element (i, j) at i + 3 j.
        ours.add_param(
            "ROTATION",
            desc="p_file = ROTATION p_world (metres of the calibration's world)",
            bytes_per_element=4,
            bytes=np.asarray(rotation, "<f4").T.tobytes(),
            dimensions=[3, 3],
        )
    if layout is not None:
        ours.add_str("LAYOUT", "Keypoint layout of the markers", layout, len(layout))
    # (N, M, 5): x, y, z, residual, camera mask; residual -1 absent, 0 filled, one step measured.
    points = np.zeros((N, M, 5), np.float32)
    points[..., :3] = np.where(present[..., None], xyz, 0.0)
    points[..., 3] = np.where(present, np.where(np.asarray(filled, bool), 0.0, scale), -1.0)
    no_analog = np.zeros((0, 0), np.float32)
    writer.add_frames([(points[n], no_analog) for n in range(N)])
    writer.set_start_frame(int(first_frame))
    with atomic_open(path, "wb") as f, warnings.catch_warnings():
        # py-c3d warns on every file without analog channels, which is what we mean to write.
        warnings.filterwarnings("ignore", "No analog data found in file", UserWarning)
        writer.write(f)


def write_csv(
    path: str | Path,
    *,
    frame: np.ndarray,
    time: np.ndarray,
    track: np.ndarray,
    keypoint: np.ndarray,
    xyz: np.ndarray,
    filled: np.ndarray,
    units: str,
) -> None:
    """Writes the tidy CSV atomically: ``frame,time,track,keypoint,x,y,z,filled``, one row each.

    Args:
      frame, time, track, keypoint: (R,) the rows' frame index, seconds, track id, keypoint name.
      xyz: (R, 3) in ``units``.
      filled: (R,) bool.
    """
    xyz = np.asarray(xyz, np.float64)
    with atomic_open(path, "w", newline="\n") as f:
        f.write("frame,time,track,keypoint,x,y,z,filled\n")
        for start in range(0, len(frame), _ROWS_PER_BLOCK):
            block = slice(start, start + _ROWS_PER_BLOCK)
            rows = zip(
                frame[block].tolist(),
                np.char.mod("%.6f", np.asarray(time[block], np.float64)).tolist(),
                track[block].tolist(),
                keypoint[block].tolist(),
                np.char.mod(f"%.{_DECIMALS[units]}f", xyz[block]).tolist(),
                filled[block].astype(int).tolist(),
                strict=True,
            )
            f.writelines(
                f"{fr},{t},{tr},{k},{x},{y},{z},{fl}\n" for fr, t, tr, k, (x, y, z), fl in rows
            )


class _Series(NamedTuple):
    """The markers of one TRC/C3D file. N frames, M markers."""

    xyz: np.ndarray  # (N, M, 3) in the file's axes and units
    present: np.ndarray  # (N, M) bool
    filled: np.ndarray  # (N, M) bool
    names: list[str]  # M marker names
    descriptions: list[str]  # M
    times: np.ndarray  # (N,) seconds
    first_frame: int  # the first frame's number, from 1


def _csv_rows(tracks: TrackedKeypoints, xyz: np.ndarray, times: np.ndarray, keypoints) -> dict:
    """The CSV rows in frame, track, keypoint order: every keypoint with a position."""
    # xyz, tracks.*: (T, F, K, ...) -> frame-major so the rows come out sorted by frame.
    f, t, k = np.nonzero(tracks.present.transpose(1, 0, 2))
    return dict(
        frame=f,
        time=times[f],
        track=tracks.ids[t],
        keypoint=np.asarray(keypoints)[k],
        xyz=xyz[t, f, k],
        filled=tracks.filled[t, f, k],
    )
