"""The ``infer --session`` job: every trial of a Pose2Sim project, each as one ``infer`` run.

A Pose2Sim session, participant or trial folder is read with Pose2Sim's own rules
(`data.pose2sim.find_trials`: configs merged level by level, the calibration found, the detection
folders paired with the calibration's cameras by sorted position). Each trial gets its own output
folder ``OUT/<trial>/`` with ``poses.json`` / ``poses.npz`` and Pose2Sim-named TRC files in
``OUT/<trial>/pose-3d/`` (`data.pose2sim.trc_name`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from mvpose_jax.data.pose2sim import Pose2SimTrial, find_trials, trc_name
from mvpose_jax.inference import PipelineConfig
from mvpose_jax.jobs.common import DetectionsSource, RigSource
from mvpose_jax.jobs.infer import INFER_PIPELINE, InferConfig, InferResult, run_infer


@dataclasses.dataclass(frozen=True)
class SessionConfig:
    """One ``infer --session`` run.

    Attributes:
      session: a Pose2Sim session, participant or trial folder.
      out: the output folder; each trial's results go to ``out/<trial name>/``.
      pipeline, matcher, estimator, resume, keep_chunks, view, progress: as `InferConfig`'s,
        for every trial.
      layout: the keypoint layout to work in (None: coco18, the layout the models use).
      fps: frames per second when the config says ``'auto'`` or nothing (None: 30).
      trc: also write Pose2Sim-named TRC files in ``out/<trial>/pose-3d/``.
    """

    session: str
    out: str
    pipeline: PipelineConfig = INFER_PIPELINE
    matcher: str | None = None
    estimator: str | None = None
    layout: str | None = None
    fps: float | None = None
    trc: bool = True
    resume: bool = False
    keep_chunks: bool = False
    view: bool = False
    progress: bool = True


class TrialResult(NamedTuple):
    """One trial's run: the trial as found, its ``infer`` result, its TRC files and what the
    reader took as it was (`data.stream.ReadReport` lines: empty entries, missing frames)."""

    trial: Pose2SimTrial
    result: InferResult
    trc: tuple[Path, ...]
    read_notes: tuple[str, ...]


def trial_config(config: SessionConfig, trial: Pose2SimTrial) -> InferConfig:
    """The ``infer`` run of one trial."""
    detections = DetectionsSource(
        str(trial.detections),
        layout=config.layout or "coco18",
        # Pose2Sim reads a frame one camera lacks as a frame where it saw nobody.
        missing_frames="empty",
        camera_map=dict(trial.camera_map),
        source_layout=trial.source_layout,
        # Only the paired folders (a pose folder may hold others).
        cameras=trial.cameras,
    )
    return InferConfig(
        RigSource(str(trial.calibration)),
        detections,
        os.path.join(config.out, trial.name),
        config.pipeline,
        matcher=config.matcher,
        estimator=config.estimator,
        fps=trial.fps or config.fps,
        resume=config.resume,
        keep_chunks=config.keep_chunks,
        export=("trc",) if config.trc else (),
        frames=trial.frame_range,
        view=config.view,
        progress=config.progress,
    )


def run_session(
    config: SessionConfig,
    *,
    on_trial: Callable[[Pose2SimTrial], None] = lambda trial: None,
    notify: Callable[[str, str], None] = lambda kind, message: None,
) -> list[TrialResult]:
    """Runs every trial (in sorted order); ``on_trial`` is called before each (e.g. to print its
    camera pairing), ``notify`` as `run_infer`'s. An interrupted trial stops the session (its
    result says so, the trials after it are not run)."""
    session = find_trials(config.session)
    out = []
    for trial in session.trials:
        on_trial(trial)
        done = run_trial(config, trial, notify=notify)
        out.append(done)
        if done.result.interrupted:
            break
    return out


def run_trial(
    config: SessionConfig,
    trial: Pose2SimTrial,
    *,
    notify: Callable[[str, str], None] = lambda kind, message: None,
    models: dict | None = None,
) -> TrialResult:
    """One trial of a session: its ``infer`` run (`trial_config`), the TRC files under
    Pose2Sim's names; what `run_session` and a ``batch`` worker run per trial (``models`` as
    `run_infer`'s)."""
    result = run_infer(trial_config(config, trial), notify=notify, models=models)
    trc = _pose2sim_names(result, trial) if result.exported else ()
    if trc:  # the exports were moved to Pose2Sim's names
        result = result._replace(exported=trc)
    return TrialResult(trial, result, trc, result.read_notes)


def _pose2sim_names(result: InferResult, trial: Pose2SimTrial) -> tuple[Path, ...]:
    """Moves the trial's TRC exports (one per track) to ``pose-3d/`` under Pose2Sim's names:
    ``<trial>_<first>-<stop>.trc`` for one person, ``<trial>_P<n>_...`` (n from 1, in track
    order) for several."""
    trcs = sorted(
        (p for p in result.exported if p.suffix == ".trc"),
        key=lambda p: int(p.stem.rsplit("_track", 1)[1]),
    )
    if not trcs:
        return ()
    folder = trcs[0].parent / "pose-3d"
    folder.mkdir(exist_ok=True)
    out = []
    for n, path in enumerate(trcs, start=1):
        person = None if len(trcs) == 1 else n
        first = trial.frame_range[0] if trial.frame_range is not None else 0
        target = folder / trc_name(trial.name, first, first + result.frames_total, person)
        os.replace(path, target)
        out.append(target)
    return tuple(out)
