"""The adapt job: a trained estimator (and optionally its matcher) fine-tuned on one
recording's own detections, written as model folders `infer` loads."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from mvpose_jax.errors import InputError
from mvpose_jax.jobs.common import (
    DetectionsSource,
    ProposalOptions,
    RigSource,
    load_detections,
    proposal_settings,
    read_dev_quality,
)

if TYPE_CHECKING:
    from mvpose_jax.adapt import AdaptConfig, AdaptReport, MatcherAdaptReport

# `adapt.MatcherAdaptConfig.max_steps`'s default, here without importing jax (the command
# line's parser shows it; tests/test_adapt.py holds the two equal).
MATCHER_ADAPT_STEPS = 400


@dataclasses.dataclass(frozen=True)
class AdaptSettings:
    """An adaptation's settings (`adapt.AdaptConfig`'s fields a caller chooses; the others keep
    their defaults). ``max_seconds`` None: the default budget rule."""

    max_steps: int = 300
    max_seconds: float | None = None
    learning_rate: float = 1e-3
    holdout_every: int = 5
    block_frames: int = 10
    patience: int = 5


def adapt_config(settings: AdaptSettings, *, min_views: int = 2, seed: int = 0) -> AdaptConfig:
    """The `adapt.AdaptConfig` of ``settings`` (``min_views``: the proposals')."""
    from mvpose_jax.adapt import AdaptConfig

    return AdaptConfig(
        learning_rate=settings.learning_rate,
        max_steps=settings.max_steps,
        max_seconds=settings.max_seconds,
        patience=settings.patience,
        holdout_every=settings.holdout_every,
        block_frames=settings.block_frames,
        min_views=min_views,
        seed=seed,
    )


@dataclasses.dataclass(frozen=True)
class AdaptJob:
    """Adapting a trained estimator to a recording.

    Attributes:
      rig: the cameras; detections: the recording.
      estimator: the trained estimator's folder.
      out: the adapted estimator's folder (new or empty).
      matcher: group the detections with this trained matcher's folder (None: epipolar).
      proposals: how detections are grouped into people.
      matcher_out: also adapt ``matcher`` first and write it to this folder (new or empty).
      matcher_max_steps: most steps of the matcher's adaptation.
      seed: batch order and augmentation.
      settings: the estimator's adaptation.
    """

    rig: RigSource
    detections: DetectionsSource
    estimator: str
    out: str
    matcher: str | None = None
    proposals: ProposalOptions = ProposalOptions()
    matcher_out: str | None = None
    matcher_max_steps: int = MATCHER_ADAPT_STEPS
    seed: int = 0
    settings: AdaptSettings = AdaptSettings()


class Adapted(NamedTuple):
    """What `adapt` did: the estimator's report (`adapt.AdaptReport`), the matcher's (None
    unless adapted), the estimator folder's dev comparison with triangulation (or None), and
    where the adaptation's report was written."""

    report: AdaptReport
    matcher_report: MatcherAdaptReport | None
    dev_quality: dict | None
    report_path: Path


def adapt(job: AdaptJob) -> Adapted:
    """Adapts (the matcher, then) the estimator and writes the model folders."""
    from mvpose_jax.adapt import adapt_estimator, save_adapted_estimator
    from mvpose_jax.data.files import check_writable
    from mvpose_jax.trained import load_estimator, load_matcher, resolve_model_folder

    out = check_writable(job.out, folder=True)
    if out.exists() and any(out.iterdir()):
        raise InputError("exists and is not empty; choose a new folder", file=out, field="--out")
    if job.matcher_out is not None:
        if not job.matcher:
            raise InputError("adapts a matcher: give --matcher", field="--matcher-out")
        matcher_out = check_writable(job.matcher_out, folder=True)
        if matcher_out.exists() and any(matcher_out.iterdir()):
            raise InputError(
                "exists and is not empty; choose a new folder",
                file=matcher_out,
                field="--matcher-out",
            )
    config = adapt_config(job.settings, min_views=job.proposals.min_views, seed=job.seed)
    config.check()
    rec, rig = load_detections(job.detections, job.rig.load())
    matcher = load_matcher(job.matcher, rig) if job.matcher else None
    # The grouping infer makes with the same options (by default: the combined matcher).
    proposals, threshold, combined = proposal_settings(job.proposals, job.matcher, matcher)
    matcher_report = None
    if job.matcher_out is not None:
        from mvpose_jax.adapt import MatcherAdaptConfig, adapt_matcher, save_adapted_matcher
        from mvpose_jax.trained import read_combined_config

        # One budget for the whole command (the estimator's, its max_seconds or its default
        # rule): the matcher gets at most half of it, the estimator what is left.
        total = config.budget_seconds(len(rec.detections.count))
        matcher, matcher_report = adapt_matcher(
            rig,
            rec.detections,
            matcher,
            combined=read_combined_config(job.matcher),
            config=MatcherAdaptConfig(
                max_steps=job.matcher_max_steps, max_seconds=total / 2, seed=job.seed
            ),
        )
        config = dataclasses.replace(config, max_seconds=max(1.0, total - matcher_report.seconds))
        matcher_report.settings["matcher"] = str(Path(job.matcher).resolve())
        save_adapted_matcher(job.matcher_out, matcher, matcher_report, settings_from=job.matcher)
        # The estimator adapts behind the grouping `infer --matcher MATCHER_OUT` makes with the
        # same options: with --proposals gat, the adapted GAT's own threshold.
        proposals, threshold, combined = proposal_settings(
            job.proposals, str(job.matcher_out), matcher
        )
    estimator = load_estimator(job.estimator, rig)
    adapted, report = adapt_estimator(
        rig,
        rec.detections,
        estimator,
        matcher=matcher,
        threshold=threshold,
        half_score_px=job.proposals.half_score_px,
        proposals=proposals,
        combined=combined,
        config=config,
    )
    report.settings["estimator"] = str(resolve_model_folder(job.estimator, "estimator").resolve())
    report.settings["detections"] = str(Path(job.detections.path).resolve())
    save_adapted_estimator(job.out, adapted, report)
    from mvpose_jax.trained import ModelFolder

    report_path = ModelFolder(job.out).adapt_report_path
    return Adapted(report, matcher_report, read_dev_quality(job.out), report_path)
