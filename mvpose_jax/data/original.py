"""The original repository's dataset JSON, read and written unchanged (DESIGN.md §4).

Schema: the file is a JSON list of frames. A frame is an object mapping camera name to::

    [skeletons, timestamp, image_name]            or
    [skeletons, timestamp, image_name, gt3d]

  * ``skeletons``: a STRING holding ``json.dumps`` of a list of skeletons (an already decoded list
    is accepted too). A skeleton is an object mapping keypoint index as a string (``"0"`` ..
    ``"17"`` for coco18) to ``[index, x, y, visible, score]`` (pixels; score in [0, 1]). A keypoint
    absent from the object, or with ``visible`` 0 or ``score`` 0, is missing. An ``"ID"`` entry,
    which the original tools skip, is skipped here too.
  * ``timestamp``: seconds (a number). The `Recording` keeps one per frame: the first camera
    entry's, in file order.
  * ``image_name``: the image file of that view (``"no_image"`` in the original tools when none).
  * ``gt3d`` (optional): a list of people, each an object mapping keypoint index (string) to
    ``[x, y, z]`` in CENTIMETRES (metres in the `Recording`). The original tools' Panoptic files
    also store the body centre (Panoptic joint 2) under ``"-1"`` and use its presence as a
    "person valid for evaluation" flag; no layout has that keypoint, so it is skipped.
    Each camera entry may carry gt3d. In the original tools' multi-person files each camera lists
    only the people it sees (their evaluation takes the longest list); here a frame's people are
    the UNION of its lists, in first-seen order, a person repeated in several lists (identical
    coordinates) counted once.

Example, 2 cameras, coco18, one skeleton with two keypoints seen by camera "a"::

    [{"a": ["[{\\"0\\": [0, 512.5, 300.0, 1, 0.9], \\"17\\": [17, 515.0, 380.0, 1, 0.8]}]",
            1650000000.25, "a/000001.jpg", [{"0": [10.0, -150.0, 300.0]}]],
      "b": ["[]", 1650000000.26, "b/000001.jpg"]}]

The file does not record the keypoint layout (the ``layout`` argument gives K, default coco18),
identities (``identity`` is None), nor ids of the ground-truth people: a person's position in its
frame's union is its G index, so people are not followed across frames. Cameras are the union of
the names in the file, in first-seen order, unless ``cameras=`` picks some; a frame without a
camera has no skeletons in that view and an empty image name.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from mvpose_jax.data.checks import (
    check_keypoints,
    check_padding,
    check_recording,
    float_lists,
    is_finite_number,
    is_number,
    load_json,
    pack_detections,
    parse_json_string,
    to_float,
)
from mvpose_jax.data.files import atomic_open
from mvpose_jax.data.recording import Recording
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Poses3D, get_layout

# Ground truth in the original files is in centimetres; the project works in metres.
CM_PER_M = 100.0
# Keys the original tools write but that are not keypoints of any layout (module docstring).
_SKIPPED_SKELETON_KEYS = frozenset({"ID"})
_SKIPPED_GT_KEYS = frozenset({"-1"})


def read_original(
    path: str | os.PathLike,
    *,
    layout: str = "coco18",
    cameras: Sequence[str] | None = None,
) -> Recording:
    """Reads a dataset JSON file of the original repository (schema in the module docstring).

    Args:
      path: the JSON file.
      layout: keypoint layout of the file (the format does not record it); fixes K.
      cameras: optional camera names to read, in this order; default: every camera of the file.
    Returns:
      A `Recording` with timestamps and image names, ground truth (metres) when the file has gt3d,
      and no identities.
    Raises:
      InputError naming file, frame, camera and field of the first problem.
    """
    return original_from_json(load_json(path), file=path, layout=layout, cameras=cameras)


def write_original(recording: Recording, path: str | os.PathLike) -> None:
    """Writes a recording in the original repository's format, atomically.

    Every camera gets an entry in every frame. A recording without timestamps gets the frame number
    as timestamp, one without image names ``"no_image"`` (the original tools' placeholder).
    Ground truth, when present, is written in centimetres to every camera entry, its valid people in
    G order: the original evaluation scripts read element 3 of every camera entry. Identities and
    projections have no place in this format and are not written.

    Raises:
      InputError on invalid values in the recording (nothing is written then).
    """
    check_recording(recording, file=path)
    det = recording.detections
    score = np.asarray(det.score, np.float32)
    count = np.asarray(det.count)
    F = score.shape[0]
    xy = float_lists(det.xy)
    score_l = float_lists(score)
    gt = recording.ground_truth
    with atomic_open(path, "w") as f:
        f.write("[\n")
        for fi in range(F):
            gt3d = None
            if gt is not None:
                gt3d = _gt3d_to_json(gt, fi)
            ts = float(recording.timestamps[fi]) if recording.timestamps is not None else float(fi)
            frame = {}
            for c, cam in enumerate(recording.cameras):
                skeletons = []
                for p in range(int(count[fi, c])):
                    present = np.flatnonzero(score[fi, c, p] > 0).tolist()
                    skeletons.append(
                        {
                            str(k): [
                                k,
                                xy[fi][c][p][k][0],
                                xy[fi][c][p][k][1],
                                1,
                                score_l[fi][c][p][k],
                            ]
                            for k in present
                        }
                    )
                image = (
                    "no_image"
                    if recording.image_names is None
                    else str(recording.image_names[fi, c])
                )
                entry = [json.dumps(skeletons, allow_nan=False), ts, image]
                if gt3d is not None:
                    entry.append(gt3d)
                frame[cam] = entry
            f.write(
                ("" if fi == 0 else ",\n") + json.dumps(frame, ensure_ascii=False, allow_nan=False)
            )
        f.write("\n]\n")


# --------------------------------------------------------------------------- reading


def original_from_json(
    data: Any,
    *,
    file: object = None,
    layout: str = "coco18",
    cameras: Sequence[str] | None = None,
) -> Recording:
    """Builds a `Recording` from a parsed original-format document (see the module docstring)."""
    lay = get_layout(layout)
    K = lay.num_keypoints
    if not isinstance(data, list):
        raise InputError("expected a JSON list of frames (original format)", file=file)
    for fi, frame in enumerate(data):
        if not isinstance(frame, dict):
            raise InputError(
                f"expected an object mapping camera name to [skeletons, timestamp, image_name], "
                f"got {type(frame).__name__}",
                file=file,
                frame=fi,
            )
        if not frame:
            # A frame with no camera entry has no timestamp either; the format always has one.
            raise InputError("frame has no camera entries", file=file, frame=fi)
    seen = list(dict.fromkeys(name for frame in data for name in frame))
    if cameras is None:
        names = seen
    else:
        names = [str(c) for c in cameras]
        if len(set(names)) != len(names):
            raise InputError(f"duplicate camera names {names}", file=file, field="cameras")
        for name in names:
            if name not in seen:
                raise InputError(
                    f"unknown camera; the file has {seen}", file=file, camera=name, field="cameras"
                )
    if not names:
        raise InputError("the file has no cameras", file=file, field="cameras")
    cam_index = {name: c for c, name in enumerate(names)}
    F, C = len(data), len(names)
    # Image names are kept per frame and camera: the grid must be justified by the entries.
    check_padding((F, C), content=sum(len(frame) for frame in data) + C, file=file, field="frames")

    blocks: list[np.ndarray] = []  # (n, K, 4): x, y, visible, score
    where_f: list[int] = []
    where_c: list[int] = []
    where_p: list[int] = []
    timestamps = np.zeros(F, np.float64)
    image_names = np.full((F, C), "", dtype=object)
    gt_frames: list[list[tuple[np.ndarray, np.ndarray]] | None] = []
    for fi, frame in enumerate(data):
        gt_here: list[tuple[np.ndarray, np.ndarray]] | None = None
        for j, (cam, entry) in enumerate(frame.items()):
            err = lambda reason, field, cam=cam, fi=fi: InputError(  # noqa: E731
                reason, file=file, frame=fi, camera=cam, field=field
            )
            if not isinstance(entry, list) or len(entry) not in (3, 4):
                raise err("expected [skeletons, timestamp, image_name] or [..., gt3d]", None)
            ts = entry[1]
            if not is_finite_number(ts):
                raise err(f"expected a finite number, got {ts!r}", "timestamp")
            if j == 0:
                timestamps[fi] = float(ts)
            if not isinstance(entry[2], str):
                raise err(f"expected a string, got {entry[2]!r}", "image_name")
            if len(entry) == 4 and entry[3] is not None:
                gt_here = _union(
                    gt_here or [], _gt3d(entry[3], K, err, file=file, frame=fi, camera=cam)
                )
            if cam not in cam_index:
                continue
            c = cam_index[cam]
            image_names[fi, c] = entry[2]
            block = _skeletons(entry[0], K, err)
            blocks.append(block)
            n = block.shape[0]
            where_f.extend([fi] * n)
            where_c.extend([c] * n)
            where_p.extend(range(n))
        gt_frames.append(gt_here)

    f_idx = np.asarray(where_f, np.int64)
    c_idx = np.asarray(where_c, np.int64)
    p_idx = np.asarray(where_p, np.int64)
    locate = lambda i: (int(f_idx[i]), names[c_idx[i]], int(p_idx[i]))  # noqa: E731
    values = np.concatenate(blocks) if blocks else np.zeros((0, K, 4))
    xy, raw_score = check_keypoints(
        values[..., :2], values[..., 3], num_keypoints=K, locate=locate, file=file, reading=True
    )
    # The format's rule: a keypoint flagged not visible is missing, whatever its score says.
    score = np.where(values[..., 2] != 0, raw_score, 0.0).astype(np.float32)
    det = pack_detections(xy, score, (f_idx, c_idx, p_idx), num_frames=F, num_cameras=C, file=file)

    ground_truth = None
    if any(g is not None for g in gt_frames):
        ground_truth = _ground_truth(gt_frames, K, file)
    try:
        return Recording(
            detections=det,
            cameras=tuple(names),
            layout=lay.name,
            ground_truth=ground_truth,
            timestamps=timestamps,
            image_names=image_names.astype(str) if F else np.zeros((0, C), "<U1"),
        )
    except InputError as e:
        raise e.at(file=file) from None


def _skeletons(value: Any, K: int, err) -> np.ndarray:
    """One view's skeletons -> (n, K, 4) float64 rows [x, y, visible, score] (absent: zeros)."""
    if isinstance(value, str):
        value = parse_json_string(value, bad=lambda reason: err(reason, "skeletons"))
    if not isinstance(value, list):
        raise err(f"expected a list of skeletons, got {type(value).__name__}", "skeletons")
    out = np.zeros((len(value), K, 4), np.float64)
    for p, sk in enumerate(value):
        if not isinstance(sk, dict):
            raise err(
                "expected an object mapping keypoint index to [index, x, y, visible, score]",
                f"skeleton[{p}]",
            )
        if not sk:
            continue
        keys = [key for key in sk if key not in _SKIPPED_SKELETON_KEYS]
        if not keys:
            continue
        idx = _indices(
            keys, K, lambda reason, key, p=p: err(reason, f"skeleton[{p}].keypoints[{key}]")
        )
        rows = [sk[key] for key in keys]
        # Fast path: one conversion per skeleton; anything odd goes through the per-entry check.
        try:
            arr = np.array(rows)
        except (ValueError, TypeError, OverflowError):
            arr = None
        if arr is None or arr.dtype.kind not in "fi" or arr.shape != (len(rows), 5):
            arr = np.zeros((len(rows), 5))
            for j, row in enumerate(rows):
                if not (isinstance(row, list) and len(row) == 5 and all(is_number(v) for v in row)):
                    raise err(
                        f"expected [index, x, y, visible, score], got {row!r}"[:200],
                        f"skeleton[{p}].keypoints[{idx[j]}]",
                    )
                arr[j] = [to_float(v) for v in row]
        arr = arr.astype(np.float64)
        mismatch = arr[:, 0] != idx
        if mismatch.any():
            j = int(np.argmax(mismatch))
            raise err(
                f"index {arr[j, 0]!r} differs from its key {idx[j]}",
                f"skeleton[{p}].keypoints[{idx[j]}]",
            )
        bad_vis = ~np.isfinite(arr[:, 3])
        if bad_vis.any():
            j = int(np.argmax(bad_vis))
            raise err(
                "visible flag is not a finite number", f"skeleton[{p}].keypoints[{idx[j]}].visible"
            )
        out[p, idx] = arr[:, 1:]
    return out


def _indices(keys, K: int, bad) -> np.ndarray:
    """Keypoint keys ("0".."K-1") -> int array; raises on non-integers, out of range, duplicates."""
    idx = []
    for key in keys:
        try:
            k = int(key)
        except ValueError:
            raise bad(f"keypoint key {key!r} is not an integer", key) from None
        if not 0 <= k < K:
            raise bad(
                f"keypoint index {k} out of range: the layout has {K} keypoints (0..{K - 1})", key
            )
        idx.append(k)
    if len(set(idx)) != len(idx):
        dup = next(k for k in idx if idx.count(k) > 1)
        raise bad(f"keypoint {dup} appears twice", dup)
    return np.asarray(idx, np.int64)


def _gt3d(
    value: Any, K: int, err, *, file: object, frame: int, camera: str
) -> list[tuple[np.ndarray, np.ndarray]]:
    """gt3d -> list of (xyz (K, 3) metres float64, present (K,) bool), one per person."""
    if not isinstance(value, list):
        raise err(f"expected a list of people, got {type(value).__name__}", "gt3d")
    people = []
    for g, person in enumerate(value):
        if not isinstance(person, dict):
            raise err("expected an object mapping keypoint index to [x, y, z]", f"gt3d[{g}]")
        xyz = np.zeros((K, 3), np.float64)
        present = np.zeros(K, bool)
        keys = [key for key in person if key not in _SKIPPED_GT_KEYS]
        idx = _indices(keys, K, lambda reason, key, g=g: err(reason, f"gt3d[{g}].keypoints[{key}]"))
        for k, row in zip(idx.tolist(), (person[key] for key in keys), strict=True):
            if not isinstance(row, list) or len(row) != 3 or not all(is_number(v) for v in row):
                raise err(f"expected [x, y, z], got {row!r}"[:200], f"gt3d[{g}].keypoints[{k}]")
            xyz[k] = [to_float(v) / CM_PER_M for v in row]
            present[k] = True
        with np.errstate(over="ignore"):
            finite = np.isfinite(xyz.astype(np.float32)).all()
        if not finite:  # reported here, where the camera is known, by the shared check
            check_keypoints(
                xyz[None],
                num_keypoints=K,
                file=file,
                locate=lambda _, g=g: (frame, camera, g),
                field="gt3d[{p}].keypoints[{k}]",
            )
        people.append((xyz, present))
    return people


def _union(
    people: list[tuple[np.ndarray, np.ndarray]], more: list[tuple[np.ndarray, np.ndarray]]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``people`` plus the people of ``more`` not already there (identical coordinates and masks).

    Matching is a multiset one: two identical people within ``more`` stay two people.
    """
    key = lambda person: (person[1].tobytes(), person[0].tobytes())  # noqa: E731
    available: dict[bytes, list[int]] = {}
    for i, person in enumerate(people):
        available.setdefault(key(person), []).append(i)
    out = list(people)
    for person in more:
        same = available.get(key(person))
        if same:
            same.pop(0)
        else:
            out.append(person)
    return out


def _ground_truth(
    frames: list[list[tuple[np.ndarray, np.ndarray]] | None], K: int, file: object
) -> Poses3D:
    """Per-frame people lists -> Poses3D padded to G = max(1, most people in a frame)."""
    F = len(frames)
    G = max([1] + [len(people) for people in frames if people])
    entries = sum(len(people) for people in frames if people)
    check_padding((F, G, K, 3), content=entries * K, file=file, field="gt3d")
    xyz = np.zeros((F, G, K, 3), np.float64)
    kvalid = np.zeros((F, G, K), bool)
    valid = np.zeros((F, G), bool)
    for fi, people in enumerate(frames):
        for g, (x, present) in enumerate(people or []):
            xyz[fi, g], kvalid[fi, g], valid[fi, g] = x, present, True
    xyz32, _ = check_keypoints(
        xyz.reshape(F * G, K, 3),
        num_keypoints=K,
        file=file,
        locate=lambda i: (i // G, None, i % G),
        field="gt3d[{p}].keypoints[{k}]",
        count_field="gt3d[{p}]",
    )
    return Poses3D(xyz32.reshape(F, G, K, 3), valid, kvalid)


def _gt3d_to_json(gt: Poses3D, f: int) -> list[dict[str, list[float]]]:
    valid = np.asarray(gt.valid)[f]
    kvalid = np.asarray(gt.keypoint_valid)[f]
    # Written so that the reader's division by 100 gives back the same float32 metres.
    cm = float_lists(np.asarray(gt.xyz, np.float32)[f], unit=CM_PER_M)
    return [
        {str(k): cm[g][k] for k in np.flatnonzero(kvalid[g]).tolist()}
        for g in np.flatnonzero(valid).tolist()
    ]
