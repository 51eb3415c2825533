"""What every recording format shares: the value checks, the padded building, the JSON helpers.

Every reader and writer validates keypoints through ONE helper, `check_keypoints` (keypoint count,
finite coordinates, scores in [0, 1]), and whole recordings through `check_recording`, so a bad
value is reported the same way, naming file, frame, camera and field, whatever the format.
Readers pad the person axis to the most people in any view (P >= 1) and set the coordinates of
missing keypoints (score 0) to 0, the `Detections` convention; they never drop a skeleton. They
refuse to pad a file's content to arrays hundreds of times larger than it (`check_padding`), so a
small hostile file cannot allocate gigabytes.

The readers (`native`, `original`, `npz`, `openpose`) import from here; `formats` imports them.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from mvpose_jax.data.files import _read_text
from mvpose_jax.data.recording import Recording
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.skeletons import Detections

# Scores above 1 up to this are accepted and clipped (detector heatmap peaks exceed 1 a little);
# beyond it a score is an error (another scale, or garbage).
MAX_SCORE = 1.5


class ScoreClippedWarning(MvposeWarning):
    """Keypoint scores slightly above 1 were clipped to 1 while reading."""


@dataclasses.dataclass
class ClippedScores:
    """A tally of scores clipped to 1 over several checks (a recording read a chunk at a time), so
    that the reader warns once per file (`warn_clipped`) rather than once per chunk."""

    count: int = 0
    largest: float = 0.0

    def add(self, scores: np.ndarray) -> None:
        """Counts the scores above 1 in ``scores`` (any shape)."""
        above = scores > 1
        if above.any():
            self.count += int(above.sum())
            self.largest = max(self.largest, float(scores.max()))


def warn_clipped(where: object, clipped: ClippedScores, *, stacklevel: int = 2) -> None:
    """The one `ScoreClippedWarning` of a file (nothing when no score was clipped)."""
    if clipped.count:
        warnings.warn(
            f"{where}: {clipped.count} keypoint scores above 1 (largest {clipped.largest:.4g}) "
            "were clipped to 1",
            ScoreClippedWarning,
            stacklevel=stacklevel + 1,
        )


# Where a row of a flat batch of skeletons comes from: row index -> (frame, camera, person).
Locate = Callable[[int], tuple[Any, Any, Any]]

# Readers pad to dense (F, C, P, K) arrays, and a small file can ask for a huge padded shape (many
# empty frames or cameras, one view with far more people than the rest): 200 KB of native JSON can
# ask for 161 GiB. Padded arrays larger than PADDING_FLOOR values must hold at least one value from
# the file per PADDING_RATIO values (`check_padding`); dense recordings of any size pass.
PADDING_FLOOR = 2**24
PADDING_RATIO = 256


# --------------------------------------------------------------------------- shared checks


def check_keypoints(
    coords: np.ndarray,
    score: np.ndarray | None = None,
    *,
    num_keypoints: int,
    locate: Locate,
    file: object = None,
    field: str = "skeleton[{p}].keypoints[{k}]",
    score_field: str = "skeleton[{p}].keypoints[{k}].score",
    count_field: str = "skeleton[{p}].keypoints",
    reading: bool = False,
    source: object = None,
    clipped: ClippedScores | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """THE keypoint check of every reader and writer: count, finite coordinates, score range.

    Args:
      coords: (N, K', D) coordinates of N skeletons (pixels or metres), any real dtype.
      score: optional (N, K') scores in [0, 1]; scores in (1, `MAX_SCORE`] are clipped to 1 with
        one `ScoreClippedWarning` for the call.
      reading: the values come from a file: a non-finite coordinate with score 0 is then a
        missing keypoint (set to 0), as several detectors write one; a writer refuses it.
      source: what the clipping warning names (default ``file``; a folder of files, say).
      clipped: a tally to add the clipped scores to instead of warning (the caller warns once,
        `warn_clipped`, after the last chunk of a file).
      num_keypoints: K, the number of keypoints the layout has; K' must equal it.
      locate: maps a row index to its (frame, camera, person), called only to report an error.
      file: the file the values came from.
      field, score_field, count_field: names of the offending field, ``str.format`` templates
        with ``{p}`` (person) and ``{k}`` (keypoint) for a bad coordinate, a bad score and a
        wrong keypoint count.
    Returns:
      coords as float32 (N, K, D) and score as float32 (N, K) (or None).
    Raises:
      InputError naming file, frame, camera and field of the first bad value.
    """
    coords = np.asarray(coords)
    if coords.ndim != 3:
        raise AssertionError(f"check_keypoints wants (N, K, D) coordinates, got {coords.shape}")

    def fail(i: int, k: int | None, template: str, reason: str):
        frame, camera, person = locate(int(i))
        name = template.format(p=person, k=k)
        raise InputError(reason, file=file, frame=frame, camera=camera, field=name)

    if coords.shape[0] and coords.shape[1] != num_keypoints:
        fail(0, None, count_field, f"expected {num_keypoints} keypoints, got {coords.shape[1]}")
    # Check after the cast: a finite float64 beyond float32's range becomes inf in the arrays.
    with np.errstate(over="ignore", invalid="ignore"):
        coords32 = coords.astype(np.float32)
        score32 = None if score is None else np.asarray(score).astype(np.float32)
    bad = ~np.isfinite(coords32).all(axis=-1)
    if score32 is not None and reading:
        # Several detectors mark a keypoint they did not find as NaN (or inf) with score 0: that
        # is a missing keypoint, whose coordinates are 0 by the `Detections` convention.
        missing = bad & (score32 == 0)
        coords32[missing] = 0.0
        bad &= ~missing
    if bad.any():
        i, k = np.argwhere(bad)[0]
        fail(i, k, field, f"coordinates {coords[i, k].tolist()} are not finite numbers")
    if score32 is None:
        return coords32, None
    bad = ~(np.isfinite(score32) & (score32 >= 0) & (score32 <= MAX_SCORE))
    if bad.any():
        i, k = np.argwhere(bad)[0]
        fail(
            i,
            k,
            score_field,
            f"score {_number(np.asarray(score)[i, k])} is outside [0, {MAX_SCORE}]",
        )
    if (score32 > 1).any():
        # Heatmap peaks exceed 1 (OpenPose writes up to about 1.04): clipped, said once per call
        # (or once per file, by the caller that passed a tally).
        if clipped is None:
            where = next((w for w in (source, file) if w is not None), "detections")
            tally = ClippedScores()
            tally.add(score32)
            warn_clipped(where, tally, stacklevel=2)
        else:
            clipped.add(score32)
        score32 = np.minimum(score32, 1.0)
    return coords32, score32


def _number(v) -> str:
    """A value as a user reads it (no numpy repr such as ``np.float64(1.02)``)."""
    try:
        return repr(float(v))
    except (TypeError, ValueError):
        return repr(v)


def check_recording(
    rec: Recording, *, file: object = None, clipped: ClippedScores | None = None
) -> None:
    """Validates the values of a `Recording` (writers call it before writing, the npz reader after).

    Checks: counts within [0, P]; padding rows with score 0; detections through `check_keypoints`;
    identities in [-1, G) and pointing at a person present in that frame; ground truth finite
    where valid and keypoint_valid only where valid; finite timestamps and projections.
    ``clipped``: as in `check_keypoints`.

    Raises:
      InputError naming file, frame, camera and field (the `Recording` attribute).
    """
    det = rec.detections
    xy, score, count = np.asarray(det.xy), np.asarray(det.score), np.asarray(det.count)
    F, C, P, K = score.shape
    cam = rec.cameras

    def at(flat: int, shape: tuple[int, ...]) -> tuple[int, ...]:
        return tuple(int(v) for v in np.unravel_index(flat, shape))

    def locate_fcp(i: int):
        f, c, p = at(i, (F, C, P))
        return f, cam[c], p

    if count.shape != (F, C) or not np.issubdtype(count.dtype, np.integer):
        raise InputError(
            f"count must be ({F}, {C}) integers, got {count.dtype} {count.shape}",
            file=file,
            field="count",
        )
    bad = (count < 0) | (count > P)
    if bad.any():
        f, c = np.argwhere(bad)[0]
        raise InputError(
            f"count {int(count[f, c])} is outside [0, {P}]",
            file=file,
            frame=int(f),
            camera=cam[c],
            field="count",
        )
    is_row = np.arange(P) < count[..., None]  # (F, C, P)
    pad_used = ~is_row & (score > 0).any(-1)
    if pad_used.any():
        f, c, p = np.argwhere(pad_used)[0]
        raise InputError(
            f"person {p} is beyond count {int(count[f, c])} but has scores > 0",
            file=file,
            frame=int(f),
            camera=cam[c],
            field="score",
        )
    check_keypoints(
        xy.reshape(F * C * P, K, 2),
        score.reshape(F * C * P, K),
        num_keypoints=K,
        locate=locate_fcp,
        file=file,
        field="xy",
        score_field="score",
        count_field="xy",
        clipped=clipped,
    )
    if rec.projected is not None:
        check_keypoints(
            np.asarray(rec.projected).reshape(F * C * P, K, 2),
            num_keypoints=K,
            locate=locate_fcp,
            file=file,
            field="projected",
            count_field="projected",
        )
    gt = rec.ground_truth
    G = None
    if gt is not None:
        valid, kvalid = np.asarray(gt.valid), np.asarray(gt.keypoint_valid)
        G = valid.shape[1]
        if valid.dtype != bool or kvalid.dtype != bool:
            raise InputError("ground-truth masks must be booleans", file=file, field="ground_truth")
        stray = kvalid & ~valid[..., None]
        if stray.any():
            f, g, _ = np.argwhere(stray)[0]
            raise InputError(
                f"person {g} is not valid but has valid keypoints",
                file=file,
                frame=int(f),
                field="gt_keypoint_valid",
            )
        xyz = np.where(kvalid[..., None], np.asarray(gt.xyz), 0.0)
        check_keypoints(
            xyz.reshape(F * G, K, 3),
            num_keypoints=K,
            locate=lambda i: (at(i, (F, G))[0], None, at(i, (F, G))[1]),
            file=file,
            field="gt_xyz",
            count_field="gt_xyz",
        )
    if rec.identity is not None:
        ident = np.asarray(rec.identity)
        if not np.issubdtype(ident.dtype, np.integer):
            raise InputError(
                f"identity must be integers, got {ident.dtype}", file=file, field="identity"
            )
        bad = (ident < -1) | (~is_row & (ident != -1))
        if G is not None:
            safe = np.clip(ident, 0, max(G - 1, 0))
            present = (
                np.take_along_axis(np.asarray(gt.valid)[:, None, :].repeat(C, 1), safe, axis=2)
                if G
                else np.zeros_like(bad)
            )
            bad |= (ident >= G) | ((ident >= 0) & ~present)
        if bad.any():
            f, c, p = np.argwhere(bad)[0]
            raise InputError(
                f"identity {int(ident[f, c, p])} of person {p} is not -1 or a ground-truth person "
                "present in the frame (padding rows must be -1)",
                file=file,
                frame=int(f),
                camera=cam[c],
                field="identity",
            )
    if rec.timestamps is not None:
        ts = np.asarray(rec.timestamps)
        if ts.shape != (F,) or ts.dtype.kind not in "fiu":
            raise InputError(
                f"timestamps must be ({F},) numbers, got {ts.dtype} {ts.shape}",
                file=file,
                field="timestamps",
            )
        bad = ~np.isfinite(ts.astype(np.float64))
        if bad.any():
            raise InputError(
                "timestamp is not finite", file=file, frame=int(np.argmax(bad)), field="timestamps"
            )
    if rec.image_names is not None and np.shape(rec.image_names) != (F, C):
        raise InputError(f"image_names must be ({F}, {C})", file=file, field="image_names")


# --------------------------------------------------------------------------- shared building


def check_padding(
    shape: Sequence[int], *, content: int, file: object = None, field: str | None = None
) -> None:
    """Refuses padded arrays far larger than what the file holds (see PADDING_FLOOR).

    Args:
      shape: the padded shape about to be allocated.
      content: how many values (or entries) of the file fill it.
    Raises:
      InputError when the array would exceed both PADDING_FLOOR values and PADDING_RATIO values
      per value of content.
    """
    size = math.prod(int(n) for n in shape)
    if size > PADDING_FLOOR and size > PADDING_RATIO * content:
        raise InputError(
            f"padding {content} values read from the file to shape {tuple(shape)} would allocate "
            f"{size} values; refused: a padded array beyond {PADDING_FLOOR} values needs one value "
            f"from the file per {PADDING_RATIO} (many empty frames or cameras, or one view with "
            "far more people than the others, make a recording this sparse)",
            file=file,
            field=field,
        )


def pack_detections(
    xy: np.ndarray,
    score: np.ndarray,
    index: tuple[np.ndarray, np.ndarray, np.ndarray],
    *,
    num_frames: int,
    num_cameras: int,
    file: object = None,
) -> Detections:
    """Scatters a flat batch of checked skeletons into padded `Detections`.

    Args:
      xy: (N, K, 2) float32 pixels; score: (N, K) float32 (0 = missing).
      index: (frame, camera, person) int arrays (N,) each: where each skeleton goes.
      num_frames, num_cameras: F and C.
      file: the file the skeletons came from, for errors.
    Returns:
      numpy `Detections` with P = max(1, most people in a view); missing keypoints get xy = 0.
    Raises:
      InputError when the padded arrays would be far larger than the skeletons (`check_padding`).
    """
    f, c, p = index
    N, K = xy.shape[:2]
    # Frames and cameras each take bytes in every format: they count as content of the (F, C) grid.
    check_padding(
        (num_frames, num_cameras), content=N + num_frames + num_cameras, file=file, field="frames"
    )
    count = np.zeros((num_frames, num_cameras), np.int32)
    if len(f):
        np.maximum.at(count, (f, c), p.astype(np.int32) + 1)
    P = max(1, int(count.max(initial=0)))
    check_padding((num_frames, num_cameras, P, K), content=N * K, file=file, field="detections")
    out_xy = np.zeros((num_frames, num_cameras, P, K, 2), np.float32)
    out_score = np.zeros((num_frames, num_cameras, P, K), np.float32)
    out_xy[f, c, p] = np.where(score[..., None] > 0, xy, 0.0)
    out_score[f, c, p] = score
    return Detections(out_xy, out_score, count)


def scatter_rows(
    values: np.ndarray, index: tuple[np.ndarray, ...], shape: tuple[int, ...], fill: Any
) -> np.ndarray:
    """Places per-row ``values`` (N, ...) at ``index`` in a new (*shape, *tail) array."""
    values = np.asarray(values)
    out = np.full(tuple(shape) + values.shape[1:], fill, dtype=values.dtype)
    out[index] = values
    return out


def number_rows(
    entries: Any, width: int, *, allow_null: bool, bad: Callable[[int | None, str], InputError]
) -> tuple[np.ndarray, np.ndarray]:
    """Converts a JSON list of ``width``-number rows (``null`` = missing if allowed) to arrays.

    Counts and values are checked later by `check_keypoints`; this only checks the structure.

    Args:
      entries: the parsed JSON value, expected a list of lists of numbers.
      width: numbers per row.
      allow_null: whether a ``null`` row is accepted (as missing).
      bad: makes the error for a row index (None: the whole list) and a reason.
    Returns:
      values (K', width) float64 (missing rows 0) and present (K',) bool.
    """
    if not isinstance(entries, list):
        raise bad(None, f"expected a list, got {type(entries).__name__}")
    # Fast path: a well-formed list converts in one call (numbers only: strings and nulls give
    # other dtypes, bools alone give 'b', ragged rows raise).
    try:
        arr = np.array(entries)
    except (ValueError, TypeError, OverflowError):
        arr = None
    if arr is not None and arr.dtype.kind in "fi" and arr.shape == (len(entries), width):
        return arr.astype(np.float64), np.ones(len(entries), bool)
    values = np.zeros((len(entries), width), np.float64)
    present = np.ones(len(entries), bool)
    for k, row in enumerate(entries):
        if row is None and allow_null:
            present[k] = False
            continue
        if not isinstance(row, list) or len(row) != width or not all(is_number(v) for v in row):
            raise bad(
                k, f"expected {width} numbers{' or null' if allow_null else ''}, got {_short(row)}"
            )
        values[k] = [to_float(v) for v in row]
    return values, present


def load_json(path: str | os.PathLike) -> Any:
    """Parses a detections JSON file.

    Unlike `mvpose_jax.data.files.read_json`, NaN and Infinity are let through so that the
    keypoint checks can report WHERE they are (frame, camera, field), not only that they exist.
    """
    text = _read_text(path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(
            f"malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}", file=path
        ) from None
    except RecursionError:
        raise InputError("JSON nested too deeply", file=path) from None
    except ValueError as e:  # e.g. an integer beyond Python's digit limit for str -> int
        raise InputError(f"unreadable JSON ({e})", file=path) from None


def parse_json_string(text: str, *, bad: Callable[[str], InputError]) -> Any:
    """Parses JSON embedded in a string field (the original format's skeletons)."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise bad(f"malformed embedded JSON at column {e.colno}: {e.msg}") from None
    except RecursionError:
        raise bad("embedded JSON nested too deeply") from None
    except ValueError as e:  # e.g. an integer beyond Python's digit limit for str -> int
        raise bad(f"unreadable embedded JSON ({e})") from None


def float_lists(values: np.ndarray, unit: float = 1.0) -> list:
    """float32 values as nested lists of Python floats that print short and read back exactly.

    Each value ``x`` becomes the double nearest to the shortest decimal ``d`` of 6 to 9
    significant digits with ``float32(d / unit) == x``, so `json` writes e.g. ``512.3`` rather
    than the exact double ``512.29998779296875``: files shrink by about 40 % and parse faster, and
    a reader dividing by ``unit`` gets bit-identical float32 values. (Starting at 6 digits loses
    nothing: when a shorter decimal works, ``x`` lies so close to it that rounding to 6 digits
    gives that same number, which `json` then prints short.) Values outside about 1e-13..1e22
    (after scaling) keep the exact double ``x * unit``.

    Args:
      values: array of any shape (cast to float32).
      unit: written value per stored unit, e.g. 100 to write metres as centimetres; ``x * unit``
        must be exact in float64 and divide back to ``x`` (true for powers of ten up to 1e6).
    Returns:
      Nested lists shaped like ``values``.
    """
    x = np.asarray(values, np.float32).ravel()
    x64 = x.astype(np.float64) * unit
    out = x64.copy()
    todo = np.flatnonzero(np.isfinite(x) & (x != 0))
    with np.errstate(all="ignore"):
        exp10 = np.floor(np.log10(np.abs(x64[todo]))).astype(np.int64)
        for digits in range(6, 10):
            if not todo.size:
                break
            # Scale so that `digits` significant digits are left of the point, round, scale back.
            # Powers of ten up to 1e22 are exact doubles, and one division (or multiplication) of
            # an exact integer by one is correctly rounded: r is the double nearest the decimal.
            k = digits - 1 - exp10
            scale = 10.0 ** np.minimum(np.abs(k), 22)
            v = x64[todo]
            r = np.where(k >= 0, np.round(v * scale) / scale, np.round(v / scale) * scale)
            hit = (np.abs(k) <= 22) & ((r / unit).astype(np.float32) == x[todo])
            out[todo[hit]] = r[hit]
            todo, exp10 = todo[~hit], exp10[~hit]
    return out.reshape(np.shape(values)).tolist()


# --------------------------------------------------------------------------- small helpers


def is_number(v: Any) -> bool:
    """A JSON number: int or float, not a bool (an int subclass in Python, but not a coordinate)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def to_float(v: float) -> float:
    """float(v), but inf for an integer beyond float range (reported later as not finite)."""
    try:
        return float(v)
    except OverflowError:
        return np.inf if v > 0 else -np.inf


def is_int(v: Any) -> bool:
    """A JSON integer (not a bool, not a float)."""
    return isinstance(v, int) and not isinstance(v, bool)


def is_finite_number(v: Any) -> bool:
    """A JSON number (not a bool) that is finite."""
    return is_number(v) and bool(np.isfinite(to_float(v)))


def _short(v: Any, limit: int = 60) -> str:
    text = repr(v)
    return text if len(text) <= limit else text[: limit - 1] + "…"
