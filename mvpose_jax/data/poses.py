"""3D pose results on disk: what ``mvpose-jax infer`` writes and ``evaluate``/``render`` read.

Two files with the same content:

* ``poses.npz``: the arrays, for programs: ``xyz`` (F, G, K, 3) float32 metres, ``valid`` (F, G),
  ``keypoint_valid`` (F, G, K), ``confidence`` (F, G), ``members`` (F, G, C) int32 (each person's
  skeleton index in each camera of ``cameras``, -1 none), ``identity`` (F, C, P) int32 (each
  detected skeleton's person, -1 none), ``cameras`` (C,) str, ``layout`` () str; optional
  ``timestamps`` (F,), ``track`` (F, G) int32 (each person's identity over time, -1 none) and
  ``filled`` (F, G, K) bool (keypoints interpolated over a gap, not measured). Read without pickle, each member's header checked against its bytes
  (`data.npz.load_npz_members`).
* ``poses.json``, for people and other tools::

    {"format": "mvpose-jax.poses", "version": 1, "units": "metres", "layout": "coco18",
     "keypoints": ["nose", ...], "cameras": ["cam0", ...],
     "frames": [{"frame": 0, "timestamp": 0.0,            # timestamp only when known
                 "people": [{"person": 0, "confidence": 0.91,
                             "track": 4,                              # only when tracked
                             "keypoints": [[x, y, z] or null, ...],   # null: not produced
                             "filled": [3, 4],                        # only when some were
                             "skeletons": {"cam0": 2, "cam1": 0}}]}]}  # the detections used

``person`` is a slot within one frame; ``track`` is the same person across frames (tracking).
``filled`` lists the keypoints interpolated over a gap rather than reconstructed from detections.

Partial results (an interrupted ``infer``) cover the first F frames of a longer recording: the
JSON then has ``"partial": true, "frames_total": N`` before ``"frames"``, the npz a member
``frames_total`` () int64, and `PoseResults.frames_total` is N (None when complete).

Both are written atomically (temporary file, then rename). `save_poses` writes results held in
memory; `assemble_poses` writes them from chunk files (`save_poses_chunk`), one chunk in memory at
a time, so a recording of any length is written in bounded memory.
"""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from mvpose_jax.data.files import atomic_open, read_json
from mvpose_jax.data.npz import load_npz_members, npz_member_shapes
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Poses3D, get_layout

FORMAT = "mvpose-jax.poses"


@dataclasses.dataclass(frozen=True)
class PoseResults:
    """People in 3D over F frames and the detections each came from (see the module docstring).

    ``frames_total``: None for complete results; for partial ones (an interrupted run), the
    recording's frame count N, of which these are the first F frames.
    """

    poses: Poses3D
    confidence: np.ndarray
    members: np.ndarray
    identity: np.ndarray
    cameras: tuple[str, ...]
    layout: str
    timestamps: np.ndarray | None = None
    track: np.ndarray | None = None
    filled: np.ndarray | None = None
    frames_total: int | None = None

    @property
    def partial(self) -> bool:
        """Whether these are the first frames of a longer recording (an interrupted run)."""
        return self.frames_total is not None

    def __post_init__(self):
        F, G, K = np.shape(self.poses.keypoint_valid)
        C = len(self.cameras)
        checks = {
            "xyz": (np.shape(self.poses.xyz), (F, G, K, 3)),
            "valid": (np.shape(self.poses.valid), (F, G)),
            "confidence": (np.shape(self.confidence), (F, G)),
            "members": (np.shape(self.members), (F, G, C)),
        }
        if self.track is not None:
            checks["track"] = (np.shape(self.track), (F, G))
        if self.filled is not None:
            checks["filled"] = (np.shape(self.filled), (F, G, K))
        for field, (got, want) in checks.items():
            if got != want:
                raise InputError(f"shape {got}, expected {want}", field=field)
        if np.ndim(self.identity) != 3 or np.shape(self.identity)[:2] != (F, C):
            raise InputError(
                f"shape {np.shape(self.identity)}, expected ({F}, {C}, P)", field="identity"
            )
        if get_layout(self.layout).num_keypoints != K:
            raise InputError(f"layout {self.layout!r} does not have {K} keypoints", field="layout")


def save_poses(results: PoseResults, folder: str | os.PathLike) -> tuple[Path, Path]:
    """Writes ``folder/poses.npz`` and ``folder/poses.json``; returns their paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    npz_path, json_path = folder / "poses.npz", folder / "poses.json"
    with atomic_open(npz_path, "wb") as f:
        np.savez_compressed(f, **_arrays_of(results))
    with atomic_open(json_path, "w") as f:
        _write_json(f, _json_head(results), _frames_json(results))
    return npz_path, json_path


def poses_to_json(results: PoseResults) -> dict:
    """The JSON form (see the module docstring); coordinates rounded to 0.1 mm."""
    return {**_json_head(results), "frames": list(_frames_json(results))}


def save_poses_chunk(results: PoseResults, path: str | os.PathLike, *, first_frame: int) -> None:
    """Writes the results of frames ``first_frame ..`` as one chunk file (a poses npz with the
    member ``first_frame``; uncompressed, atomically), for `assemble_poses`."""
    arrays = {**_arrays_of(results), "first_frame": np.asarray(first_frame, np.int64)}
    with atomic_open(path, "wb") as f:
        np.savez(f, **arrays)


def load_poses_chunk(path: str | os.PathLike) -> tuple[int, PoseResults]:
    """A chunk file written by `save_poses_chunk`: (its first frame, its results), checked as
    `load_poses` checks a poses file."""
    results = load_poses(path)
    data = load_npz_members(path, _CHUNK_MEMBERS)
    first = data.get("first_frame")
    if first is None or first.shape != () or first.dtype.kind not in "iu" or first < 0:
        raise InputError("not a chunk file (no first frame)", file=path, field="first_frame")
    return int(first), results


def assemble_poses(
    chunks: Sequence[str | os.PathLike], folder: str | os.PathLike, *, frames_total: int
) -> tuple[Path, Path, int]:
    """Writes ``folder/poses.npz`` and ``folder/poses.json`` from consecutive chunk files.

    One chunk is in memory at a time: a first pass reads the chunks' ``.npy`` headers (people
    axis G and skeleton axis P of the whole are the largest of any chunk's), then each npz member
    is written chunk by chunk into the archive, and the JSON frame by frame. The result equals
    `save_poses` of the chunks' results joined along frames (people padded as
    `inference.concat_results` pads them). Both files are written atomically.

    Args:
      chunks: chunk files (`save_poses_chunk`), in order, the first starting at frame 0 and each
        where the previous ends.
      folder: the output folder.
      frames_total: the recording's frame count; when the chunks cover fewer frames the results
        are written as partial (`PoseResults.frames_total`).
    Returns:
      (npz path, json path, frames covered).
    Raises:
      InputError: a chunk that does not start where the previous one ends, or that does not go
        with the first (cameras, layout, optional members).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    heads = [_chunk_head(p) for p in chunks]
    F = 0
    for path, head in zip(chunks, heads, strict=True):
        if head["first_frame"] != F:
            raise InputError(
                f"the chunk starts at frame {head['first_frame']}, the previous chunks end at {F}",
                file=path,
                field="first_frame",
            )
        for key in ("cameras", "layout", "optional"):
            if head[key] != heads[0][key]:
                raise InputError(
                    f"{key} {head[key]} differ from the first chunk's {heads[0][key]}",
                    file=path,
                    field=key,
                )
        F += head["frames"]
    if heads:
        cameras, layout, optional = heads[0]["cameras"], heads[0]["layout"], heads[0]["optional"]
    else:  # nothing finished: an empty (partial) result
        cameras, layout, optional = (), "coco18", ()
    G = max([1] + [h["people"] for h in heads])
    P = max([1] + [h["skeletons"] for h in heads])
    K = get_layout(layout).num_keypoints
    C = len(cameras)
    partial = frames_total > F
    # name -> (dtype, shape of the whole, padding value); the order of `save_poses`.
    members: dict[str, tuple[Any, tuple[int, ...], Any]] = {
        "xyz": (np.float32, (F, G, K, 3), 0),
        "valid": (bool, (F, G), False),
        "keypoint_valid": (bool, (F, G, K), False),
        "confidence": (np.float32, (F, G), 0),
        "members": (np.int32, (F, G, C), -1),
        "identity": (np.int32, (F, C, P), -1),
    }
    for name, dtype, shape, fill in _optional_members(F, G, K):
        if name in optional:
            members[name] = (dtype, shape, fill)
    npz_path, json_path = folder / "poses.npz", folder / "poses.json"
    with atomic_open(npz_path, "wb") as raw, zipfile.ZipFile(raw, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, (dtype, shape, fill) in members.items():
            dtype = np.dtype(dtype)
            with zf.open(name + ".npy", "w", force_zip64=True) as f:
                header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False}
                np.lib.format.write_array_header_2_0(f, {**header, "shape": shape})
                for path in chunks:
                    with np.load(path, allow_pickle=False) as chunk:
                        a = np.asarray(chunk[name], dtype)
                    if name != "timestamps":  # pad the people (skeletons) axis to the whole's
                        axis, size = (2, P) if name == "identity" else (1, G)
                        pad = [(0, 0)] * a.ndim
                        pad[axis] = (0, size - a.shape[axis])
                        a = np.pad(a, pad, constant_values=fill)
                    f.write(np.ascontiguousarray(a).tobytes())
        small = {"cameras": np.asarray(cameras, dtype=str), "layout": np.asarray(layout, dtype=str)}
        if partial:
            small["frames_total"] = np.asarray(frames_total, np.int64)
        for name, a in small.items():
            with zf.open(name + ".npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, a, allow_pickle=False)

    def frames() -> Iterable[dict]:
        for path in chunks:
            first, results = load_poses_chunk(path)
            yield from _frames_json(results, first_frame=first)

    head = {
        "format": FORMAT,
        "version": 1,
        "units": "metres",
        "layout": layout,
        "keypoints": list(get_layout(layout).keypoints),
        "cameras": list(cameras),
    }
    if partial:
        head.update(partial=True, frames_total=int(frames_total))
    with atomic_open(json_path, "w") as f:
        _write_json(f, head, frames())
    return npz_path, json_path, F


def _optional_members(F: int, G: int, K: int):
    """The optional per-frame members of a poses npz: (name, dtype, shape, padding value)."""
    return (
        ("timestamps", np.float64, (F,), 0),
        ("track", np.int32, (F, G), -1),
        ("filled", bool, (F, G, K), False),
    )


# The members every poses npz holds; chunk files add the optional ones and their first frame.
_REQUIRED_MEMBERS = (
    "xyz",
    "valid",
    "keypoint_valid",
    "confidence",
    "members",
    "identity",
    "cameras",
    "layout",
)
_CHUNK_MEMBERS = (
    *_REQUIRED_MEMBERS,
    *(name for name, *_ in _optional_members(0, 0, 0)),
    "first_frame",
)


def _chunk_head(path) -> dict:
    """What `assemble_poses` needs of a chunk before reading its arrays: its first frame, frame
    count, people G, skeletons P, cameras, layout and optional members (from the headers)."""
    shapes = npz_member_shapes(path, _CHUNK_MEMBERS)
    try:
        with np.load(path, allow_pickle=False) as chunk:
            small = {k: chunk[k] for k in ("first_frame", "cameras", "layout")}
    except Exception as e:
        raise InputError(
            f"not a readable chunk file ({type(e).__name__}: {e})", file=path
        ) from None
    return {
        "first_frame": int(small["first_frame"]),
        "frames": shapes["valid"][0],
        "people": shapes["valid"][1],
        "skeletons": shapes["identity"][2],
        "cameras": tuple(str(c) for c in np.atleast_1d(small["cameras"])),
        "layout": str(small["layout"]),
        "optional": tuple(n for n, *_ in _optional_members(0, 0, 0) if n in shapes),
    }


def _arrays_of(results: PoseResults) -> dict[str, np.ndarray]:
    """The npz members of results (module docstring)."""
    arrays = {
        "xyz": np.asarray(results.poses.xyz, np.float32),
        "valid": np.asarray(results.poses.valid, bool),
        "keypoint_valid": np.asarray(results.poses.keypoint_valid, bool),
        "confidence": np.asarray(results.confidence, np.float32),
        "members": np.asarray(results.members, np.int32),
        "identity": np.asarray(results.identity, np.int32),
        "cameras": np.asarray(results.cameras, dtype=str),
        "layout": np.asarray(results.layout, dtype=str),
    }
    if results.timestamps is not None:
        arrays["timestamps"] = np.asarray(results.timestamps, np.float64)
    if results.track is not None:
        arrays["track"] = np.asarray(results.track, np.int32)
    if results.filled is not None:
        arrays["filled"] = np.asarray(results.filled, bool)
    if results.frames_total is not None:
        arrays["frames_total"] = np.asarray(results.frames_total, np.int64)
    return arrays


def _json_head(results: PoseResults) -> dict:
    head = {
        "format": FORMAT,
        "version": 1,
        "units": "metres",
        "layout": results.layout,
        "keypoints": list(get_layout(results.layout).keypoints),
        "cameras": list(results.cameras),
    }
    if results.frames_total is not None:
        head.update(partial=True, frames_total=int(results.frames_total))
    return head


def _frames_json(results: PoseResults, *, first_frame: int = 0) -> Iterable[dict]:
    """Each frame's JSON object (coordinates rounded to 0.1 mm), frames numbered from
    ``first_frame``."""
    # From the float32 values the npz holds, so that the two files say the same.
    xyz = np.round(np.asarray(results.poses.xyz, np.float32).astype(np.float64), 4)
    confidence = np.asarray(results.confidence, np.float32)
    kv = np.asarray(results.poses.keypoint_valid)
    for f in range(len(xyz)):
        people = []
        for g in np.nonzero(np.asarray(results.poses.valid[f]))[0]:
            person = {
                "person": int(g),
                "confidence": round(float(confidence[f, g]), 4),
            }
            if results.track is not None:
                person["track"] = int(results.track[f, g])
            person["keypoints"] = [
                xyz[f, g, k].tolist() if kv[f, g, k] else None for k in range(xyz.shape[2])
            ]
            if results.filled is not None and results.filled[f, g].any():
                person["filled"] = np.nonzero(results.filled[f, g])[0].tolist()
            person["skeletons"] = {
                cam: int(s)
                for cam, s in zip(results.cameras, results.members[f, g], strict=True)
                if s >= 0
            }
            people.append(person)
        frame = {"frame": first_frame + f, "people": people}
        if results.timestamps is not None:
            frame["timestamp"] = float(results.timestamps[f])
        yield frame


def _write_json(out: IO[str], head: dict, frames: Iterable[dict]) -> None:
    """``{**head, "frames": [...]}`` as compact JSON, written one frame at a time."""
    compact = {"separators": (",", ":")}
    text = json.dumps({**head, "frames": []}, **compact)
    out.write(text[: -len("]}")])
    for i, frame in enumerate(frames):
        out.write(("," if i else "") + json.dumps(frame, **compact))
    out.write("]}")


def load_poses(path: str | os.PathLike) -> PoseResults:
    """Reads ``poses.npz`` (or a folder holding it, or ``poses.json``) written by `save_poses`
    or `assemble_poses`; partial results have `PoseResults.frames_total` set.

    Raises:
      InputError naming the file and field when it is not such a file.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "poses.npz"
    if path.suffix.lower() == ".json":
        return _poses_from_json(path)
    # Untrusted bytes: the checked member reader refuses a header that does not describe its
    # member's bytes (so a declared huge array allocates nothing) and object (pickled) arrays.
    data = load_npz_members(path)
    missing = [k for k in _REQUIRED_MEMBERS if k not in data]
    if missing:
        raise InputError(f"not a poses file: missing {missing}", file=path, field=missing[0])
    for field in ("xyz", "confidence"):
        if data[field].dtype.kind not in "biuf":  # np.isfinite has no answer for text or bytes
            raise InputError(f"expected numbers, got {data[field].dtype}", file=path, field=field)
        if not np.isfinite(data[field]).all():
            raise InputError("non-finite values", file=path, field=field)
    for field in ("members", "identity", "track"):  # indices: a float (or NaN) is no index
        if field not in data:
            continue
        if data[field].dtype.kind not in "iu":
            raise InputError(f"expected integers, got {data[field].dtype}", file=path, field=field)
    for field in ("valid", "keypoint_valid", "filled"):
        if field not in data:
            continue
        if data[field].dtype.kind not in "biu":
            raise InputError(f"expected booleans, got {data[field].dtype}", file=path, field=field)
    frames_total = None
    if "frames_total" in data:
        total = data["frames_total"]
        frames = data["valid"].shape[0] if data["valid"].ndim else 0
        if total.shape != () or total.dtype.kind not in "iu" or total < frames:
            raise InputError(
                "expected the recording's frame count, at least the frames here",
                file=path,
                field="frames_total",
            )
        frames_total = int(total)
    try:
        return PoseResults(
            Poses3D(
                data["xyz"].astype(np.float32),
                data["valid"].astype(bool),
                data["keypoint_valid"].astype(bool),
            ),
            data["confidence"].astype(np.float32),
            data["members"].astype(np.int32),
            data["identity"].astype(np.int32),
            tuple(str(c) for c in np.atleast_1d(data["cameras"])),
            str(data["layout"]),
            data.get("timestamps"),
            data["track"].astype(np.int32) if "track" in data else None,
            data["filled"].astype(bool) if "filled" in data else None,
            frames_total,
        )
    except InputError as e:
        raise e.at(file=path) from None
    except (ValueError, TypeError, KeyError) as e:
        raise InputError(f"not a poses file ({e})", file=path) from None


def _poses_from_json(path: Path) -> PoseResults:
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"not a poses file (format is not {FORMAT!r})", file=path, field="format")
    try:
        layout, cameras, frames = str(data["layout"]), tuple(data["cameras"]), data["frames"]
        K = get_layout(layout).num_keypoints
        F = len(frames)
        G = max([1] + [int(p["person"]) + 1 for fr in frames for p in fr["people"]])
        xyz = np.zeros((F, G, K, 3), np.float32)
        kv = np.zeros((F, G, K), bool)
        valid = np.zeros((F, G), bool)
        conf = np.zeros((F, G), np.float32)
        members = np.full((F, G, len(cameras)), -1, np.int32)
        tracked = any("track" in p for fr in frames for p in fr["people"])
        track = np.full((F, G), -1, np.int32) if tracked else None
        filled = np.zeros((F, G, K), bool)
        for f, fr in enumerate(frames):
            for p in fr["people"]:
                g = int(p["person"])
                valid[f, g] = True
                conf[f, g] = float(p["confidence"])
                if track is not None:
                    track[f, g] = int(p.get("track", -1))
                for k in p.get("filled", ()):
                    filled[f, g, int(k)] = True
                for k, v in enumerate(p["keypoints"]):
                    if v is not None:
                        xyz[f, g, k], kv[f, g, k] = v, True
                for cam, s in p["skeletons"].items():
                    members[f, g, cameras.index(cam)] = int(s)
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise InputError(f"malformed poses file ({type(e).__name__}: {e})", file=path) from None
    P = max(1, int(members.max(initial=-1)) + 1)
    identity = np.full((F, len(cameras), P), -1, np.int32)
    f, g, c = np.nonzero(members >= 0)
    identity[f, c, members[f, g, c]] = g
    timestamps = None
    if frames and all("timestamp" in fr for fr in frames):
        timestamps = np.array([float(fr["timestamp"]) for fr in frames])
    frames_total = None
    if data.get("partial", False) is not False:
        frames_total = data.get("frames_total")
        if data["partial"] is not True or type(frames_total) is not int or frames_total < F:
            raise InputError(
                'partial results need "partial": true and "frames_total": the recording\'s '
                "frame count, at least the frames here",
                file=path,
                field="frames_total",
            )
    return PoseResults(
        Poses3D(xyz, valid, kv),
        conf,
        members,
        identity,
        cameras,
        layout,
        timestamps,
        track,
        filled if filled.any() else None,
        frames_total,
    )
