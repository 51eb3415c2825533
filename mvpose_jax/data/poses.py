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

Both are written atomically (temporary file, then rename).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from mvpose_jax.data.files import atomic_open, read_json
from mvpose_jax.data.npz import load_npz_members
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Poses3D, get_layout

FORMAT = "mvpose-jax.poses"


@dataclasses.dataclass(frozen=True)
class PoseResults:
    """People in 3D over F frames and the detections each came from (see the module docstring)."""

    poses: Poses3D
    confidence: np.ndarray
    members: np.ndarray
    identity: np.ndarray
    cameras: tuple[str, ...]
    layout: str
    timestamps: np.ndarray | None = None
    track: np.ndarray | None = None
    filled: np.ndarray | None = None

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
    npz_path, json_path = folder / "poses.npz", folder / "poses.json"
    with atomic_open(npz_path, "wb") as f:
        np.savez_compressed(f, **arrays)
    with atomic_open(json_path, "w") as f:
        json.dump(poses_to_json(results), f, separators=(",", ":"))
    return npz_path, json_path


def poses_to_json(results: PoseResults) -> dict:
    """The JSON form (see the module docstring); coordinates rounded to 0.1 mm."""
    xyz = np.round(np.asarray(results.poses.xyz, np.float64), 4)
    kv = np.asarray(results.poses.keypoint_valid)
    frames = []
    for f in range(len(xyz)):
        people = []
        for g in np.nonzero(np.asarray(results.poses.valid[f]))[0]:
            person = {
                "person": int(g),
                "confidence": round(float(results.confidence[f, g]), 4),
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
        frame = {"frame": f, "people": people}
        if results.timestamps is not None:
            frame["timestamp"] = float(results.timestamps[f])
        frames.append(frame)
    return {
        "format": FORMAT,
        "version": 1,
        "units": "metres",
        "layout": results.layout,
        "keypoints": list(get_layout(results.layout).keypoints),
        "cameras": list(results.cameras),
        "frames": frames,
    }


def load_poses(path: str | os.PathLike) -> PoseResults:
    """Reads ``poses.npz`` (or a folder holding it) written by `save_poses`.

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
    needed = (
        "xyz",
        "valid",
        "keypoint_valid",
        "confidence",
        "members",
        "identity",
        "cameras",
        "layout",
    )
    missing = [k for k in needed if k not in data]
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
    )
