"""The project's native detections JSON: a recording of 2D skeletons, its identities and 3D truth.

Schema (version 1). Keys not listed here are errors, so a misspelt key never loses data silently::

    {
      "format": "mvpose-jax.detections",   # optional; if present, exactly this
      "version": 1,                         # optional; if present, 1
      "description": "...",                 # optional free text (not kept in the Recording)
      "layout": "coco18",                   # optional, default "coco18"; fixes K (keypoints)
      "cameras": ["cam0", "cam1"],          # required, unique names: the order of the camera axis
      "rig": {"cameras": [...]},            # optional native calibration (calibration.rig_to_dict)
      "frames": [                           # required list, one entry per frame (F)
        {
          "index": 0,                       # optional; if present, the position in "frames"
          "timestamp": 0.0,                 # optional seconds; all frames or none
          "images": {"cam0": "0000.jpg"},   # optional image file per camera (others "")
          "views": {                        # optional; a camera left out saw nobody
            "cam0": [                       # the skeletons this camera saw, in detector order
              {
                "keypoints": [[x, y, score], ...],   # exactly K entries; score in [0, 1]
                "identity": 3,              # optional: the ground-truth "id" of this person in
                                            #   this frame; -1 or absent = unknown / false positive
                                            #   (identities and ids are integers below 2^31)
                "projected": [[x, y], ...]  # optional: K noise-free projections of the truth;
              }                             #   all skeletons or none
            ]
          },
          "ground_truth": [                 # optional: the people present in this frame
            {"id": 3, "keypoints": [[x, y, z], null, ...]}   # metres; K entries, null = missing;
          ]                                 #   "keypoints" absent = all missing
        }
      ]
    }

A missing keypoint has score 0 and is written ``[0, 0, 0]``; ``null`` is read as missing too.
Coordinates must be finite (``NaN``/``Infinity`` and numbers beyond float32 are errors).

In the `Recording`, ground-truth people live on the G axis: G is the sorted union of the ids over
the whole recording, so a person keeps its G index in every frame (``valid`` is False in the
frames it is absent from), and ``identity`` holds G indices. Ids are therefore renumbered 0..G-1;
the writer writes the G index as the id. Without ground truth, identities are kept as written
(any integer >= -1). Readers pad P to the most skeletons in any view (at least 1).

Example (lists shortened with ``...``: a coco18 file has 18 entries in each)::

    {"format": "mvpose-jax.detections", "version": 1, "layout": "coco18", "cameras": ["a", "b"],
     "frames": [{"index": 0, "timestamp": 0.04,
                 "views": {"a": [{"keypoints": [[512.5, 300.25, 0.91], [0, 0, 0], ...],
                                  "identity": 7}],
                           "b": []},
                 "ground_truth": [{"id": 7, "keypoints": [[0.1, 1.52, 2.0], null, ...]}]}]}
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

from mvpose_jax.cameras import Rig
from mvpose_jax.data.calibration import rig_from_dict, rig_to_dict
from mvpose_jax.data.checks import (
    check_keypoints,
    check_padding,
    check_recording,
    float_lists,
    is_finite_number,
    is_int,
    load_json,
    number_rows,
    pack_detections,
    scatter_rows,
)
from mvpose_jax.data.files import atomic_open
from mvpose_jax.data.recording import Recording
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import LAYOUTS, Poses3D, get_layout

FORMAT = "mvpose-jax.detections"
VERSION = 1

_TOP_KEYS = frozenset({"format", "version", "description", "layout", "cameras", "rig", "frames"})
_FRAME_KEYS = frozenset({"index", "timestamp", "images", "views", "ground_truth"})
_SKELETON_KEYS = frozenset({"keypoints", "identity", "projected"})
_GT_KEYS = frozenset({"id", "keypoints"})
# Identities and ids are stored as int32.
_MAX_ID = 2**31 - 1


def read_native(path: str | os.PathLike) -> Recording:
    """Reads a native detections JSON file (schema in the module docstring).

    Raises:
      InputError naming the file, frame (index in ``frames``), camera and field of the first
      problem.
    """
    return native_from_json(load_json(path), file=path)


def read_native_rig(path: str | os.PathLike) -> Rig | None:
    """The calibration embedded in a native file, or None when it has none.

    The rig is returned as stored (it may hold more cameras than the recording); every camera of
    the recording must be in it. Use ``rig.select(recording.cameras)`` to align the camera axes.
    """
    data = load_json(path)
    cameras = _header(data, path)[1]
    if data.get("rig") is None:
        return None
    rig = rig_from_dict(data["rig"], file=path)
    for name in cameras:
        if name not in rig.names:
            raise InputError(
                f"camera missing from the embedded rig {list(rig.names)}",
                file=path,
                camera=name,
                field="rig",
            )
    return rig


def write_native(recording: Recording, path: str | os.PathLike, rig: Rig | None = None) -> None:
    """Writes a recording as native JSON, atomically (a reader never sees half a file).

    Floats are written with the shortest text that reads back to the same float32, so
    ``read_native(write_native(r))`` equals ``r`` exactly, except where ``r`` has more padding than
    its content needs: P shrinks to the most people in a view, G loses people present in no
    frame (ids are renumbered accordingly), and a recording without any skeleton reads back
    without identities. One frame per line.

    Args:
      recording: the recording; its values are validated first (nothing is written if bad).
      path: output file.
      rig: optional calibration to embed; it must contain every camera of the recording.
    Raises:
      InputError on invalid values in the recording or a rig lacking one of its cameras.
    """
    check_recording(recording, file=path)
    if rig is not None:
        for name in recording.cameras:
            if name not in rig.names:
                raise InputError(
                    f"camera missing from the rig {list(rig.names)}",
                    file=path,
                    camera=name,
                    field="rig",
                )
    header: dict[str, Any] = {"format": FORMAT, "version": VERSION, "layout": recording.layout}
    header["cameras"] = list(recording.cameras)
    if rig is not None:
        header["rig"] = rig_to_dict(rig)
    compact: dict[str, Any] = {"separators": (",", ":"), "ensure_ascii": False, "allow_nan": False}
    with atomic_open(path, "w") as f:
        f.write("{\n")
        for key, value in header.items():
            f.write(f"{json.dumps(key)}: {json.dumps(value, **compact)},\n")
        f.write('"frames": [\n')
        for i, frame in enumerate(_frames_to_json(recording)):
            f.write(("" if i == 0 else ",\n") + json.dumps(frame, **compact))
        f.write("\n]}\n")


# --------------------------------------------------------------------------- reading


def native_from_json(data: Any, *, file: object = None) -> Recording:
    """Builds a `Recording` from a parsed native JSON document (see the module docstring)."""
    layout, cameras = _header(data, file)
    K = get_layout(layout).num_keypoints
    frames = data["frames"]
    if not isinstance(frames, list):
        raise InputError(
            f"expected a list of frames, got {type(frames).__name__}", file=file, field="frames"
        )
    F, C = len(frames), len(cameras)
    cam_index = {name: c for c, name in enumerate(cameras)}

    # One pass over the structure collects every skeleton in file order with where it goes
    # (frame, camera, person); the numbers are converted afterwards in bulk (see `_rows`).
    where: list[tuple[int, int, int]] = []
    raw_keypoints: list[Any] = []
    raw_projected: list[Any] = []  # None where a skeleton has none
    identities: list[int] = []  # as written, -1 unknown
    has_identity = False
    timestamps: list[float | None] = []
    images: dict[tuple[int, int], str] = {}
    has_images = False
    gt_where: list[tuple[int, int, int]] = []  # frame, id, position in the frame's list
    gt_keypoints: list[Any] = []
    has_gt = False
    gt_ids: list[set[int]] = []

    for fi, frame in enumerate(frames):
        err = lambda reason, field, camera=None, fi=fi: InputError(  # noqa: E731
            reason, file=file, frame=fi, camera=camera, field=field
        )
        if not isinstance(frame, dict):
            raise err(f"expected an object, got {type(frame).__name__}", f"frames[{fi}]")
        for key in frame:
            if key not in _FRAME_KEYS:
                raise err(f"unknown key; frames have {sorted(_FRAME_KEYS)}", str(key))
        if "index" in frame and not (is_int(frame["index"]) and frame["index"] == fi):
            raise err(
                f"index {frame['index']!r} is not the frame's position {fi} in 'frames'", "index"
            )
        ts = frame.get("timestamp")
        if ts is not None and not is_finite_number(ts):
            raise err(f"expected a finite number, got {ts!r}", "timestamp")
        timestamps.append(None if ts is None else float(ts))

        if frame.get("images") is not None:
            has_images = True
            imgs = frame["images"]
            if not isinstance(imgs, dict):
                raise err("expected an object mapping camera to image file", "images")
            for cam, name in imgs.items():
                if cam not in cam_index:
                    raise err(f"unknown camera; cameras are {cameras}", "images", cam)
                if not isinstance(name, str):
                    raise err(f"expected a string, got {name!r}", "images", cam)
                images[fi, cam_index[cam]] = name

        ids: set[int] = set()
        if frame.get("ground_truth") is not None:
            has_gt = True
            people = frame["ground_truth"]
            if not isinstance(people, list):
                raise err("expected a list of people", "ground_truth")
            for g, person in enumerate(people):
                pfield = f"ground_truth[{g}]"
                if not isinstance(person, dict):
                    raise err("expected an object with 'id' and 'keypoints'", pfield)
                for key in person:
                    if key not in _GT_KEYS:
                        raise err(f"unknown key; people have {sorted(_GT_KEYS)}", f"{pfield}.{key}")
                pid = person.get("id")
                if not is_int(pid) or not 0 <= pid <= _MAX_ID:
                    raise err(
                        f"expected an integer id in [0, 2^31), got {pid!r}"[:200], f"{pfield}.id"
                    )
                if pid in ids:
                    raise err(f"duplicate id {pid}", f"{pfield}.id")
                ids.add(pid)
                kps = person.get("keypoints")
                gt_keypoints.append([None] * K if kps is None else kps)
                gt_where.append((fi, pid, g))
        gt_ids.append(ids)

        views = frame.get("views")
        if views is None:
            continue
        if not isinstance(views, dict):
            raise err("expected an object mapping camera name to a list of skeletons", "views")
        for cam, skeletons in views.items():
            if cam not in cam_index:
                raise err(f"unknown camera; cameras are {cameras}", "views", cam)
            c = cam_index[cam]
            if not isinstance(skeletons, list):
                raise err("expected a list of skeletons", "views", cam)
            for p, sk in enumerate(skeletons):
                sfield = f"skeleton[{p}]"
                if not isinstance(sk, dict):
                    raise err("expected an object with 'keypoints'", sfield, cam)
                for key in sk:
                    if key not in _SKELETON_KEYS:
                        raise err(
                            f"unknown key; skeletons have {sorted(_SKELETON_KEYS)}",
                            f"{sfield}.{key}",
                            cam,
                        )
                if "keypoints" not in sk:
                    raise err("missing field", f"{sfield}.keypoints", cam)
                ident = sk.get("identity")
                if ident is not None:
                    has_identity = True
                    if not is_int(ident) or not -1 <= ident <= _MAX_ID:
                        raise err(
                            f"expected an integer in [-1, 2^31), got {ident!r}"[:200],
                            f"{sfield}.identity",
                            cam,
                        )
                identities.append(-1 if ident is None else ident)
                raw_keypoints.append(sk["keypoints"])
                raw_projected.append(sk.get("projected"))
                where.append((fi, c, p))

    f_idx, c_idx, p_idx = index = tuple(np.array(where, np.int64).reshape(-1, 3).T)
    locate = lambda i: (int(f_idx[i]), cameras[c_idx[i]], int(p_idx[i]))  # noqa: E731
    values, present = _rows(
        raw_keypoints, 3, K, allow_null=True, locate=locate, file=file, name="keypoints"
    )
    values[~present] = 0.0
    xy, score = check_keypoints(
        values[..., :2], values[..., 2], num_keypoints=K, locate=locate, file=file, reading=True
    )
    det = pack_detections(xy, score, index, num_frames=F, num_cameras=C, file=file)
    P = det.score.shape[2]

    # Projections: all skeletons or none (a partial array would invent zeros for the others).
    proj_arr = None
    if any(v is not None for v in raw_projected):
        if None in raw_projected:
            fi, cam, p = locate(raw_projected.index(None))
            raise InputError(
                "some skeletons have 'projected' and this one has not (all or none)",
                file=file,
                frame=fi,
                camera=cam,
                field=f"skeleton[{p}].projected",
            )
        proj, _ = _rows(
            raw_projected, 2, K, allow_null=False, locate=locate, file=file, name="projected"
        )
        proj32, _ = check_keypoints(
            proj,
            num_keypoints=K,
            locate=locate,
            file=file,
            field="skeleton[{p}].projected[{k}]",
            count_field="skeleton[{p}].projected",
        )
        proj_arr = scatter_rows(proj32, index, (F, C, P), 0.0)

    # Timestamps: all frames or none (NaN placeholders would poison later arithmetic).
    ts_arr = None
    if any(t is not None for t in timestamps):
        if None in timestamps:
            raise InputError(
                "some frames have a timestamp and this one has not (all or none)",
                file=file,
                frame=timestamps.index(None),
                field="timestamp",
            )
        ts_arr = np.asarray(timestamps, np.float64)

    img_arr = None
    if has_images:
        img_arr = np.full((F, C), "", dtype=object)
        for (fi, c), name in images.items():
            img_arr[fi, c] = name
        img_arr = img_arr.astype(str) if F * C else np.zeros((F, C), "<U1")

    ground_truth, g_of_id = None, {}
    if has_gt:
        ground_truth, g_of_id = _ground_truth(gt_keypoints, gt_where, F, K, file)

    ident_arr = None
    if has_identity:
        raw = np.asarray(identities, np.int64)
        mapped = raw.copy()
        if has_gt:
            for i in np.flatnonzero(raw >= 0):
                fi = int(f_idx[i])
                if raw[i] not in gt_ids[fi]:
                    _, cam, p = locate(i)
                    raise InputError(
                        f"identity {int(raw[i])} is not the id of a ground-truth person of this "
                        "frame "
                        f"(ids: {sorted(gt_ids[fi])})",
                        file=file,
                        frame=fi,
                        camera=cam,
                        field=f"skeleton[{p}].identity",
                    )
                mapped[i] = g_of_id[int(raw[i])]
        ident_arr = scatter_rows(mapped.astype(np.int32), index, (F, C, P), -1)

    try:
        return Recording(
            detections=det,
            cameras=tuple(cameras),
            layout=layout,
            ground_truth=ground_truth,
            identity=ident_arr,
            timestamps=ts_arr,
            image_names=img_arr,
            projected=proj_arr,
        )
    except InputError as e:
        raise e.at(file=file) from None


def _rows(
    raw: list[Any], width: int, K: int, *, allow_null: bool, locate, file: object, name: str
) -> tuple[np.ndarray, np.ndarray]:
    """Lists of K ``width``-number rows, one per skeleton -> (N, K, width) float64, present (N, K).

    Fast path: a well-formed recording converts in ONE numpy call (a 2000-frame, 6-camera,
    8-person file holds ~100k skeletons). Anything else (nulls, strings, wrong counts) goes
    skeleton by skeleton, so the error names the first bad one in file order.
    """
    try:
        arr = np.array(raw)
    except (ValueError, TypeError, OverflowError):
        arr = None
    if arr is not None and arr.dtype.kind in "fi" and arr.shape == (len(raw), K, width):
        return arr.astype(np.float64), np.ones((len(raw), K), bool)
    values = np.zeros((len(raw), K, width), np.float64)
    present = np.zeros((len(raw), K), bool)
    for i, entries in enumerate(raw):
        fi, cam, p = locate(i)
        field = f"{'ground_truth' if cam is None else 'skeleton'}[{p}].{name}"
        v, ok = number_rows(
            entries,
            width,
            allow_null=allow_null,
            bad=lambda k, reason, fi=fi, cam=cam, field=field: InputError(
                reason,
                file=file,
                frame=fi,
                camera=cam,
                field=field + ("" if k is None else f"[{k}]"),
            ),
        )
        if v.shape[0] != K:  # reported by the shared check, like every other reader
            check_keypoints(
                v[None],
                num_keypoints=K,
                locate=lambda _, where=(fi, cam, p): where,
                file=file,
                count_field=field,
            )
        values[i], present[i] = v, ok
    return values, present


def _header(data: Any, file: object) -> tuple[str, list[str]]:
    """Checks the top level; returns (layout, cameras)."""
    if not isinstance(data, dict):
        raise InputError("expected a JSON object (native detections format)", file=file)
    for key in data:
        if key not in _TOP_KEYS:
            raise InputError(
                f"unknown key; the top level has {sorted(_TOP_KEYS)}", file=file, field=str(key)
            )
    if "format" in data and data["format"] != FORMAT:
        raise InputError(f"expected {FORMAT!r}, got {data['format']!r}", file=file, field="format")
    if "version" in data and not (is_int(data["version"]) and data["version"] == VERSION):
        raise InputError(
            f"unsupported version {data['version']!r}; this reader knows version {VERSION}",
            file=file,
            field="version",
        )
    if "description" in data and not isinstance(data["description"], str):
        raise InputError("expected a string", file=file, field="description")
    layout = data.get("layout", "coco18")
    if not isinstance(layout, str) or layout not in LAYOUTS:
        raise InputError(
            f"unknown keypoint layout {layout!r}; known: {sorted(LAYOUTS)}",
            file=file,
            field="layout",
        )
    cameras = data.get("cameras")
    if not isinstance(cameras, list) or not cameras:
        raise InputError("expected a non-empty list of camera names", file=file, field="cameras")
    for i, name in enumerate(cameras):
        if not isinstance(name, str) or not name:
            raise InputError(
                f"expected a non-empty string, got {name!r}", file=file, field=f"cameras[{i}]"
            )
    if len(set(cameras)) != len(cameras):
        raise InputError(f"duplicate camera names in {cameras}", file=file, field="cameras")
    if "frames" not in data:
        raise InputError("missing field", file=file, field="frames")
    return layout, list(cameras)


def _ground_truth(
    raw: list[Any], where: list[tuple[int, int, int]], F: int, K: int, file: object
) -> tuple[Poses3D, dict[int, int]]:
    """Ground-truth keypoint lists and their (frame, id, position) -> Poses3D, and id -> G index."""
    ids = sorted({pid for _, pid, _ in where})
    g_of_id = {pid: g for g, pid in enumerate(ids)}
    # G >= 1 like P: a recording with ground truth but nobody in it still has a (padding) person.
    G = max(1, len(ids))
    check_padding((F, G, K, 3), content=len(where) * K, file=file, field="ground_truth")
    locate = lambda i: (where[i][0], None, where[i][2])  # noqa: E731
    xyz, present = _rows(raw, 3, K, allow_null=True, locate=locate, file=file, name="keypoints")
    xyz32, _ = check_keypoints(
        np.where(present[..., None], xyz, 0.0),
        num_keypoints=K,
        file=file,
        locate=locate,
        field="ground_truth[{p}].keypoints[{k}]",
        count_field="ground_truth[{p}].keypoints",
    )
    index = (
        np.array([w[0] for w in where], np.int64),
        np.array([g_of_id[w[1]] for w in where], np.int64),
    )
    xyz_arr = scatter_rows(xyz32, index, (F, G), 0.0)
    kvalid = scatter_rows(present, index, (F, G), False)
    valid = scatter_rows(np.ones(len(where), bool), index, (F, G), False)
    return Poses3D(xyz_arr, valid, kvalid), g_of_id


# --------------------------------------------------------------------------- writing


def _frames_to_json(rec: Recording):
    """Yields the JSON object of each frame."""
    det = rec.detections
    score = np.asarray(det.score, np.float32)
    count = np.asarray(det.count)
    F, K = score.shape[0], score.shape[3]
    # (F, C, P, K, 3) rows [x, y, score], missing keypoints written [0, 0, 0].
    kp = np.concatenate([np.asarray(det.xy, np.float32), score[..., None]], axis=-1)
    kp[score == 0] = 0.0
    kp_lists = float_lists(kp)
    proj_lists = (
        None if rec.projected is None else float_lists(np.asarray(rec.projected, np.float32))
    )
    ident = None if rec.identity is None else np.asarray(rec.identity).tolist()
    gt = rec.ground_truth
    if gt is not None:
        gt_valid = np.asarray(gt.valid)
        gt_kvalid = np.asarray(gt.keypoint_valid)
        gt_xyz = float_lists(np.asarray(gt.xyz, np.float32))
    for f in range(F):
        frame: dict[str, Any] = {"index": f}
        if rec.timestamps is not None:
            frame["timestamp"] = float(rec.timestamps[f])
        if rec.image_names is not None:
            frame["images"] = {cam: str(rec.image_names[f, c]) for c, cam in enumerate(rec.cameras)}
        views = {}
        for c, cam in enumerate(rec.cameras):
            skeletons = []
            for p in range(int(count[f, c])):
                sk: dict[str, Any] = {"keypoints": kp_lists[f][c][p]}
                if ident is not None:
                    sk["identity"] = ident[f][c][p]
                if proj_lists is not None:
                    sk["projected"] = proj_lists[f][c][p]
                skeletons.append(sk)
            views[cam] = skeletons
        frame["views"] = views
        if gt is not None:
            frame["ground_truth"] = [
                {
                    "id": g,
                    "keypoints": [
                        gt_xyz[f][g][k] if gt_kvalid[f, g, k] else None for k in range(K)
                    ],
                }
                for g in np.flatnonzero(gt_valid[f]).tolist()
            ]
        yield frame
