"""Recordings as compressed numpy archives (``.npz``): the fastest format to load.

Members (letters as in `mvpose_jax.skeletons`: F frames, C cameras, P people, K keypoints, G
ground-truth people)::

    version            ()               int, 1
    layout             ()               str, keypoint layout name (fixes K)
    cameras            (C,)             str, camera names
    xy                 (F, C, P, K, 2)  float32 pixels
    score              (F, C, P, K)     float32 in [0, 1], 0 = missing
    count              (F, C)           int32, skeletons per view (rows >= count are padding)
    identity           (F, C, P)        int32, optional: G index of each detection, -1 unknown
    gt_xyz             (F, G, K, 3)     float32 metres, optional, with the two masks below
    gt_valid           (F, G)           bool
    gt_keypoint_valid  (F, G, K)        bool
    timestamps         (F,)             float64 seconds, optional
    image_names        (F, C)           str, optional
    projected          (F, C, P, K, 2)  float32 pixels, optional

Reading never unpickles (``allow_pickle=False``): an archive with object arrays is refused, so a
file from elsewhere cannot run code. Each member's ``.npy`` header must describe exactly the bytes
the member holds (checked before reading, so a header declaring a huge array allocates nothing).
Every member's dtype, shape and values are checked; any other member is an error (nothing in the
file is silently ignored).
"""

from __future__ import annotations

import math
import os
import zipfile
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mvpose_jax.data.checks import ClippedScores, check_recording
from mvpose_jax.data.files import atomic_open
from mvpose_jax.data.recording import Recording
from mvpose_jax.data.stream import RecordingStream
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import LAYOUTS, Detections, Poses3D, get_layout

VERSION = 1
_REQUIRED = ("version", "layout", "cameras", "xy", "score", "count")
_GT = ("gt_xyz", "gt_valid", "gt_keypoint_valid")
_OPTIONAL = ("identity", *_GT, "timestamps", "image_names", "projected")
_SMALL = ("version", "layout", "cameras")  # the members without a frame axis


def write_npz(recording: Recording, path: str | os.PathLike) -> None:
    """Writes a recording as a compressed ``.npz`` archive, atomically.

    Raises:
      InputError on invalid values in the recording (nothing is written then).
    """
    check_recording(recording, file=path)
    det = recording.detections
    arrays: dict[str, np.ndarray] = {
        "version": np.asarray(VERSION, np.int32),
        "layout": np.asarray(recording.layout, dtype=str),
        "cameras": np.asarray(recording.cameras, dtype=str),
        "xy": np.asarray(det.xy, np.float32),
        "score": np.asarray(det.score, np.float32),
        "count": np.asarray(det.count, np.int32),
    }
    if recording.identity is not None:
        arrays["identity"] = np.asarray(recording.identity, np.int32)
    gt = recording.ground_truth
    if gt is not None:
        arrays["gt_xyz"] = np.asarray(gt.xyz, np.float32)
        arrays["gt_valid"] = np.asarray(gt.valid, bool)
        arrays["gt_keypoint_valid"] = np.asarray(gt.keypoint_valid, bool)
    if recording.timestamps is not None:
        arrays["timestamps"] = np.asarray(recording.timestamps, np.float64)
    if recording.image_names is not None:
        arrays["image_names"] = np.asarray(recording.image_names).astype(str)
    if recording.projected is not None:
        arrays["projected"] = np.asarray(recording.projected, np.float32)
    with atomic_open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def read_npz(path: str | os.PathLike) -> Recording:
    """Reads a recording written by `write_npz` (members in the module docstring).

    Raises:
      InputError naming the file and member (and frame and camera for bad values): a missing,
      empty, truncated or non-zip file, object (pickled) arrays, wrong dtypes or shapes, unknown
      members, non-finite values, scores outside [0, 1.5] (above 1: clipped, with a warning),
      inconsistent counts or identities.
    """
    arrays = _load_members(path)
    _check_members({name: (a.shape, a.dtype) for name, a in arrays.items()}, arrays, path)
    return _recording_of(arrays, path)


class NpzStream(RecordingStream):
    """A ``.npz`` recording read a range of frames at a time (`mvpose_jax.data.stream`).

    Opening reads and checks every member's ``.npy`` header (names, dtypes, shapes, sizes: the
    checks of `read_npz`) and the small members (version, layout, cameras); `read_frames` then
    reads only the rows of the range from each per-frame member, stored or deflated alike (a
    deflated member is decompressed from its start up to the range: read ranges in order). The
    values of a range get `read_npz`'s checks, frames named by their place in the recording. A
    member written in Fortran order (numpy writes one for a Fortran-contiguous array) has no
    contiguous rows: it is read whole when opened.
    """

    def __init__(self, path: str | os.PathLike):
        archive = _open_archive(path)
        try:
            members: dict[str, tuple[zipfile.ZipInfo, tuple, np.dtype, bool, int]] = {}
            for info in archive.infolist():
                name = _member_name(info, path, _REQUIRED + _OPTIONAL, members)
                try:
                    with archive.open(info) as f:
                        shape, fortran, dtype = _check_header(f, info.file_size)
                        members[name] = (info, shape, dtype, fortran, f.tell())
                except InputError as e:
                    raise e.at(file=path, field=name) from None
                except Exception as e:
                    raise _unreadable(e, path, name) from None
            _check_names(members, path)
            small = {name: self._whole(archive, members[name], path, name) for name in _SMALL}
            _check_members({n: (m[1], m[2]) for n, m in members.items()}, small, path)
            cameras = tuple(small["cameras"].tolist())
        except BaseException:
            archive.close()
            raise
        super().__init__(
            path,
            cameras=cameras,
            layout=str(small["layout"]),
            num_frames=members["xy"][1][0],
            streamed=True,
        )
        self._archive = archive
        self._members = members
        self._small = small
        self._open: dict[str, tuple[object, int]] = {}  # name -> (member file, next row)
        # Fortran order: rows are not contiguous in the member's bytes; read those whole.
        self._loaded = {
            name: self._whole(archive, m, path, name)
            for name, m in members.items()
            if name not in _SMALL and m[3] and len(m[1]) > 1
        }

    def read_frames(self, start: int, stop: int) -> Recording:
        start, stop = max(0, start), min(self.num_frames, stop)
        arrays = dict(self._small)
        for name in self._members:
            if name in _SMALL:
                continue
            if name in self._loaded:
                arrays[name] = self._loaded[name][start:stop]
            else:
                arrays[name] = self._rows(name, start, stop)
        return _recording_of(arrays, self.path, first_frame=start, clipped=self.clipped)

    def close(self) -> None:
        for f, _ in self._open.values():
            f.close()
        self._open.clear()
        self._archive.close()
        super().close()

    def _rows(self, name: str, start: int, stop: int) -> np.ndarray:
        """Rows ``start:stop`` of a per-frame member, read from the archive."""
        info, shape, dtype, _, header = self._members[name]
        out = np.empty((stop - start, *shape[1:]), dtype)
        row = math.prod(shape[1:]) * dtype.itemsize
        try:
            f, at = self._open.get(name, (None, -1))
            if f is None:
                f = self._archive.open(info)
                f.seek(header)
                at = 0
            if at != start:  # a deflated member re-reads from its start to go back
                f.seek(header + start * row)
            view = out.reshape(-1).view(np.uint8)
            done = 0
            while done < view.size:
                n = f.readinto(view[done:])
                if not n:
                    raise InputError(
                        f"member ends after {header + start * row + done} of the "
                        f"{info.file_size} bytes its size says"
                    )
                done += n
            self._open[name] = (f, stop)
        except InputError as e:
            raise e.at(file=self.path, field=name) from None
        except Exception as e:
            raise _unreadable(e, self.path, name) from None
        return out

    @staticmethod
    def _whole(archive, member, path, name: str) -> np.ndarray:
        try:
            with archive.open(member[0]) as f:
                return np.lib.format.read_array(f, allow_pickle=False)
        except Exception as e:
            raise _unreadable(e, path, name) from None


def _check_members(
    meta: dict[str, tuple[tuple, np.dtype]], small: dict[str, np.ndarray], path
) -> None:
    """The members' dtypes and shapes (``meta``: name -> (shape, dtype)), and the version and
    layout (``small``: their values), as `read_npz` checks them."""
    err = lambda reason, field: InputError(reason, file=path, field=field)  # noqa: E731

    def need(name: str, kinds: str, ndim: int) -> tuple:
        shape, dtype = meta[name]
        if dtype.kind not in kinds or len(shape) != ndim:
            raise err(
                f"expected a {ndim}-d array of kind {kinds!r}, got {dtype} with shape {shape}",
                name,
            )
        return shape

    need("version", "iu", 0)
    version = small["version"]
    if int(version) != VERSION:
        raise err(
            f"unsupported version {int(version)}; this reader knows version {VERSION}", "version"
        )
    need("layout", "U", 0)
    layout = str(small["layout"])
    if layout not in LAYOUTS:
        raise err(f"unknown keypoint layout {layout!r}; known: {sorted(LAYOUTS)}", "layout")
    K = get_layout(layout).num_keypoints
    F, C, P = need("xy", "f", 5)[:3]
    shapes = {
        "xy": (F, C, P, K, 2),
        "score": (F, C, P, K),
        "count": (F, C),
        "cameras": (C,),
        "identity": (F, C, P),
        "timestamps": (F,),
        "image_names": (F, C),
        "projected": (F, C, P, K, 2),
    }
    if "gt_xyz" in meta:
        G = need("gt_xyz", "f", 4)[1]
        shapes.update(gt_xyz=(F, G, K, 3), gt_valid=(F, G), gt_keypoint_valid=(F, G, K))
    kinds = {
        "xy": "f",
        "score": "f",
        "count": "iu",
        "cameras": "U",
        "identity": "iu",
        "gt_xyz": "f",
        "gt_valid": "b",
        "gt_keypoint_valid": "b",
        "timestamps": "fiu",
        "image_names": "U",
        "projected": "f",
    }
    for name, shape in shapes.items():
        if name in meta:
            need(name, kinds[name], len(shape))
            if tuple(meta[name][0]) != shape:
                raise err(
                    f"expected shape {shape} (layout {layout!r}), got {tuple(meta[name][0])}", name
                )


def _recording_of(
    arrays: dict[str, np.ndarray],
    path,
    *,
    first_frame: int = 0,
    clipped: ClippedScores | None = None,
) -> Recording:
    """The checked `Recording` of members whose shapes `_check_members` accepted (a whole file,
    or a range of its frames starting at ``first_frame``, which errors then count from)."""
    err = lambda reason, field: InputError(reason, file=path, field=field)  # noqa: E731
    try:
        return _values_of(arrays, path, err, clipped)
    except InputError as e:
        if e.frame is None or not first_frame:
            raise
        raise InputError(
            e.reason, file=e.file, frame=e.frame + first_frame, camera=e.camera, field=e.field
        ) from None


def _values_of(arrays, path, err, clipped) -> Recording:
    layout = str(arrays["layout"])
    cameras = tuple(arrays["cameras"].tolist())
    if any(not name for name in cameras) or len(set(cameras)) != len(cameras):
        raise err(f"camera names must be unique and non-empty, got {list(cameras)}", "cameras")
    count = arrays["count"]
    if count.size and (count.min() < 0 or count.max() > np.iinfo(np.int32).max):
        raise err("count must be non-negative int32", "count")
    xy, score = arrays["xy"], arrays["score"]
    with np.errstate(over="ignore", invalid="ignore"):
        det = Detections(
            # Coordinates of missing keypoints are meaningless (NaN, say): zero them as every
            # reader does; a seen keypoint's NaN stays, for the check to report where it is.
            np.where(score[..., None] > 0, xy, 0.0),
            score,
            count.astype(np.int32),
        )
    gt = None
    if "gt_xyz" in arrays:
        kvalid = arrays["gt_keypoint_valid"]
        gt_xyz = np.where(kvalid[..., None], arrays["gt_xyz"], 0.0)
        gt = Poses3D(gt_xyz, arrays["gt_valid"], kvalid)
    identity = arrays.get("identity")
    if identity is not None:
        if identity.size and (identity.min() < -1 or identity.max() > np.iinfo(np.int32).max):
            raise err("identity must be int32 values >= -1", "identity")
        identity = identity.astype(np.int32)
    try:
        rec = Recording(
            detections=det,
            cameras=cameras,
            layout=layout,
            ground_truth=gt,
            identity=identity,
            timestamps=arrays.get("timestamps"),
            image_names=arrays.get("image_names"),
            projected=arrays.get("projected"),
        )
    except InputError as e:
        raise e.at(file=path) from None
    # Values: ranges, finiteness, padding, identities (frame and camera named), then exact dtypes.
    check_recording(rec, file=path, clipped=clipped)
    f32 = lambda a: None if a is None else np.asarray(a, np.float32)  # noqa: E731
    return Recording(
        # Scores in (1, MAX_SCORE] passed the check with a warning; clipped like every reader.
        detections=Detections(f32(det.xy), np.minimum(f32(det.score), 1.0), det.count),
        cameras=cameras,
        layout=layout,
        ground_truth=None if gt is None else Poses3D(f32(gt.xyz), gt.valid, gt.keypoint_valid),
        identity=identity,
        timestamps=None if rec.timestamps is None else np.asarray(rec.timestamps, np.float64),
        image_names=rec.image_names,
        projected=f32(rec.projected),
    )


def load_npz_members(
    path: str | os.PathLike, names: Sequence[str] | None = None
) -> dict[str, np.ndarray]:
    """Every member of a ``.npz`` archive, by name (without ``.npy``), read as untrusted bytes.

    Each member's ``.npy`` header is read first and its declared shape and dtype checked against
    the bytes the member holds, so a header declaring a huge array is refused before anything is
    allocated, and object (pickled) arrays are refused before they are read. The recording reader
    (`read_npz`) and the poses reader (`data.poses.load_poses`) both read through here.

    Args:
      path: the archive.
      names: the member names allowed; any other member is an error. None: any name.
    Raises:
      InputError naming the file (and the member, where one is to blame): a missing, empty,
      truncated or non-zip file, a single ``.npy``, an unknown or repeated member, a header that
      does not describe the member's bytes, object arrays, a member that does not read.
    """
    archive = _open_archive(path)
    out: dict[str, Any] = {}
    with archive:
        for info in archive.infolist():
            name = _member_name(info, path, names, out)
            try:
                with archive.open(info) as f:
                    _check_header(f, info.file_size)
                with archive.open(info) as f:
                    out[name] = np.lib.format.read_array(f, allow_pickle=False)
            except InputError as e:
                raise e.at(file=path, field=name) from None
            except Exception as e:
                raise _unreadable(e, path, name) from None
    return out


def npz_member_shapes(
    path: str | os.PathLike, names: Sequence[str] | None = None
) -> dict[str, tuple[int, ...]]:
    """Each member's shape, from its ``.npy`` header (checked as `load_npz_members` checks it),
    without reading any member's data.

    Args:
      path: the archive.
      names: the member names allowed; any other member is an error. None: any name.
    Raises:
      InputError as `load_npz_members`.
    """
    out: dict[str, tuple[int, ...]] = {}
    with _open_archive(path) as archive:
        for info in archive.infolist():
            name = _member_name(info, path, names, out)
            try:
                with archive.open(info) as f:
                    out[name] = _check_header(f, info.file_size)[0]
            except InputError as e:
                raise e.at(file=path, field=name) from None
            except Exception as e:
                raise _unreadable(e, path, name) from None
    return out


def _load_members(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A recording's members: known names only, the required ones (and ground truth) complete."""
    out = load_npz_members(path, _REQUIRED + _OPTIONAL)
    _check_names(out, path)
    return out


def _check_names(members: Collection[str], path) -> None:
    """The required members are there, and ground truth is whole or absent."""
    for name in _REQUIRED:
        if name not in members:
            raise InputError("missing member", file=path, field=name)
    present = [name for name in _GT if name in members]
    if present and len(present) != len(_GT):
        missing = next(name for name in _GT if name not in members)
        raise InputError(f"ground truth needs all of {list(_GT)}", file=path, field=missing)


def _open_archive(path: str | os.PathLike) -> zipfile.ZipFile:
    """The archive at ``path``, opened (its directory read); InputError when it is none."""
    p = Path(path)
    try:
        size = p.stat().st_size
    except FileNotFoundError:
        raise InputError("no such file", file=path) from None
    except OSError as e:
        raise InputError(f"cannot read ({e.strerror})", file=path) from None
    if p.is_dir():
        raise InputError("is a folder, expected a file", file=path)
    if size == 0:
        raise InputError("file is empty", file=path)
    # The file is untrusted bytes: zipfile and numpy raise many kinds of errors on corrupt input
    # (BadZipFile, zlib.error, EOFError, ValueError, struct.error ...); all of them mean "bad file".
    try:
        return zipfile.ZipFile(p)
    except Exception as e:
        with open(p, "rb") as f:
            magic = f.read(6)
        if magic == b"\x93NUMPY":
            raise InputError("a single .npy array, expected a .npz archive", file=path) from None
        raise InputError(
            f"not a readable .npz archive ({type(e).__name__}: {e})", file=path
        ) from None


def _member_name(
    info: zipfile.ZipInfo, path, names: Sequence[str] | None, seen: Collection[str]
) -> str:
    """A member's name without ``.npy``; refuses unknown (not in ``names``) and repeated ones."""
    name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
    if names is not None and name not in names:
        raise InputError(f"unknown member; members are {list(names)}", file=path, field=name)
    if name in seen:
        raise InputError("member appears twice", file=path, field=name)
    return name


def _unreadable(e: Exception, path, name: str) -> InputError:
    return InputError(f"cannot read member ({type(e).__name__}: {e})", file=path, field=name)


def _check_header(f, member_size: int) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Reads a member's .npy header; its shape and dtype must describe exactly the bytes left.

    Returns:
      (shape, fortran order, dtype); ``f`` is left at the first byte of the data.
    """
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
    else:
        raise InputError(f".npy format version {version} is not supported (1.0 and 2.0 are)")
    if dtype.hasobject:
        raise InputError(
            "object arrays are refused: loading them would unpickle, which can run code"
        )
    declared = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
    held = member_size - f.tell()
    if declared != held:
        raise InputError(
            f"the header declares a {dtype} array of shape {shape} ({declared} bytes), but the "
            f"member holds {held} bytes"
        )
    return shape, fortran, dtype
