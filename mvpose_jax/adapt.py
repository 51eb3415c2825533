"""Adapting a trained 3D estimator to one recording, without labels.

The estimator's loss (DESIGN.md §1.3) is the reprojection error of its 3D people in the cameras
that saw them: it needs no 3D truth, so the recording being reconstructed is training data too.
`adapt_estimator` groups the recording's detections into people with the current proposals (a
learned matcher, or the epipolar one), builds estimator samples from those groups exactly as
training does (`train.make_estimator_batch`, the estimator's own normalised frame), and
fine-tunes the given parameters with the training step and fit loop of `train`
(`make_train_step`, `fit`). Contiguous blocks of frames are held out (every ``holdout_every``-th
block of ``block_frames`` frames, so neighbouring frames of a held-out frame, nearly the same
people, cannot leak into the adaptation set); their reprojection loss decides early stopping,
and the best parameters (the given ones included) are returned. Steps and wall-clock time are
bounded (`AdaptConfig`).

`save_adapted_estimator` writes the result as a model folder that `trained.load_estimator`
(and ``mvpose-jax infer --estimator``) loads, with the report beside it.

`adapt_matcher` does the same for a matcher (issue 19's optional item): the combined proposals'
groups label every cross-view pair of the recording, and the GAT is fine-tuned on them with its
training loss; `save_adapted_matcher` writes a folder `trained.load_matcher` loads.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig
from mvpose_jax.data.files import to_jsonable
from mvpose_jax.errors import InputError
from mvpose_jax.estimator_training import compare_with_triangulation, estimator_training
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import group_people
from mvpose_jax.proposals import CombinedConfig
from mvpose_jax.skeletons import Detections
from mvpose_jax.train import TrainState, fit, init_train_state, make_optimizer, make_train_step
from mvpose_jax.trained import (
    Estimator,
    Matcher,
    ModelFolder,
    TrainConfig,
)

# The time bound of the issue (19, item 3): at most 2 minutes per 1,000 frames (quick size, 2 CPU
# cores); the default wall-clock budget of an adaptation.
SECONDS_PER_1000_FRAMES = 120.0


def _budget_seconds(max_seconds: float | None, num_frames: int) -> float:
    """``max_seconds``, else `SECONDS_PER_1000_FRAMES` per 1,000 frames (at least 30 s)."""
    if max_seconds is not None:
        return float(max_seconds)
    return max(30.0, SECONDS_PER_1000_FRAMES * num_frames / 1000.0)


def _fit_within_budget(
    state: TrainState,
    train_step,
    check_batches,
    evaluate,
    tcfg: TrainConfig,
    *,
    check_every: int,
    desc: str,
    progress: bool,
    start: float,
    budget: float,
) -> tuple[TrainState, int, list, dict, dict, str]:
    """`train.fit` from the given parameters, which count as the best so far, within what is
    left of ``budget`` seconds since ``start``; ``tcfg.max_steps`` 0 runs nothing.

    Returns:
      (the best state, steps run, history, held-out metrics before and after, why it stopped:
      "max_steps", "max_seconds" or "patience").
    """
    before = evaluate(state)
    if tcfg.max_steps == 0:
        return state, 0, [], before, before, "max_steps"
    result = fit(
        state,
        train_step,
        check_batches,
        evaluate,
        tcfg,
        steps_per_epoch=check_every,
        desc=desc,
        progress=progress,
        best_val_loss=before["val_loss"],
        best_state=state,
        max_seconds=max(0.0, budget - (time.perf_counter() - start)),
    )
    after = evaluate(result.state)
    if result.steps >= tcfg.max_steps:
        stopped = "max_steps"
    elif time.perf_counter() - start >= budget:
        stopped = "max_seconds"
    else:
        stopped = "patience"
    return result.state, result.steps, result.history, before, after, stopped


@dataclasses.dataclass(frozen=True)
class AdaptConfig:
    """How an estimator is adapted to a recording.

    Attributes:
      learning_rate: Adam's initial step size; final_lr_fraction: below 1, a cosine decay to
        this fraction of it over ``max_steps``; 1: constant. The defaults (1e-3 decaying to 1e-4)
        were chosen on the domain-shift experiment's validation scenes (quick scale; 1e-4 and
        3e-4 constant did as well within 0.2 PCP points, and stopped later).
      batch_size: people per step (augmented view subsets come on top, as in training).
      max_steps: most steps.
      max_seconds: wall-clock budget of the whole call (proposals, compilation and steps); None:
        `SECONDS_PER_1000_FRAMES` per 1,000 frames of the recording (at least 30 s).
      check_every: steps between two evaluations of the held-out frames.
      patience: stop after this many evaluations without improvement.
      holdout_every: every this-many-th block of frames is held out (5: a fifth of the frames).
      block_frames: frames per block (contiguous, so held-out frames' neighbours stay out of the
        adaptation set).
      num_augment: view-subset samples per person (None: the estimator's training setting).
      loss_power: per-person loss e^power (None: the estimator's training setting).
      min_views: a person group takes part when it has skeletons in this many cameras.
      min_people: the least people the adaptation set needs (and the held-out set a quarter of
        it); fewer is an error.
      seed: batch order and augmentation.
    """

    learning_rate: float = 1e-3
    final_lr_fraction: float = 0.1
    batch_size: int = 256
    max_steps: int = 300
    max_seconds: float | None = None
    check_every: int = 20
    patience: int = 5
    holdout_every: int = 5
    block_frames: int = 10
    num_augment: int | None = None
    loss_power: float | None = None
    min_views: int = 2
    min_people: int = 16
    seed: int = 0

    def budget_seconds(self, num_frames: int) -> float:
        """The wall-clock budget for a recording of ``num_frames`` frames."""
        return _budget_seconds(self.max_seconds, num_frames)

    def check(self) -> None:
        """Raises `InputError` naming the first setting out of range."""
        positive = ("batch_size", "check_every", "holdout_every", "block_frames", "min_people")
        for name in positive:
            if getattr(self, name) < 1:
                raise InputError(f"must be at least 1, not {getattr(self, name)}", field=name)
        if self.holdout_every < 2:
            raise InputError(
                "must be at least 2 (1 would hold out every frame)", field="holdout_every"
            )
        if self.max_steps < 0 or self.patience < 1 or self.min_views < 1:
            raise InputError("max_steps >= 0, patience >= 1 and min_views >= 1", field="config")
        if not self.learning_rate > 0 or not 0 < self.final_lr_fraction <= 1:
            raise InputError(
                "learning_rate > 0 and final_lr_fraction in (0, 1]", field="learning_rate"
            )
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise InputError(f"must be > 0, not {self.max_seconds}", field="max_seconds")


@dataclasses.dataclass(frozen=True)
class AdaptReport:
    """What an adaptation did, for the user and the report file.

    Attributes:
      frames, frames_adapt, frames_heldout: the recording's frames and how they were split.
      people_adapt, people_heldout: person groups in each part.
      heldout_loss_before, heldout_loss_after: the held-out reprojection loss (mean of e^power
        per person) of the given and of the returned parameters.
      heldout_px_before, heldout_px_after: the same as mean L1 error per detected keypoint (px).
      steps: steps run; best_step: the step of the returned parameters (0: the given ones).
      stopped: "max_steps", "max_seconds" or "patience".
      seconds: the whole call; seconds_grouping: of it, the proposals.
      settings: the `AdaptConfig` and the grouping used.
      quality: the returned estimator against DLT triangulation on the held-out people
        (`train.compare_with_triangulation`; written beside a saved model, where
        `trained.load_estimator` warns from it).
      history: one record per held-out evaluation (`train.fit`).
    """

    frames: int
    frames_adapt: int
    frames_heldout: int
    people_adapt: int
    people_heldout: int
    heldout_loss_before: float
    heldout_loss_after: float
    heldout_px_before: float
    heldout_px_after: float
    steps: int
    best_step: int
    stopped: str
    seconds: float
    seconds_grouping: float
    settings: dict
    quality: dict
    history: list[dict[str, float]]

    def to_json(self) -> dict:
        return to_jsonable(dataclasses.asdict(self))


def heldout_frames(num_frames: int, block_frames: int, holdout_every: int) -> np.ndarray:
    """Which frames are held out: (F,) bool, True for every frame of every ``holdout_every``-th
    block of ``block_frames`` consecutive frames (blocks holdout_every-1, 2*holdout_every-1, ...),
    so a recording's start and end both adapt."""
    block = np.arange(num_frames) // block_frames
    return block % holdout_every == holdout_every - 1


def person_samples(
    detections: Detections, members: np.ndarray, min_views: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each proposed person's skeletons as one estimator sample.

    Args:
      detections: xy (F, C, P, K, 2), score (F, C, P, K) in the C cameras of ``members``.
      members: (F, G, C) each person's skeleton per camera, -1 none.
      min_views: least cameras with a skeleton.
    Returns:
      xy (N, C, K, 2), score (N, C, K) and frame (N,) of the N people kept, frame order.
    """
    xy, score = group_people(detections.xy, detections.score, members)  # (F, G, C, K, ...)
    views = ((members >= 0) & (score > 0).any(-1)).sum(-1)  # (F, G)
    f, g = np.nonzero(views >= min_views)
    return xy[f, g], score[f, g], f


def adapt_estimator(
    rig: Rig,
    detections: Detections,
    estimator: Estimator,
    *,
    members: np.ndarray | None = None,
    matcher: Matcher | None = None,
    threshold: float = 0.5,
    half_score_px: float = 30.0,
    proposals: str | None = None,
    combined: CombinedConfig | None = None,
    config: AdaptConfig = AdaptConfig(),
    progress: bool = True,
) -> tuple[Estimator, AdaptReport]:
    """Fine-tunes ``estimator`` on a recording's own detections (no labels; module docstring).

    Args:
      rig: the C cameras of ``detections``, in their order.
      detections: xy (F, C, P, K, 2) pixels, score (F, C, P, K), count (F, C).
      estimator: the starting point; its inference cameras must be among the grouping cameras.
      members: (F, G, C) person groups on ``rig``'s cameras (e.g. an earlier run's
        `PipelineResult.members`); None: the pipeline's proposals (``proposals``, ``combined``,
        ``matcher``, ``threshold``, ``half_score_px`` as `inference.stream_pipeline` takes them:
        by default the combined matcher with a ``matcher``, else the epipolar one).
      config: `AdaptConfig`.
    Returns:
      (the adapted `Estimator`: the parameters with the lowest held-out loss, possibly the given
      ones; its cameras and normalisation unchanged, `AdaptReport`).
    Raises:
      InputError on settings out of range, cameras or keypoints that do not fit, or a recording
      too short (or too empty) to hold out frames from.
    """
    start = time.perf_counter()
    config.check()
    F, C, P, K = np.shape(detections.score)
    budget = config.budget_seconds(F)
    if members is None:
        grouping = "matcher" if matcher is not None else f"epipolar ({half_score_px:g} px)"
        res = run_pipeline(
            rig,
            detections,
            matcher=matcher,
            threshold=threshold,
            half_score_px=half_score_px,
            proposals=proposals,
            combined=combined,
            min_views=config.min_views,
        )
        members, cameras = res.members, res.cameras
    else:
        grouping, cameras = "given", tuple(rig.names)
        if np.shape(members)[0] != F or np.ndim(members) != 3 or np.shape(members)[2] != C:
            raise InputError(
                f"members have shape {np.shape(members)}, expected ({F}, G, {C})", field="members"
            )
    seconds_grouping = time.perf_counter() - start
    cam_idx = [rig.names.index(c) for c in cameras]
    missing = [c for c in estimator.rig_infer.names if c not in cameras]
    if missing:
        raise InputError(
            f"the estimator's inference cameras {missing} are not among the grouping cameras "
            f"{list(cameras)}",
            field="cameras",
        )
    infer_idx = [list(cameras).index(c) for c in estimator.rig_infer.names]
    det = Detections(
        np.asarray(detections.xy, np.float32)[:, cam_idx],
        np.asarray(detections.score, np.float32)[:, cam_idx],
        np.asarray(detections.count)[:, cam_idx],
    )
    model = nnx.merge(estimator.graphdef, estimator.params, estimator.rest)
    if model.num_keypoints != K:
        raise InputError(
            f"the estimator was trained on {model.num_keypoints} keypoints, the detections have "
            f"{K} (convert the layout)",
            field="keypoints",
        )
    xy, score, frame = person_samples(det, np.asarray(members), config.min_views)
    # Only people the estimator can see: at least one inference view.
    seen = (score[:, infer_idx] > 0).any(axis=(1, 2))
    xy, score, frame = xy[seen], score[seen], frame[seen]
    held_frames = heldout_frames(F, config.block_frames, config.holdout_every)  # (F,)
    held = held_frames[frame]  # (N,)
    n_adapt, n_held = int((~held).sum()), int(held.sum())
    need_held = max(1, config.min_people // 4)
    if n_adapt < config.min_people or n_held < need_held:
        raise InputError(
            f"too little to adapt on: {n_adapt} people (of {config.min_views}+ views) in the "
            f"adaptation frames and {n_held} in the held-out frames (every {config.holdout_every}"
            f"th block of {config.block_frames} frames) of {F} frames; need {config.min_people} "
            f"and {need_held}: a longer recording, or smaller --block-frames",
            field="detections",
        )
    power = estimator.config.loss_power if config.loss_power is None else config.loss_power
    augment = estimator.config.num_augment if config.num_augment is None else config.num_augment
    batch = min(config.batch_size, n_adapt)
    max_steps = config.max_steps
    tcfg = TrainConfig(
        learning_rate=config.learning_rate,
        clip_norm=estimator.config.train.clip_norm,
        batch_size=batch,
        max_epochs=max(1, math.ceil(max_steps / config.check_every)),
        max_steps=max_steps,
        eval_every=1,
        patience=config.patience,
        seed=config.seed,
        final_lr_fraction=config.final_lr_fraction,
        checkpoint_every_steps=0,
    )
    # The estimator's own set-up, on the grouping cameras, from its parameters (copied: the
    # caller keeps the given estimator) and in its normalised frame.
    setup = estimator_training(
        rig,
        dataclasses.replace(
            estimator.config,
            train_cameras=tuple(cameras),
            infer_cameras=tuple(estimator.rig_infer.names),
            num_augment=augment,
            loss_power=power,
            train=tcfg,
        ),
        K,
        steps_per_epoch=config.check_every,
        start=estimator,
    )
    graphdef, rest, state = setup.graphdef, setup.rest, setup.state
    adapt_data = setup.batches(xy[~held], score[~held])
    held_data = setup.batches(xy[held], score[held])

    def evaluate(s: TrainState) -> dict[str, float]:
        return {k: float(v) for k, v in setup.evaluate(s.params, held_data).items()}

    def check_batches(epoch: int):
        # An "epoch" of the fit loop is one evaluation period: check_every random batches.
        rng = np.random.default_rng([config.seed, epoch])
        for _ in range(config.check_every):
            idx = rng.choice(n_adapt, batch, replace=False)
            yield jax.tree.map(lambda a: a[idx], adapt_data)

    result_state, steps, history, before, after, stopped = _fit_within_budget(
        state,
        setup.train_step,
        check_batches,
        evaluate,
        tcfg,
        check_every=config.check_every,
        desc="adapt",
        progress=progress,
        start=start,
        budget=budget,
    )
    best_step = int(result_state.step)
    adapted = estimator._replace(params=jax.device_get(result_state.params))
    quality = compare_with_triangulation(
        graphdef,
        rest,
        result_state.params,
        setup.rig_train,
        setup.infer_idx,
        xy[held],
        score[held],
        normalisation=estimator.normalisation,
    )
    quality["how"] += " (here: the people of the adaptation's held-out frames)"
    report = AdaptReport(
        frames=F,
        frames_adapt=int((~held_frames).sum()),
        frames_heldout=int(held_frames.sum()),
        people_adapt=n_adapt,
        people_heldout=n_held,
        heldout_loss_before=before["val_loss"],
        heldout_loss_after=after["val_loss"],
        heldout_px_before=before["val_px_per_keypoint"],
        heldout_px_after=after["val_px_per_keypoint"],
        steps=int(steps),
        best_step=best_step,
        stopped=stopped,
        seconds=time.perf_counter() - start,
        seconds_grouping=seconds_grouping,
        settings={
            **dataclasses.asdict(config),
            "grouping": grouping,
            "proposals": proposals if grouping == "matcher" else None,
            "threshold": threshold if grouping != "given" else None,
            "grouping_cameras": list(cameras),
            "loss_power": power,
            "num_augment": augment,
            "budget_seconds": budget,
        },
        quality=quality,
        history=history,
    )
    return adapted, report


def save_adapted_estimator(
    directory: str | os.PathLike,
    estimator: Estimator,
    report: AdaptReport,
) -> Path:
    """Writes an adapted estimator as a model folder `trained.load_estimator` loads, with
    ``adapt_report.json`` beside the checkpoint.

    The folder is assembled under a temporary name beside ``directory`` and renamed into place
    when complete: an interrupted call leaves no half-written model.

    Args:
      directory: the new model folder; it must not exist, or be empty.
    Raises:
      InputError when ``directory`` holds something already.
    """
    config = to_jsonable(dataclasses.asdict(estimator.config))
    names = list(estimator.rig_infer.names)
    centre, radius = estimator.normalisation
    config.update(
        train_cameras=list(estimator.config.train_cameras or names),
        infer_cameras=names,
        num_keypoints=int(
            nnx.merge(estimator.graphdef, estimator.params, estimator.rest).num_keypoints
        ),
        frame=[float(x) for x in np.asarray(centre)] + [float(radius)],
        adapted={k: v for k, v in report.to_json().items() if k not in ("history", "quality")},
    )
    with ModelFolder.create(directory) as folder:
        folder.save_params(estimator.params, report.best_step, config, report.heldout_loss_after)
        folder.write_adapt_report(report.to_json())
        folder.write_dev_quality(report.quality)
    return Path(directory)


# =========================================================================== the matcher
# A matcher meets the recording's detectors, people and floor for the first time too. The
# combined proposals lean on geometry where the GAT is out of its depth, so their groups are
# labels the GAT can learn from: every cross-view pair of a frame is labelled 1 when the
# proposals put both skeletons into one person, else 0 (`graphs.build_graphs` with the proposals
# as identity), and the GAT is fine-tuned on them with its training loss and step. As for the
# estimator, blocks of frames are held out; their pseudo-label loss stops it early.


@dataclasses.dataclass(frozen=True)
class MatcherAdaptConfig:
    """How a matcher is adapted to a recording (`adapt_matcher`).

    Attributes:
      learning_rate: Adam's step size (constant). Chosen on the domain-shift experiment's
        validation scenes (quick matchers: training seed 0 on none and part-mixing, seed 0
        trained 0.6 m too low on none, seed 1 on occluders; 200 frames, so the 30 s budget
        allowed 51-101 steps on 2 busy cores), by the combined matcher's ARI after adaptation,
        then the GAT's: 1e-3 and 3e-4 both change the combined ARI by 0 to +0.0018 (1e-3: +0.0018
        on part-mixing against +0.0010); the GAT alone reaches 0.9922 on average with 1e-3
        against 0.9826 (from 0.6473 on the wrong floor, 0.8748 with part mixing); 1e-4 was
        slower still (unbounded: 0.984 after 400 steps on the wrong floor).
      batch_frames: frames (graphs) per step.
      max_steps, check_every, patience: most steps; steps between two evaluations of the
        held-out frames; evaluations without improvement before it stops.
      max_seconds: wall-clock budget of the whole call (None: `SECONDS_PER_1000_FRAMES` per
        1,000 frames, at least 30 s).
      holdout_every, block_frames: every this-many-th block of this many frames is held out.
      min_frames: the least adaptation frames with a cross-view pair (the held-out frames need a
        quarter of it); fewer is an error.
      seed: batch order.
    """

    learning_rate: float = 1e-3
    batch_frames: int = 16
    max_steps: int = 400
    max_seconds: float | None = None
    check_every: int = 25
    patience: int = 4
    holdout_every: int = 5
    block_frames: int = 10
    min_frames: int = 16
    seed: int = 0

    def budget_seconds(self, num_frames: int) -> float:
        """The wall-clock budget for a recording of ``num_frames`` frames."""
        return _budget_seconds(self.max_seconds, num_frames)

    def check(self) -> None:
        """Raises `InputError` naming the first setting out of range."""
        for name in ("batch_frames", "check_every", "patience", "block_frames", "min_frames"):
            if getattr(self, name) < 1:
                raise InputError(f"must be at least 1, not {getattr(self, name)}", field=name)
        if self.holdout_every < 2:
            raise InputError(
                "must be at least 2 (1 would hold out every frame)", field="holdout_every"
            )
        if self.max_steps < 0:
            raise InputError(f"must be >= 0, not {self.max_steps}", field="max_steps")
        if not self.learning_rate > 0:
            raise InputError(f"must be > 0, not {self.learning_rate}", field="learning_rate")
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise InputError(f"must be > 0, not {self.max_seconds}", field="max_seconds")


@dataclasses.dataclass(frozen=True)
class MatcherAdaptReport:
    """What a matcher adaptation did.

    Attributes:
      frames, frames_adapt, frames_heldout: the recording's frames, and those with a cross-view
        pair in each part.
      pairs_adapt, pairs_heldout: labelled pairs in each part; positive_fraction: of them, the
        share labelled one person.
      heldout_loss_before, heldout_loss_after: the held-out pseudo-label loss (MSE per pair) of
        the given and of the returned parameters; heldout_accuracy_*: decisions at 0.5 that
        agree with the pseudo-labels.
      threshold, threshold_ari: the returned GAT's proposal threshold, chosen on the held-out
        frames by the best per-frame ARI of its proposals against the pseudo-labels
        (`proposals.choose_proposal_threshold`), and the ARI of each threshold tried. The
        threshold chosen on composed dev frames was chosen for the given network's scores, not
        for the adapted one's, which have learnt this recording's pairs.
      steps, best_step, stopped, seconds, seconds_grouping, settings, history: as `AdaptReport`.
    """

    frames: int
    frames_adapt: int
    frames_heldout: int
    pairs_adapt: int
    pairs_heldout: int
    positive_fraction: float
    heldout_loss_before: float
    heldout_loss_after: float
    heldout_accuracy_before: float
    heldout_accuracy_after: float
    threshold: float
    threshold_ari: dict[float, float]
    steps: int
    best_step: int
    stopped: str
    seconds: float
    seconds_grouping: float
    settings: dict
    history: list[dict[str, float]]

    def to_json(self) -> dict:
        return to_jsonable(dataclasses.asdict(self))


def adapt_matcher(
    rig: Rig,
    detections: Detections,
    matcher: Matcher,
    *,
    identity: np.ndarray | None = None,
    combined: CombinedConfig | None = None,
    config: MatcherAdaptConfig = MatcherAdaptConfig(),
    progress: bool = True,
) -> tuple[Matcher, MatcherAdaptReport]:
    """Fine-tunes ``matcher``'s GAT on a recording's own detections, labelled by proposals.

    Every cross-view pair of skeletons is a training node: 1 where the pseudo-labels put both
    into one person, 0 elsewhere (a skeleton in no person is a false detection, as in training).

    Args:
      rig: the cameras of ``detections``, in their order; the matcher's cameras must be among
        them (the rest are not used).
      detections: xy (F, C, P, K, 2) pixels, score (F, C, P, K), count (F, C).
      matcher: the starting point.
      identity: (F, C, P) pseudo-labels on ``rig``'s cameras (-1: in no person); None: the
        combined proposals of ``matcher`` with ``combined`` (default `CombinedConfig()`).
      config: `MatcherAdaptConfig`.
    Returns:
      (the adapted `Matcher`: the parameters with the lowest held-out loss, possibly the given
      ones, `MatcherAdaptReport`).
    Raises:
      InputError on settings out of range, cameras that do not fit, or a recording with too few
      frames of cross-view pairs to hold some out.
    """
    from mvpose_jax.graphs import build_graphs, detection_features, graph_budget
    from mvpose_jax.matcher_training import matcher_eval_sums, matcher_loss_fn
    from mvpose_jax.matching import gat_match_table, propose_with_matcher
    from mvpose_jax.proposals import choose_proposal_threshold

    start = time.perf_counter()
    config.check()
    names = list(matcher.rig.names)
    missing = [c for c in names if c not in rig.names]
    if missing:
        raise InputError(
            f"the matcher's cameras {missing} are not in the recording's {list(rig.names)}",
            field="cameras",
        )
    cam_idx = [rig.names.index(c) for c in names]
    det = Detections(
        np.asarray(detections.xy, np.float32)[:, cam_idx],
        np.asarray(detections.score, np.float32)[:, cam_idx],
        np.asarray(detections.count)[:, cam_idx],
    )
    F, C, P, K = det.score.shape
    if identity is None:
        grouping = "combined"
        cfg = combined or CombinedConfig()
        identity = propose_with_matcher(matcher, det, mode="combined", combined=cfg).identity
    else:
        grouping = "given"
        if np.shape(identity) != (F, len(rig.names), P):
            raise InputError(
                f"identity has shape {np.shape(identity)}, expected ({F}, {len(rig.names)}, {P})",
                field="identity",
            )
        identity = np.asarray(identity)[:, cam_idx]
    seconds_grouping = time.perf_counter() - start
    budget_s = config.budget_seconds(F)
    count = np.asarray(det.count)
    features = detection_features(matcher.rig, det.xy, det.score)
    valid = np.arange(P)[None, None] < count[..., None]
    identity = np.where(valid, identity, -1)
    # Pairs of each frame: every cross-camera pair of its skeletons.
    pairs = (count.sum(1) ** 2 - (count**2).sum(1)) // 2  # (F,)
    dets = count.sum(1)
    held_frames = heldout_frames(F, config.block_frames, config.holdout_every)
    adapt_f = np.flatnonzero(~held_frames & (pairs > 0))
    held_f = np.flatnonzero(held_frames & (pairs > 0))
    need_held = max(1, config.min_frames // 4)
    if len(adapt_f) < config.min_frames or len(held_f) < need_held:
        raise InputError(
            f"too little to adapt on: {len(adapt_f)} frames with a cross-view pair in the "
            f"adaptation frames and {len(held_f)} in the held-out frames (every "
            f"{config.holdout_every}th block of {config.block_frames} frames) of {F} frames; "
            f"need {config.min_frames} and {need_held}",
            field="detections",
        )
    B = min(config.batch_frames, len(adapt_f))
    # One padded budget for every batch (one compilation): the B largest frames together.
    top = lambda a: int(np.sort(a)[::-1][:B].sum())  # noqa: E731
    budget = graph_budget(top(dets), top(pairs), B)

    def graphs_of(frames: np.ndarray):
        return build_graphs(
            features[frames], valid[frames], identity[frames], num_graphs=B, budget=budget
        )

    held_batches = [jax.device_put(graphs_of(held_f[i : i + B])) for i in range(0, len(held_f), B)]
    tcfg = TrainConfig(
        learning_rate=config.learning_rate,
        clip_norm=matcher.config.train.clip_norm,
        batch_size=B,
        max_epochs=max(1, math.ceil(config.max_steps / config.check_every)),
        max_steps=config.max_steps,
        eval_every=1,
        patience=config.patience,
        seed=config.seed,
        final_lr_fraction=1.0,
        checkpoint_every_steps=0,
    )
    tx = make_optimizer(tcfg, config.check_every)
    # A copy: the train step donates its state, and the caller keeps the given matcher.
    model = nnx.merge(matcher.graphdef, jax.tree.map(jnp.copy, matcher.params), matcher.rest)
    graphdef, rest, state = init_train_state(model, tx)
    train_step = make_train_step(graphdef, rest, tx, matcher_loss_fn, xla_kernels=True)
    eval_batch = jax.jit(lambda params, b: matcher_eval_sums(graphdef, rest, params, b))

    def evaluate(s: TrainState) -> dict[str, float]:
        sums = [eval_batch(s.params, b) for b in held_batches]
        total = {k: sum(float(x[k]) for x in sums) for k in sums[0]}
        n = max(total["count"], 1.0)
        return {"val_loss": total["sq_error"] / n, "val_accuracy": total["correct"] / n}

    def check_batches(epoch: int):
        rng = np.random.default_rng([config.seed, epoch])
        for _ in range(config.check_every):
            yield graphs_of(rng.choice(adapt_f, B, replace=False))

    result_state, steps, history, before, after, stopped = _fit_within_budget(
        state,
        train_step,
        check_batches,
        evaluate,
        tcfg,
        check_every=config.check_every,
        desc="adapt matcher",
        progress=progress,
        start=start,
        budget=budget_s,
    )
    labelled = identity[adapt_f]
    positive = sum(
        int(
            (
                (labelled[:, a, :, None] >= 0)
                & (labelled[:, a, :, None] == labelled[:, b, None, :])
            ).sum()
        )
        for a in range(C)
        for b in range(a + 1, C)
    )
    adapted = matcher._replace(params=jax.device_get(result_state.params))
    held_rows, held_scores = gat_match_table(adapted, jax.tree.map(lambda a: a[held_f], det))
    threshold, threshold_ari = choose_proposal_threshold(
        held_rows, held_scores, identity[held_f], count[held_f]
    )
    report = MatcherAdaptReport(
        frames=F,
        frames_adapt=len(adapt_f),
        frames_heldout=len(held_f),
        pairs_adapt=int(pairs[adapt_f].sum()),
        pairs_heldout=int(pairs[held_f].sum()),
        positive_fraction=positive / max(1, int(pairs[adapt_f].sum())),
        heldout_loss_before=before["val_loss"],
        heldout_loss_after=after["val_loss"],
        heldout_accuracy_before=before["val_accuracy"],
        heldout_accuracy_after=after["val_accuracy"],
        threshold=float(threshold),
        threshold_ari={float(k): float(v) for k, v in threshold_ari.items()},
        steps=int(steps),
        best_step=int(result_state.step),
        stopped=stopped,
        seconds=time.perf_counter() - start,
        seconds_grouping=seconds_grouping,
        settings={
            **dataclasses.asdict(config),
            "grouping": grouping,
            "cameras": names,
            "num_keypoints": K,
            "budget_seconds": budget_s,
        },
        history=history,
    )
    return adapted, report


def save_adapted_matcher(
    directory: str | os.PathLike,
    matcher: Matcher,
    report: MatcherAdaptReport,
    *,
    settings_from: str | os.PathLike | None = None,
) -> Path:
    """Writes an adapted matcher as a folder `trained.load_matcher` loads, with
    ``adapt_report.json`` beside the checkpoint and, from the matcher folder ``settings_from``,
    its chosen proposal settings (`trained.ModelFolder.copy_proposal_settings`: chosen on its dev
    frames, kept).

    Assembled under a temporary name and renamed into place when complete.

    Raises:
      InputError when ``directory`` holds something already.
    """
    config = to_jsonable(dataclasses.asdict(matcher.config))
    config.update(
        cameras=list(matcher.rig.names),
        num_keypoints=int(report.settings["num_keypoints"]),
        adapted={k: v for k, v in report.to_json().items() if k != "history"},
    )
    with ModelFolder.create(directory) as folder:
        folder.save_params(matcher.params, report.best_step, config, report.heldout_loss_after)
        folder.write_adapt_report(report.to_json())
        if settings_from is not None:
            folder.copy_proposal_settings(ModelFolder(settings_from))
        # The GAT's threshold is the adapted network's own; the combined matcher's settings
        # (chosen on the matcher's composed dev frames) are kept as they were.
        folder.set_proposal_threshold(
            report.threshold,
            report.threshold_ari,
            report.frames_heldout,
            "the best per-frame adjusted Rand index of the adapted GAT's proposals against the "
            "pseudo-labels on the recording's held-out frames (adapt.adapt_matcher)",
        )
    return Path(directory)
