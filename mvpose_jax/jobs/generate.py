"""Synthetic recordings on any rig (`generate`) and the one-frame figure of one
(`synthetic_figure`)."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.jobs.common import DetectionsSource, RigSource, fit_detector_to, measure_floor

if TYPE_CHECKING:
    from mvpose_jax.detector_fit import DetectorFit
    from mvpose_jax.floor import FloorEstimate
    from mvpose_jax.synthetic import SyntheticConfig

# Floor jitter of single-person training recordings: the measured or guessed floor may be off by
# a few decimetres, and training on one exact floor ties the models to it.
TRAINING_FLOOR_JITTER_M = 0.3

# Detector rates a caller may set: option name -> `synthetic.DetectorConfig` field.
RATE_OPTIONS = {
    "miss-rate": "miss_rate",
    "false-positive-rate": "false_positive_rate",
    "swap-rate": "swap_rate",
    "occluded-drop-rate": "occluded_drop_rate",
    "keypoint-drop-rate": "keypoint_drop_rate",
    "noise-relative": "noise_relative",
    "offset-scale": "offset_scale",
}


@dataclasses.dataclass(frozen=True)
class GenerateConfig:
    """One synthetic scene, or single-person training recordings, on a rig.

    Attributes:
      rig: the cameras.
      out: output file (.json native, .npz) or, with ``single_person_recordings``, a folder.
      people, frames, seed: the scene's people, frames per recording and random seed.
      single_person_recordings: N > 0: write N one-person recordings into the ``out`` folder.
      format: "native" or "npz" for the single-person recordings (None: native JSON).
      fps: frame rate (Hz).
      floor_height: floor along the up vector (metres); None: measured from ``floor_from``,
        else guessed from the cameras (with a warning).
      floor_from: detections of people on this rig to measure the floor from.
      floor_jitter: each recording's floor within this distance (metres) of the floor height;
        None: `TRAINING_FLOOR_JITTER_M` for single-person recordings, 0 for a scene.
      clean: a perfect detector.
      detector_like: the user's own detections on this rig: the simulated detector is fitted to
        them (`detector_fit.fit_detector`) instead of the default one.
      rates: `DetectorConfig` field -> value, over the (clean, fitted or default) detector.
    """

    rig: RigSource
    out: str
    people: int = 4
    frames: int = 500
    seed: int = 0
    single_person_recordings: int = 0
    format: str | None = None
    fps: float | None = None
    floor_height: float | None = None
    floor_from: DetectionsSource | None = None
    floor_jitter: float | None = None
    clean: bool = False
    detector_like: DetectionsSource | None = None
    rates: Mapping[str, float] = dataclasses.field(default_factory=dict)


class Generated(NamedTuple):
    """What `generate` wrote.

    Attributes:
      out: the file (one scene) or folder (single-person recordings).
      recordings: how many recordings were written.
      frames: frames per recording.
      cameras: cameras per recording.
      detections: detections in the scene (single-person recordings: 0).
      floor: the floor measured from ``floor_from``, or None.
      detector: the detector fitted to ``detector_like``, or None.
    """

    out: Path
    recordings: int
    frames: int
    cameras: int
    detections: int
    floor: FloorEstimate | None
    detector: DetectorFit | None = None


def generate(config: GenerateConfig) -> Generated:
    """Simulates and writes the recordings ``config`` describes (a progress bar on stderr)."""
    from mvpose_jax.data import save_recording
    from mvpose_jax.data.files import check_writable
    from mvpose_jax.synthetic import generate_recording, generate_single_person_recordings

    rig = config.rig.load()
    out = check_writable(config.out, folder=config.single_person_recordings > 0)
    if config.clean and config.detector_like is not None:
        raise InputError("a clean detector or one fitted to a recording, not both", field="--clean")
    measured = measure_floor(rig, config.floor_from) if config.floor_from else None
    fitted = fit_detector_to(rig, config.detector_like) if config.detector_like else None
    synthetic = synthetic_config(config, measured, fitted)
    if synthetic.scene.floor_height is None:
        from mvpose_jax.synthetic import scene_geometry

        guess = scene_geometry(rig, synthetic.scene).floor_height
        warnings.warn(
            f"the floor height is a guess from the camera positions ({guess:.3f} m along up), "
            "which can be half a metre off on a real rig, and models trained on a wrong floor "
            "fail on the real one; pass --floor-height or --floor-from DETECTIONS",
            MvposeWarning,
            stacklevel=2,
        )
    if config.single_person_recordings > 0:
        recordings = generate_single_person_recordings(
            rig,
            num_recordings=config.single_person_recordings,
            num_frames=config.frames,
            config=synthetic,
            seed=config.seed,
            progress=True,
        )
        suffix = ".npz" if config.format == "npz" else ".json"
        width = len(str(len(recordings) - 1))
        for i, rec in enumerate(recordings):
            path = out / f"person_{i:0{width}d}{suffix}"
            save_recording(rec, path, rig=rig if suffix == ".json" else None)
        return Generated(out, len(recordings), config.frames, rig.num_cameras, 0, measured, fitted)
    rec = generate_recording(
        rig,
        num_people=config.people,
        num_frames=config.frames,
        config=synthetic,
        seed=config.seed,
        progress=True,
    )
    native = out.suffix.lower() != ".npz"
    save_recording(rec, out, rig=rig if native else None)
    count = int(rec.detections.count.sum())
    return Generated(out, 1, rec.num_frames, len(rec.cameras), count, measured, fitted)


def synthetic_config(
    config: GenerateConfig,
    measured: FloorEstimate | None = None,
    fitted: DetectorFit | None = None,
) -> SyntheticConfig:
    """The `SyntheticConfig` of ``config`` (``measured``: the floor measured from the people,
    its height used when ``config.floor_height`` is not given, its up when measured from the
    people, the calibration having none; ``fitted``: the detector fitted to the user's
    recording, used instead of the default one)."""
    floor_height = None if measured is None else measured.height
    from mvpose_jax.synthetic import DetectorConfig, MotionConfig, SceneConfig, SyntheticConfig

    detector = DetectorConfig().clean() if config.clean else DetectorConfig()
    if fitted is not None:
        detector = fitted.config
    motion = MotionConfig()
    return SyntheticConfig(
        detector=dataclasses.replace(detector, **config.rates),
        motion=dataclasses.replace(motion, fps=motion.fps if config.fps is None else config.fps),
        scene=dataclasses.replace(
            SceneConfig(),
            floor_height=config.floor_height if config.floor_height is not None else floor_height,
            floor_jitter_m=floor_jitter(config),
            up=None if measured is None else measured.measured_up,
        ),
    )


def floor_jitter(config: GenerateConfig) -> float:
    """The floor jitter (metres) ``config`` asks for, its default filled in."""
    jitter = config.floor_jitter
    if jitter is None:
        return TRAINING_FLOOR_JITTER_M if config.single_person_recordings > 0 else 0.0
    if not jitter >= 0:
        raise InputError(f"must be >= 0, not {jitter}", field="--floor-jitter")
    return jitter


@dataclasses.dataclass(frozen=True)
class SyntheticFigureConfig:
    """One frame of a synthetic recording, drawn (`render.render_frame_figure`).

    Attributes:
      rig: the cameras; people, frames, seed: the simulated recording; frame: the frame drawn
      (negative: from the end); out: the PNG.
    """

    rig: RigSource
    out: str
    people: int = 4
    frames: int = 150
    frame: int = -1
    seed: int = 0


def synthetic_figure(config: SyntheticFigureConfig) -> Path:
    """Simulates a recording and draws one frame of it; returns the PNG written."""
    from mvpose_jax.data.files import check_writable
    from mvpose_jax.render import render_frame_figure
    from mvpose_jax.synthetic import generate_recording

    rig = config.rig.load()
    check_writable(config.out, folder=False)
    rec = generate_recording(
        rig, num_people=config.people, num_frames=config.frames, seed=config.seed
    )
    frame = config.frame % rec.num_frames
    return render_frame_figure(
        rec,
        rig,
        frame,
        config.out,
        title=f"synthetic {config.rig.rig}: {config.people} people, frame {frame}, "
        f"seed {config.seed}",
    )
