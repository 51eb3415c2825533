"""Training jobs: a matcher or an estimator model folder from single-person recordings.

`train_matcher_job` also chooses the proposals' settings on multi-person frames composed from the
dev recordings and writes them into the folder; `train_estimator_job` leaves the comparison with
triangulation on the dev people there (`train.compare_with_triangulation`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from mvpose_jax.errors import InputError
from mvpose_jax.jobs.common import RigSource, read_dev_quality, recordings_in

if TYPE_CHECKING:
    from mvpose_jax.proposals import CombinedConfig


@dataclasses.dataclass(frozen=True)
class TrainingRun:
    """What every training job shares: data, output folder, devices and checkpoints.

    Attributes:
      rig: the cameras.
      train: single-person recordings (a file, an OpenPose folder, or a folder of them).
      dev: validation recordings, as ``train`` (the estimator: None takes the last 10% of the
        training people).
      out: the model folder (best and latest checkpoints).
      layout: keypoint layout to convert the recordings to (None: theirs).
      source_layout: OpenPose folders' keypoint layout (None: from the count).
      seed: initialisation, sample order and augmentation.
      devices: data-parallel devices, a count or "all" (None: one).
      checkpoint_every: steps between saves of the latest state (0: only at validations).
      coordinator_address, num_processes, process_id: several hosts (`parallel`).
      resume: continue from the latest checkpoint in ``out``.
    """

    rig: RigSource
    train: str
    dev: str | None
    out: str
    layout: str | None = None
    source_layout: str | None = None
    seed: int = 0
    devices: int | str | None = None
    checkpoint_every: int = 500
    coordinator_address: str | None = None
    num_processes: int | None = None
    process_id: int | None = None
    resume: bool = False


@dataclasses.dataclass(frozen=True)
class MatcherJob:
    """A matcher's training (`trained.MatcherConfig` with these changes; None keeps its value).

    Attributes:
      run: data, folder, devices.
      cameras: inference cameras C_i (None: every camera of the rig).
      quick: `MatcherConfig.quick()` instead of the paper's.
      max_epochs, learning_rate, max_people, keypoint_dropout: overrides.
      start: fine-tune this rig-agnostic matcher (a model folder, or "pretrained": the one
        shipped in the package) on the rig's cameras instead of training a new network; its
        network replaces ``quick``'s.
    """

    run: TrainingRun
    cameras: tuple[str, ...] | None = None
    quick: bool = False
    max_epochs: int | None = None
    learning_rate: float | None = None
    max_people: int | None = None
    keypoint_dropout: float | None = None
    start: str | None = None


class ProposalChoice(NamedTuple):
    """The proposals' settings chosen on composed dev frames (`proposals.write_proposal_threshold`).

    Attributes:
      threshold: the GAT's threshold; ari: threshold -> ARI on the composed frames.
      combined: the combined matcher's settings; combined_ari: its threshold -> ARI.
    """

    threshold: float
    ari: dict
    combined: CombinedConfig
    combined_ari: dict


class MatcherTrained(NamedTuple):
    """A matcher's training: validation loss, steps, seconds, folder, and the proposal settings
    chosen (None on every process but the first of several hosts)."""

    best_val_loss: float
    steps: int
    seconds: float
    out: str
    proposals: ProposalChoice | None


def train_matcher_job(job: MatcherJob) -> MatcherTrained:
    """Trains the matcher into ``job.run.out`` and writes its chosen proposal settings there."""
    from mvpose_jax.matcher_settings import choose_matcher_settings
    from mvpose_jax.matcher_training import train_matcher
    from mvpose_jax.parallel import resolve_num_devices
    from mvpose_jax.trained import MatcherConfig, load_matcher, write_proposal_threshold

    run = job.run
    rig = _begin(run)
    config = MatcherConfig.quick() if job.quick else MatcherConfig()
    train = dataclasses.replace(
        config.train,
        seed=run.seed,
        num_devices=resolve_num_devices(run.devices),
        checkpoint_every_steps=run.checkpoint_every,
        **{
            k: v
            for k, v in (("max_epochs", job.max_epochs), ("learning_rate", job.learning_rate))
            if v is not None
        },
    )
    config = dataclasses.replace(
        config,
        train=train,
        cameras=tuple(job.cameras) if job.cameras else None,
        **({"max_people": job.max_people} if job.max_people else {}),
        **({"keypoint_dropout": job.keypoint_dropout} if job.keypoint_dropout is not None else {}),
    )
    if not 0 <= config.keypoint_dropout < 1:
        raise InputError(
            f"--keypoint-dropout must be in [0, 1), not {config.keypoint_dropout}",
            field="keypoint_dropout",
        )
    train_recs = recordings_in(run.train, run.layout, run.source_layout)
    dev_recs = recordings_in(run.dev, run.layout, run.source_layout)
    start = None
    if job.start:
        start = load_matcher(job.start, rig.select(list(config.cameras or rig.names)))
    matcher, fit = train_matcher(
        rig, train_recs, dev_recs, config, checkpoint_dir=run.out, resume=run.resume, start=start
    )
    import jax

    choice = None
    if jax.process_index() == 0:
        chosen = choose_matcher_settings(matcher, dev_recs, seed=run.seed)
        write_proposal_threshold(
            run.out,
            chosen.threshold,
            chosen.ari_by_threshold,
            chosen.composed_frames,
            combined=chosen.combined,
            combined_ari=chosen.ari_by_combined_threshold,
        )
        choice = ProposalChoice(
            chosen.threshold,
            chosen.ari_by_threshold,
            chosen.combined,
            chosen.ari_by_combined_threshold,
        )
        write_model_pipeline(run.out, matcher=True)
    return MatcherTrained(fit.best_val_loss, fit.steps, fit.seconds, run.out, choice)


@dataclasses.dataclass(frozen=True)
class EstimatorJob:
    """An estimator's training (`trained.EstimatorConfig`).

    Attributes:
      run: data, folder, devices.
      train_cameras: training cameras C_t (None: every camera of the rig).
      infer_cameras: inference cameras C_i, a subset of C_t (None: C_t).
      paper_size: the paper's MLP widths (else `MLPConfig.quick()`'s).
      output: what the MLP predicts ("absolute", "anchored", "residual"; `models.MLPConfig`).
      loss_power: per-sample loss e^power.
      augment: view-subset samples per seed sample.
      steps, batch_size, learning_rate, patience: the fit loop.
      constant_lr: no cosine decay.
      start: fine-tune this estimator (a model folder, or "pretrained": the rig-agnostic one
        shipped in the package) instead of a fresh network; its architecture wins over
        ``paper_size`` and ``output``, and it must take ``infer_cameras`` (a rig-agnostic one
        takes any).
    """

    run: TrainingRun
    train_cameras: tuple[str, ...] | None = None
    infer_cameras: tuple[str, ...] | None = None
    paper_size: bool = False
    output: str = "residual"
    loss_power: float = 1.0
    augment: int = 4
    steps: int = 4000
    batch_size: int = 256
    learning_rate: float = 1e-3
    constant_lr: bool = False
    patience: int = 20
    start: str | None = None


class EstimatorTrained(NamedTuple):
    """An estimator's training: training people, the best validation reprojection error (px per
    keypoint; NaN without validations), steps, seconds, folder, and the dev comparison with
    triangulation (`jobs.common.read_dev_quality`; None when not written)."""

    people: int
    best_px_per_keypoint: float
    steps: int
    seconds: float
    out: str
    dev_quality: dict | None


def train_estimator_job(job: EstimatorJob) -> EstimatorTrained:
    """Trains the estimator into ``job.run.out``."""
    from mvpose_jax.estimator_training import train_estimator
    from mvpose_jax.features import single_person_samples
    from mvpose_jax.models import MLPConfig
    from mvpose_jax.parallel import resolve_num_devices
    from mvpose_jax.trained import EstimatorConfig, TrainConfig

    run = job.run
    rig = _begin(run)
    train_cams = tuple(job.train_cameras or rig.names)
    infer_cams = tuple(job.infer_cameras or train_cams)
    for c in train_cams:
        rig.camera_index(c)  # unknown names fail here, naming the camera

    xy, score = single_person_samples(
        recordings_in(run.train, run.layout, run.source_layout), train_cams
    )
    if run.dev:
        dev_xy, dev_score = single_person_samples(
            recordings_in(run.dev, run.layout, run.source_layout), train_cams
        )
    else:
        n = max(1, len(xy) // 10)
        xy, score, dev_xy, dev_score = xy[:-n], score[:-n], xy[-n:], score[-n:]
    start = None
    if job.start:
        from mvpose_jax.trained import load_estimator

        start = load_estimator(job.start, rig.select(list(infer_cams)))
        mlp = start.config.mlp
        if mlp.views == "pooled":
            # A rig-agnostic network is fine-tuned on, and set up for, every camera of the rig.
            train_cams = infer_cams = tuple(rig.names)
            start = load_estimator(job.start, rig)
    else:
        mlp = MLPConfig() if job.paper_size else MLPConfig.quick()
        mlp = MLPConfig(widths=mlp.widths, output=job.output)
    config = EstimatorConfig(
        train_cameras=train_cams,
        infer_cameras=infer_cams,
        mlp=mlp,
        num_augment=job.augment,
        loss_power=job.loss_power,
        train=TrainConfig(
            learning_rate=job.learning_rate,
            batch_size=job.batch_size,
            max_steps=job.steps,
            patience=job.patience,
            seed=run.seed,
            final_lr_fraction=1.0 if job.constant_lr else 0.01,
            num_devices=resolve_num_devices(run.devices),
            checkpoint_every_steps=run.checkpoint_every,
        ),
    )
    _, fit = train_estimator(
        rig.select(list(train_cams)),
        xy,
        score,
        dev_xy,
        dev_score,
        config,
        checkpoint_dir=run.out,
        resume=run.resume,
        start=start,
    )
    write_model_pipeline(run.out, matcher=False)
    best = min(fit.history, key=lambda h: h["val_loss"]) if fit.history else {}
    return EstimatorTrained(
        len(xy),
        best.get("val_px_per_keypoint", float("nan")),
        fit.steps,
        fit.seconds,
        run.out,
        read_dev_quality(run.out),
    )


@dataclasses.dataclass(frozen=True)
class TemporalJob:
    """A temporal model's training (`temporal_training.fit_temporal`).

    Attributes:
      run: data and folder (one device; no resuming: a run is minutes).
      steps, learning_rate, window: the training and the window (frames).
      start: a temporal model folder to fine-tune (None: a new model).
      multi_person: the recordings hold several people: the geometric pipeline (epipolar
        proposals, robust triangulation, tracking) finds and tracks them, and the model trains
        on its tracks (a user's own recording); else each frame's main skeleton per view is the
        one person (single-person recordings, e.g. `mvpose-jax generate --detector-like`).
    """

    run: TrainingRun
    steps: int = 1500
    learning_rate: float = 1e-3
    window: int = 32
    start: str | None = None
    multi_person: bool = False


class TemporalTrained(NamedTuple):
    """A temporal model's training: windows, dev losses (before and after), steps, folder."""

    train_windows: int
    dev_windows: int
    initial_dev_loss: float
    dev_loss: float
    best_step: int
    seconds: float
    out: str


def _tracked_windows(rig, recordings, window: int):
    """Windows of the people the geometric pipeline tracks in multi-person recordings."""
    from mvpose_jax.data.recording import recording_fps
    from mvpose_jax.inference import run_pipeline
    from mvpose_jax.lifting import group_people
    from mvpose_jax.temporal_training import windows_of_tracks
    from mvpose_jax.tracking import TrackingConfig

    parts = []
    for rec in recordings:
        det = rec.detections
        fps = recording_fps(rec.timestamps) if rec.timestamps is not None else 30.0
        res = run_pipeline(rig, det, method="robust", tracking=TrackingConfig(), fps=fps)
        xy, score = group_people(det.xy, det.score, res.members)
        parts.append(windows_of_tracks(xy, score, res.track, res.poses.valid, window))
    return parts


def train_temporal_job(job: TemporalJob) -> TemporalTrained:
    """Trains (or fine-tunes) a temporal model into ``job.run.out``."""
    import time

    import numpy as np

    from mvpose_jax.data.recording import select_cameras
    from mvpose_jax.temporal import TemporalConfig, load_temporal, save_temporal
    from mvpose_jax.temporal_training import (
        TemporalBatch,
        TemporalTrainConfig,
        fit_temporal,
        windows_of_recordings,
    )

    run = job.run
    if run.resume or run.devices not in (None, 1) or run.num_processes:
        raise InputError(
            "train-temporal runs on one device and is not resumed (a run is minutes)",
            field="--resume" if run.resume else "--devices",
        )
    t0 = time.perf_counter()
    rig = _begin(run)

    layouts = set()

    def windows(path: str) -> TemporalBatch:
        recs = recordings_in(path, run.layout, run.source_layout)
        if not recs:
            raise InputError("no recordings here", file=path)
        layouts.update(r.layout for r in recs)
        if len(layouts) > 1:
            raise InputError(
                f"recordings of several layouts {sorted(layouts)}: give --layout", file=path
            )
        recs = [select_cameras(r, list(rig.names), file=path) for r in recs]
        if job.multi_person:
            parts = _tracked_windows(rig, recs, job.window)
            return TemporalBatch(*(np.concatenate(a) for a in zip(*parts, strict=True)))
        return windows_of_recordings(recs, job.window)

    train = windows(run.train)
    if run.dev:
        dev = windows(run.dev)
    else:  # the last tenth of the windows
        n = max(1, len(train.present) // 10)
        train, dev = (
            TemporalBatch(*(a[:-n] for a in train)),
            TemporalBatch(*(a[-n:] for a in train)),
        )
    if len(train.present) == 0 or len(dev.present) == 0:
        raise InputError(
            f"too few frames for windows of {job.window}: {len(train.present)} training and "
            f"{len(dev.present)} dev windows",
            file=run.train,
        )
    start = load_temporal(job.start, rig) if job.start else None
    (layout,) = layouts
    model, record = fit_temporal(
        rig,
        train,
        dev,
        TemporalConfig(window=job.window, layout=layout),
        TemporalTrainConfig(steps=job.steps, learning_rate=job.learning_rate, seed=run.seed),
        start=start,
        progress=True,
    )
    save_temporal(run.out, model, record)
    return TemporalTrained(
        record["train_windows"],
        record["dev_windows"],
        record["initial_dev_loss"],
        record["dev_loss"],
        record["best_step"],
        time.perf_counter() - t0,
        run.out,
    )


def write_model_pipeline(folder: str, *, matcher: bool) -> None:
    """Writes into a model folder the `PipelineConfig` ``infer`` runs with it and no other
    option (`jobs.infer.resolve_pipeline` of `jobs.infer.INFER_PIPELINE`): a matcher's with the
    proposal settings chosen and written there (the combined matcher); an estimator's with the
    3D method it serves (blend, robust triangulation where it reconstructs)."""
    from mvpose_jax.jobs.infer import INFER_PIPELINE, resolve_pipeline
    from mvpose_jax.trained import ModelFolder

    config = resolve_pipeline(INFER_PIPELINE, folder if matcher else None, estimator=not matcher)
    ModelFolder(folder).write_pipeline(config.to_dict())


def model_pipeline(folder: str):
    """The `PipelineConfig` a model folder serves (`write_model_pipeline`), or None."""
    from mvpose_jax.inference import PipelineConfig
    from mvpose_jax.trained import PIPELINE_FILE, ModelFolder

    record = ModelFolder(folder).read_pipeline()
    if record is None:
        return None
    try:
        return PipelineConfig.from_dict(record)
    except (TypeError, ValueError) as e:
        raise InputError(f"unreadable pipeline ({e})", file=Path(folder) / PIPELINE_FILE) from None


def _begin(run: TrainingRun):
    """A training run's start, before anything touches a device: the output folder checked, a
    multi-host run joined to its coordinator; returns the rig."""
    from mvpose_jax.data.files import check_writable
    from mvpose_jax.parallel import initialize_distributed

    check_writable(run.out, folder=True)
    initialize_distributed(run.coordinator_address, run.num_processes, run.process_id)
    return run.rig.load()
