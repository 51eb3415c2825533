"""Calibration files and rig presets.

Formats read (``load_rig`` picks by content):
  * native JSON (DESIGN.md §2): ``{"cameras": [{"name", "width", "height", "K", "dist", "R", "t"}],
    "up"?}`` with ``x_cam = R x_world + t`` in metres, ``dist`` = [k1, k2, p1, p2, k3];
  * CMU Panoptic JSON: ``{"cameras": [{"name", "resolution", "K", "distCoef", "R", "t"}]}`` with
    ``t`` in centimetres (converted to metres); select cameras by name;
  * anipose / Pose2Sim TOML: ``[cam_N]`` tables with ``name``, ``size`` [w, h], ``matrix``,
    ``distortions``, ``rotation`` (Rodrigues vector) and ``translation``; ``translation_scale``
    converts its length unit to metres (anipose uses the board's unit, often millimetres).
Presets ``panoptic5`` and ``arplab6`` are the paper's real rigs, shipped as package data.
"""

from __future__ import annotations

import importlib.resources
import json
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mvpose_jax.cameras import Rig, make_rig, rig_centre_and_radius
from mvpose_jax.data.files import atomic_write_text, read_json, read_toml
from mvpose_jax.errors import InputError, MvposeWarning

PRESETS = ("panoptic5", "arplab6")


def load_preset(name: str, cameras: Sequence[str] | None = None) -> Rig:
    """A rig preset shipped with the package (``panoptic5`` or ``arplab6``)."""
    if name not in PRESETS:
        raise InputError(f"unknown rig preset {name!r}; presets: {list(PRESETS)}", field="rig")
    resource = importlib.resources.files("mvpose_jax.data") / "rigs" / f"{name}.json"
    with importlib.resources.as_file(resource) as path:
        rig = rig_from_dict(read_json(path), file=f"preset:{name}")
    return rig if cameras is None else rig.select(cameras)


def load_rig(
    source: str | os.PathLike | Rig,
    cameras: Sequence[str] | None = None,
    *,
    translation_scale: float = 1.0,
    orthonormalise: bool = False,
) -> Rig:
    """Loads a rig from a preset name or a calibration file in any supported format.

    Args:
      source: a preset name, a path (``.json`` native or Panoptic, ``.toml``), or a Rig.
      cameras: optional camera names to keep, in this order.
      translation_scale: TOML only: metres per unit of its translations (0.001 for millimetres);
        must be a positive number.
      orthonormalise: replace each R by its nearest rotation (calibrations written with few
        decimals), with a `CalibrationWarning` giving the largest change.
    Raises:
      InputError naming the file, camera and field on any problem.
    Warns:
      `CalibrationWarning` when the cameras are over 100 m or under 0.1 m from their centre
      (translations in another unit than metres).
    """
    if not (math.isfinite(translation_scale) and translation_scale > 0):
        raise InputError(
            f"the translation scale must be a positive number, not {translation_scale!r}",
            field="translation_scale",
        )
    if isinstance(source, Rig):
        rig = source
    elif isinstance(source, str) and source in PRESETS:
        rig = load_preset(source)
    else:
        path = Path(source)
        if path.suffix.lower() == ".toml":
            rig = rig_from_toml(
                read_toml(path),
                file=path,
                translation_scale=translation_scale,
                orthonormalise=orthonormalise,
            )
        else:
            data = read_json(path)
            if _is_panoptic(data):
                rig = rig_from_panoptic(
                    data, file=path, cameras=cameras, orthonormalise=orthonormalise
                )
            else:
                rig = rig_from_dict(data, file=path, orthonormalise=orthonormalise)
        _warn_about_units(rig, path)
    if cameras is not None:
        try:
            rig = rig.select(cameras)
        except InputError as e:
            raise e.at(file=None if isinstance(source, Rig) else source) from None
    return rig


# Orthonormalising repairs rotations written with few decimals (4 decimals: about 1e-4 off);
# a larger change means a wrong matrix, which it must not hide.
MAX_ORTHONORMALISE_CHANGE = 1e-2


class CalibrationWarning(MvposeWarning):
    """A calibration that loads but is probably not what its author meant (or was changed)."""


def _warn_about_units(rig: Rig, path: Path) -> None:
    if rig.num_cameras < 2:
        return
    _, radius = rig_centre_and_radius(rig)
    radius = float(radius)
    if radius > 100:
        hint = "are the translations in millimetres? pass --translation-scale 0.001"
    elif radius < 0.1:
        hint = "are the translations in metres? check the file's unit"
    else:
        return
    warnings.warn(
        f"{path}: the cameras are {radius:.3g} m from their centre; {hint}",
        CalibrationWarning,
        stacklevel=3,
    )


def save_rig(rig: Rig, path: str | os.PathLike, description: str | None = None) -> None:
    """Writes a rig as native calibration JSON, atomically."""
    atomic_write_text(path, json.dumps(rig_to_dict(rig, description), indent=1) + "\n")


def rig_to_dict(rig: Rig, description: str | None = None) -> dict[str, Any]:
    """The native calibration dict of a rig."""
    out: dict[str, Any] = {}
    if description:
        out["description"] = description
    if rig.up is not None:
        out["up"] = list(rig.up)
    arr = lambda a, c: np.asarray(a, np.float64)[c].tolist()  # noqa: E731
    out["cameras"] = [
        {
            "name": name,
            "width": int(round(float(rig.size[c, 0]))),
            "height": int(round(float(rig.size[c, 1]))),
            "K": arr(rig.K, c),
            "dist": arr(rig.dist, c),
            "R": arr(rig.R, c),
            "t": arr(rig.t, c),
        }
        for c, name in enumerate(rig.names)
    ]
    return out


def rig_from_dict(data: Any, *, file: object = None, orthonormalise: bool = False) -> Rig:
    """Builds a rig from a native calibration dict (see module docstring)."""
    cams = _camera_list(data, file)
    names, K, dist, R, t, size = [], [], [], [], [], []
    for i, cam in enumerate(cams):
        name = _camera_name(cam, i, file)
        names.append(name)
        get = lambda key: _field(cam, key, file, name)  # noqa: E731
        K.append(_matrix(get("K"), (3, 3), file, name, "K"))
        dist.append(_vector(get("dist"), (4, 5), file, name, "dist"))
        R.append(_matrix(get("R"), (3, 3), file, name, "R"))
        t.append(_vector(get("t"), (3,), file, name, "t"))
        size.append(
            [
                _number(get("width"), file, name, "width"),
                _number(get("height"), file, name, "height"),
            ]
        )
    up = data.get("up")
    up = None if up is None else _up(up, file)
    return _make_rig(K, dist, R, t, size, names, up, file, orthonormalise)


def rig_from_panoptic(
    data: Any,
    *,
    file: object = None,
    cameras: Sequence[str] | None = None,
    orthonormalise: bool = False,
) -> Rig:
    """Builds a rig from a CMU Panoptic calibration dict (``t`` in centimetres).

    Panoptic's world has its y axis pointing down, so ``up`` is (0, -1, 0).
    """
    cams = _camera_list(data, file)
    by_name = {}
    for i, cam in enumerate(cams):
        by_name.setdefault(_camera_name(cam, i, file), cam)
    wanted = list(by_name) if cameras is None else [str(c) for c in cameras]
    names, K, dist, R, t, size = [], [], [], [], [], []
    for name in wanted:
        if name not in by_name:
            raise InputError(
                f"unknown camera; the file has {sorted(by_name)[:12]}{' …' if len(by_name) > 12 else ''}",
                file=file,
                camera=name,
            )
        cam = by_name[name]
        get = lambda key: _field(cam, key, file, name)  # noqa: E731
        names.append(name)
        K.append(_matrix(get("K"), (3, 3), file, name, "K"))
        dist.append(_vector(get("distCoef"), (4, 5), file, name, "distCoef"))
        R.append(_matrix(get("R"), (3, 3), file, name, "R"))
        t.append(_vector(get("t"), (3,), file, name, "t") / 100.0)
        size.append(_vector(get("resolution"), (2,), file, name, "resolution"))
    return _make_rig(K, dist, R, t, size, names, (0.0, -1.0, 0.0), file, orthonormalise)


def rig_from_toml(
    data: Any, *, file: object = None, translation_scale: float = 1.0, orthonormalise: bool = False
) -> Rig:
    """Builds a rig from an anipose / Pose2Sim calibration dict (parsed TOML)."""
    if not isinstance(data, dict):
        raise InputError("expected TOML tables", file=file)
    tables = [(k, v) for k, v in data.items() if k != "metadata" and isinstance(v, dict)]
    if not tables:
        raise InputError("no camera tables (e.g. [cam_1]) found", file=file, field="cameras")
    names, K, dist, R, t, size = [], [], [], [], [], []
    for key, cam in tables:
        name = cam.get("name", key)
        if not isinstance(name, str) or not name:
            raise InputError(
                f"expected a non-empty string, got {name!r}"[:200],
                file=file,
                camera=key,
                field="name",
            )
        get = lambda field: _field(cam, field, file, name)  # noqa: E731
        fisheye = cam.get("fisheye", False)
        if not isinstance(fisheye, bool):
            raise InputError(
                f"expected true or false, got {fisheye!r}"[:200],
                file=file,
                camera=name,
                field="fisheye",
            )
        if fisheye:
            raise InputError(
                "fisheye calibrations are not supported", file=file, camera=name, field="fisheye"
            )
        names.append(name)
        size.append(_vector(get("size"), (2,), file, name, "size"))
        K.append(_matrix(get("matrix"), (3, 3), file, name, "matrix"))
        dist.append(_vector(get("distortions"), (4, 5), file, name, "distortions"))
        R.append(rodrigues(_vector(get("rotation"), (3,), file, name, "rotation")))
        t.append(_vector(get("translation"), (3,), file, name, "translation") * translation_scale)
    return _make_rig(K, dist, R, t, size, names, None, file, orthonormalise)


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a Rodrigues (axis * angle) vector, as cv2.Rodrigues. (3,) -> (3, 3)."""
    rvec = np.asarray(rvec, np.float64)
    theta = np.linalg.norm(rvec)
    if theta < 1e-12:
        return np.eye(3)
    k = rvec / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * (kx @ kx)


# --------------------------------------------------------------------------- parsing helpers


def _is_panoptic(data: Any) -> bool:
    cams = data.get("cameras") if isinstance(data, dict) else None
    return (
        bool(cams)
        and isinstance(cams, list)
        and isinstance(cams[0], dict)
        and "distCoef" in cams[0]
    )


def _camera_list(data: Any, file: object) -> list:
    if not isinstance(data, dict):
        raise InputError("expected a JSON object with a 'cameras' list", file=file)
    cams = data.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise InputError("expected a non-empty list", file=file, field="cameras")
    return cams


def _camera_name(cam: Any, i: int, file: object) -> str:
    if not isinstance(cam, dict):
        raise InputError("expected an object", file=file, camera=i, field=f"cameras[{i}]")
    name = cam.get("name")
    if not isinstance(name, (str, int)) or isinstance(name, bool) or str(name) == "":
        raise InputError("missing or invalid camera name", file=file, camera=i, field="name")
    return str(name)


def _field(cam: dict, key: str, file: object, name: str) -> Any:
    if key not in cam:
        raise InputError("missing field", file=file, camera=name, field=key)
    return cam[key]


def _make_rig(K, dist, R, t, size, names, up, file: object, orthonormalise: bool = False) -> Rig:
    """`make_rig`, once every number is known to be finite in float32 (the rig's precision);
    with ``orthonormalise``, each R replaced first by its nearest rotation (`nearest_rotation`)."""
    R_in = R
    for field, values in (("K", K), ("dist", dist), ("R", R), ("t", t), ("size", size)):
        for name, v in zip(names, values, strict=False):
            with np.errstate(over="ignore"):
                finite = np.isfinite(np.asarray(v, np.float32)).all()
            if not finite:
                raise InputError(
                    "a number is beyond float32 range", file=file, camera=name, field=field
                )
    if orthonormalise:
        R = [nearest_rotation(np.asarray(r, np.float64)) for r in R]
        changes = [
            float(np.abs(new - np.asarray(old, np.float64)).max())
            for new, old in zip(R, R_in, strict=True)
        ]
        worst = int(np.argmax(changes))
        if changes[worst] > MAX_ORTHONORMALISE_CHANGE:
            raise InputError(
                f"R is far from a rotation (its nearest rotation differs by {changes[worst]:.2g}); "
                "orthonormalising fixes rounding, not a wrong matrix",
                file=file,
                camera=names[worst],
                field="R",
            )
        warnings.warn(
            f"{file or 'calibration'}: R of {len(R)} cameras replaced by the nearest rotations "
            f"(largest change {changes[worst]:.2g}, camera {names[worst]})",
            CalibrationWarning,
            stacklevel=3,
        )
    return make_rig(K, _pad5(dist), R, t, size, names, up, file=file)


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to a 3x3 matrix in the Frobenius norm (SVD: U V^T), for R written
    with few decimals. A reflection stays a reflection (det -1), for `make_rig` to refuse."""
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def _up(value: Any, file: object) -> tuple[float, float, float]:
    """The native format's optional world up vector: 3 finite numbers, not all zero."""
    u = _vector(value, (3,), file, None, "up")
    scale = np.abs(u).max()
    if not scale > 0:
        raise InputError("up must be a non-zero 3-vector", file=file, field="up")
    return tuple(float(x) for x in u / scale)  # scaled first: its norm cannot overflow


def _array(value: Any, file: object, name: str | None, field: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise InputError("expected numbers", file=file, camera=name, field=field) from None
    if not np.all(np.isfinite(arr)):
        raise InputError("contains NaN or infinity", file=file, camera=name, field=field)
    return arr


def _matrix(value: Any, shape: tuple[int, int], file: object, name: str, field: str) -> np.ndarray:
    arr = _array(value, file, name, field)
    if arr.shape != shape:
        raise InputError(
            f"expected a {shape[0]}x{shape[1]} matrix, got shape {arr.shape}",
            file=file,
            camera=name,
            field=field,
        )
    return arr


def _vector(
    value: Any, sizes: tuple[int, ...], file: object, name: str | None, field: str
) -> np.ndarray:
    arr = _array(value, file, name, field)
    if arr.ndim == 2 and arr.shape[1] == 1:  # Panoptic stores t as a column, [[x], [y], [z]]
        arr = arr[:, 0]
    if arr.ndim != 1 or arr.shape[0] not in sizes:
        raise InputError(
            f"expected {' or '.join(map(str, sizes))} numbers, got shape {arr.shape}",
            file=file,
            camera=name,
            field=field,
        )
    return arr


def _number(value: Any, file: object, name: str, field: str) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    try:
        ok = ok and bool(np.isfinite(float(value)))
    except OverflowError:  # an integer beyond float range
        ok = False
    if not ok:
        raise InputError("expected a finite number", file=file, camera=name, field=field)
    return float(value)


def _pad5(dist: list[np.ndarray]) -> np.ndarray:
    return np.stack([np.pad(d, (0, 5 - d.shape[0])) for d in dist])
