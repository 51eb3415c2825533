"""Tracked 3D poses filtered per track and their short gaps filled (`smoothing.smooth_poses`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from mvpose_jax.data.recording import recording_fps
from mvpose_jax.errors import InputError

if TYPE_CHECKING:
    from mvpose_jax.smoothing import OneEuroConfig


@dataclasses.dataclass(frozen=True)
class SmoothingOptions:
    """The filter and gap filling of ``infer`` and ``smooth``.

    Attributes:
      filter: "none", "one-euro" or "butterworth".
      cutoff_hz: Butterworth cut-off (Hz).
      fill_gap_s: fill gaps of a track's keypoints up to this long (s; 0: none).
      outlier_m: drop samples further than this (m) from their 7-frame median (0: keep all).
      min_cutoff: One-Euro cut-off when still (Hz); beta: its rise per speed (Hz per m/s).
      fps: frame rate (None: the recording's, from its timestamps).
    """

    filter: str = "butterworth"
    cutoff_hz: float = 2.0
    fill_gap_s: float = 0.5
    outlier_m: float = 0.1
    min_cutoff: float = 1.0
    beta: float = 7.0
    fps: float | None = None


def smoothing_settings(options: SmoothingOptions) -> tuple[OneEuroConfig, dict[str, Any]]:
    """``options`` checked, as (OneEuroConfig, `smooth_poses` keyword arguments)."""
    from mvpose_jax.smoothing import OneEuroConfig

    for name in ("cutoff_hz", "min_cutoff", "fps"):
        value = getattr(options, name)
        if value is not None and value <= 0:
            raise InputError("must be > 0", field="--" + name.replace("_", "-"))
    for name in ("fill_gap_s", "outlier_m", "beta"):
        if getattr(options, name) < 0:
            raise InputError("must be >= 0", field="--" + name.replace("_", "-"))
    one_euro = OneEuroConfig(min_cutoff_hz=options.min_cutoff, beta=options.beta)
    return one_euro, {
        "cutoff_hz": options.cutoff_hz,
        "fill_gap_s": options.fill_gap_s,
        "outlier_m": options.outlier_m or None,
        "one_euro": one_euro,
    }


@dataclasses.dataclass(frozen=True)
class SmoothConfig:
    """Attributes: poses (infer's poses.npz / poses.json or their folder), out (a folder), and
    the smoothing."""

    poses: str
    out: str
    smoothing: SmoothingOptions = SmoothingOptions()


class Smoothed(NamedTuple):
    """What was written: frames, tracks, the frame rate used, keypoints filled, the files."""

    frames: int
    tracks: int
    fps: float
    filled: int
    json: Path
    npz: Path


def smooth(config: SmoothConfig) -> Smoothed:
    """Reads the poses, smooths them and writes poses.json and poses.npz in ``config.out``."""
    import numpy as np

    from mvpose_jax.data.files import check_writable
    from mvpose_jax.data.poses import load_poses, save_poses
    from mvpose_jax.smoothing import smooth_poses

    check_writable(config.out, folder=True)
    _, smooth_kwargs = smoothing_settings(config.smoothing)
    poses = load_poses(config.poses)
    fps = config.smoothing.fps or recording_fps(poses.timestamps)
    try:
        out = smooth_poses(poses, fps=fps, filter=config.smoothing.filter, **smooth_kwargs)
    except InputError as e:
        raise e.at(file=config.poses) from None
    npz_path, json_path = save_poses(out, config.out)
    tracks = len(np.unique(out.track[out.poses.valid & (out.track >= 0)]))
    return Smoothed(len(out.confidence), tracks, fps, int(out.filled.sum()), json_path, npz_path)
