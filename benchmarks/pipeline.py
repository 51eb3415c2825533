"""The ``pipeline`` group: what users run, timed through the library's public API.

Six pipelines (`PIPELINES`), each through `inference.stream_pipeline` / `inference.run_pipeline`
with a `PipelineConfig`, as ``mvpose-jax infer`` builds them:

* ``default``: `jobs.infer.INFER_PIPELINE` with a matcher and an estimator, as `infer`
  resolves it (`jobs.infer.resolve_pipeline`) for a matcher folder: the combined matcher at the
  folder's settings (chosen as ``train-matcher`` chooses them, `train_models`), the blend,
  tracking and the Butterworth filter;
* ``paper``: the GAT's proposals (at the folder's threshold) and the MLP, untracked;
* ``geometric``: ``infer --method robust`` without models: epipolar proposals, robust
  triangulation, tracking and the Butterworth filter;
* ``dlt``: epipolar proposals and DLT, untracked;
* ``pretrained``: ``infer --estimator pretrained`` (the rig-agnostic estimator shipped in the
  package, no training on the rig): epipolar proposals, the blend, tracking and the Butterworth
  filter;
* ``shipped``: ``infer --matcher pretrained --estimator pretrained`` (both rig-agnostic models
  shipped in the package, no training on the rig), as `infer` resolves it: the combined
  matcher at the shipped folder's settings, the blend, tracking and the Butterworth filter.

Models are the CLI's default sizes (`GATConfig()`, `MLPConfig.quick()`), per rig: trained for a
few steps on synthetic single-person recordings of the scene's rig in the full tier, random
weights in ``--quick`` and ``--smoke`` (the timing does not depend on the weights; the
proposals' people do, a little: each record says how many were found, ``people_found``).

Each pipeline runs in two modes (`MODES`):

* ``live``: one frame per call, as a live loop calls it: one `stream_pipeline` over an iterable
  of one-frame chunks, so the tracker's state is kept from frame to frame; the clock runs over
  the loop. The Butterworth filter is zero-phase: no live loop can run it, so live rows have no
  filtering (``stages_ms["filtering"]`` 0).
* ``offline``: `run_pipeline` over the whole recording in chunks of `CHUNK_FRAMES`, then, for
  the filtered pipelines, `smoothing.smooth_poses` on its results (what `infer` runs while
  assembling, without the files).

Each (scene, pipeline, mode) is run once to warm up (every shape compiled, every matching graph
built), then ``repeats`` times; ``ms_per_frame`` is the median of those runs' wall time per frame.

How the rest is measured (the same in every record's ``how``):

* stages: ``matching`` is the wall time of the match tables (`matching.gat_match_table`,
  `matching.geometric_match_table`, `matching.combined_match_tables`,
  `matching.epipolar_distances_of_rows`, each returns numpy),
  measured by wrapping those module functions while the group runs (`_matching_clock`; the
  library is not changed, the wrappers return what the functions return); ``proposals`` is the
  pipeline's own proposals clock (`PipelineResult.seconds`) less ``matching`` (grouping: union-
  find, the combined matcher's repairs); ``3d`` and ``tracking`` are the pipeline's own clocks;
  ``filtering`` the Butterworth pass; ``other`` the rest of the wall time (the pipeline's glue
  between stages). Medians over the timed runs, per frame.
* ``jit_calls_per_frame``: XLA executable launches (``...LoadedExecutable::ExecuteHelper...``
  events) in a `jax.profiler` trace of one extra, untimed run; eager jnp operations count too
  (each is its own executable).
* ``host_round_trips_per_frame``: device-to-host fetches in the same run: `jax.Array`s given to
  numpy's converters (``np.asarray``, ``np.array``, ...) or converted to Python scalars, counted
  by wrapping those functions during that run (`_host_fetches`; on the CPU such a fetch is a
  zero-copy read that no profiler event shows, but the host waits for the device there).
  ``host_to_device_per_frame``: ``DevicePut`` events in the trace (numpy arguments of jitted
  calls).
* ``compilations``: XLA backend compilations (`jax.monitoring`'s
  ``/jax/core/compile/backend_compile_duration`` events) during the timed runs and the counting
  run, i.e. after the warm-up: 0 means nothing recompiled; ``compilations_warmup`` those of the
  warm-up run.

Scenes: synthetic panoptic5 recordings (5 cameras) with 1, 2, 4 and 8 people
(`scenes.recording`), and the real two-person trial of Pose2Sim's demo session
(``../shared/real/pose2sim-demo-s00``, 4 cameras, its raw ``pose/`` detections, read as
``experiments.pose2sim_demo.raw_detections`` reads them; skipped with a note where the folder is
missing). Where Pose2Sim is installed (``pip install .[bench]``), its person association,
triangulation and filtering are timed on the same trial (`pose2sim_timing`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import glob
import importlib.util
import os
import re
import shutil
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import jax
import numpy as np

from benchmarks import scenes
from mvpose_jax import matching as matching_module
from mvpose_jax.cameras import Rig
from mvpose_jax.data import load_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.pose2sim import find_trials
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.estimator_training import train_estimator
from mvpose_jax.features import single_person_samples
from mvpose_jax.inference import PipelineConfig, PipelineResult, run_pipeline, stream_pipeline
from mvpose_jax.jobs.infer import INFER_PIPELINE, resolve_pipeline
from mvpose_jax.jobs.session import SessionConfig, trial_config
from mvpose_jax.lifting import LiftingConfig
from mvpose_jax.matcher_settings import MatcherSettings, choose_matcher_settings
from mvpose_jax.matcher_training import train_matcher
from mvpose_jax.matching import MatchingConfig
from mvpose_jax.models import GATConfig, MLPConfig
from mvpose_jax.proposals import CombinedConfig
from mvpose_jax.skeletons import Detections
from mvpose_jax.smoothing import smooth_poses
from mvpose_jax.synthetic import generate_single_person_recordings
from mvpose_jax.trained import (
    PRETRAINED,
    Estimator,
    EstimatorConfig,
    Matcher,
    MatcherConfig,
    TrainConfig,
    load_estimator,
    load_matcher,
)

# geometric first: the others' yardstick
PIPELINES = ("geometric", "default", "paper", "dlt", "pretrained", "shipped")
MODES = ("live", "offline")
STAGES = ("matching", "proposals", "3d", "tracking", "filtering", "other")
CHUNK_FRAMES = 256
FPS = 30.0
LAYOUT = "coco18"
NUM_KEYPOINTS = 18  # coco18
REPO = Path(__file__).resolve().parents[1]
REAL_DATA = REPO.parent / "shared" / "real" / "pose2sim-demo-s00"  # experiments' ../shared/real
REAL_TRIAL = "S00_P01_T02_Participants1-2"
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
# Profiler event names: an XLA executable launch (CPU's PjRt client; the pattern also takes the
# other clients' ExecuteHelper events) and a host-to-device transfer.
EXECUTE_EVENT = re.compile(r"LoadedExecutable::ExecuteHelper")
PUT_EVENT = "DevicePut"


HOW = {
    "ms_per_frame": "median over the timed runs (after one warm-up run) of the run's wall time / "
    "frames; live: one stream_pipeline over one-frame chunks; offline: run_pipeline in chunks "
    f"of {CHUNK_FRAMES}, then smoothing.smooth_poses for the Butterworth-filtered pipelines",
    "stages_ms": "the median run's: matching = wall time inside matching.gat_match_table / "
    "geometric_match_table / combined_match_tables / epipolar_distances_of_rows (wrapped while "
    "the group runs); "
    "proposals = PipelineResult.seconds['proposals'] - matching; 3d, tracking = "
    "PipelineResult.seconds['poses'], ['tracking']; filtering = smooth_poses; other = the rest",
    "jit_calls_per_frame": "XLA executable launches (profiler host events matching "
    "'LoadedExecutable::ExecuteHelper') in one extra untimed run, per frame",
    "host_round_trips_per_frame": "device-to-host fetches in that run: jax.Arrays given to "
    "numpy.asarray/array/asanyarray/ascontiguousarray or converted to Python scalars "
    "(float/int/bool/item), counted by wrapping those during that run, per frame",
    "host_to_device_per_frame": "profiler 'DevicePut' events in that run, per frame",
    "compilations": "jax.monitoring backend_compile_duration events after the warm-up run",
}


@dataclasses.dataclass(frozen=True)
class PipelineTier:
    """How much the group measures.

    Attributes:
      people: people of the synthetic scenes (5 cameras each).
      live_frames, offline_frames: frames of the synthetic scenes timed per run in each mode.
      real_live_frames, real_offline_frames: the same for the real trial (None: all of it).
      repeats: timed runs after the warm-up (the median counts).
      count_frames: frames of the live counting run (offline: the whole recording).
      train_steps: training steps of each model (per rig).
      gat, mlp: model sizes.
      real_pipelines: the pipelines timed on the real trial (None: every one of `PIPELINES`).
    """

    people: tuple[int, ...]
    live_frames: int
    offline_frames: int
    real_live_frames: int | None
    real_offline_frames: int | None
    repeats: int
    count_frames: int
    train_steps: int
    gat: GATConfig = GATConfig()
    mlp: MLPConfig = MLPConfig.quick()
    real_pipelines: tuple[str, ...] | None = None


PIPELINE_TIERS = {
    "full": PipelineTier((1, 2, 4, 8), 200, 1024, None, None, 3, 32, 100),
    # The acceptance scenes only (4 people and the real trial), untrained models: compiling
    # every pipeline for every scene's shapes, and training, are most of a run's time.
    "quick": PipelineTier((4,), 24, 256, 24, 256, 3, 8, 0),
    # The real trial's reader and 4-camera shapes with and without models; every pipeline is
    # timed on the synthetic scene (each pipeline's compiles are most of the smoke run).
    "smoke": PipelineTier(
        (2,), 3, 8, 3, 8, 1, 2, 0, gat=GATConfig.quick(), real_pipelines=("geometric", "default")
    ),
}


# --------------------------------------------------------------------------- counting hooks

_compilations = [0]


def _on_duration(event: str, duration: float, **kwargs) -> None:
    del duration, kwargs
    if event == COMPILE_EVENT:
        _compilations[0] += 1


_listening = [False]


def _listen_for_compilations() -> None:
    if not _listening[0]:
        jax.monitoring.register_event_duration_secs_listener(_on_duration)
        _listening[0] = True


@contextlib.contextmanager
def _matching_clock(clock: dict[str, float]) -> Iterator[None]:
    """Adds the wall time of the pipeline's match-table calls to ``clock["matching"]``.

    The proposal stages call `matching.gat_match_table`, `matching.geometric_match_table`,
    `matching.combined_match_tables` (the GAT's scores and the epipolar distances of its pairs in
    one call) and `matching.epipolar_distances_of_rows` through the module's globals; each is
    wrapped here, for
    the duration of the context, by a wall clock around the call (each returns numpy, so the
    clock stops once the result is on the host). Results are unchanged.
    """
    names = (
        "gat_match_table",
        "geometric_match_table",
        "combined_match_tables",
        "epipolar_distances_of_rows",
    )
    saved = {n: getattr(matching_module, n) for n in names}

    def wrapped(fn: Callable) -> Callable:
        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                clock["matching"] += time.perf_counter() - t

        return timed

    try:
        for n, fn in saved.items():
            setattr(matching_module, n, wrapped(fn))
        yield
    finally:
        for n, fn in saved.items():
            setattr(matching_module, n, fn)


@contextlib.contextmanager
def _host_fetches(counter: Counter) -> Iterator[None]:
    """Counts `jax.Array` -> host conversions in ``counter["fetches"]`` while the context lasts:
    numpy's converters (``np.asarray``, ``np.array``, ``np.asanyarray``,
    ``np.ascontiguousarray``, called through the numpy module as the library and jax call them)
    given a `jax.Array`, and scalar conversions of one (``float``, ``int``, ``bool``,
    ``.item()``). On the CPU a fetch is a zero-copy read through the buffer protocol, which no
    profiler event shows, but it still waits for the device: each is a host round trip."""
    array_type = type(jax.device_put(np.float32(0)))  # jax.Array's concrete class; no compile
    converters = ("asarray", "array", "asanyarray", "ascontiguousarray")
    scalars = [
        n
        for n in ("__float__", "__int__", "__bool__", "__index__", "item")
        if n in vars(array_type)
    ]
    saved_np = {n: getattr(np, n) for n in converters}
    saved_scalar = {n: vars(array_type)[n] for n in scalars}

    def converter(fn):
        def counted(a, *args, **kwargs):
            if isinstance(a, jax.Array):
                counter["fetches"] += 1
            return fn(a, *args, **kwargs)

        return counted

    def scalar(fn):
        def counted(self, *args, **kwargs):
            counter["fetches"] += 1
            return fn(self, *args, **kwargs)

        return counted

    try:
        for n, fn in saved_np.items():
            setattr(np, n, converter(fn))
        for n, fn in saved_scalar.items():
            setattr(array_type, n, scalar(fn))
        yield
    finally:
        for n, fn in saved_np.items():
            setattr(np, n, fn)
        for n, fn in saved_scalar.items():
            setattr(array_type, n, fn)


def _profile_counts(run: Callable[[], None]) -> dict[str, int]:
    """Executable launches and host-to-device puts (a `jax.profiler` trace, host events only, no
    Python tracer) and device-to-host fetches (`_host_fetches`) while ``run()`` runs."""
    options = jax.profiler.ProfileOptions()
    options.python_tracer_level = 0
    counts: Counter = Counter()
    with tempfile.TemporaryDirectory() as tmp:
        with _host_fetches(counts), jax.profiler.trace(tmp, profiler_options=options):
            run()
        for path in glob.glob(os.path.join(tmp, "**", "*.xplane.pb"), recursive=True):
            data = jax.profiler.ProfileData.from_file(path)
            for plane in data.planes:
                for line in plane.lines:
                    for event in line.events:
                        if EXECUTE_EVENT.search(event.name):
                            counts["launches"] += 1
                        elif event.name == PUT_EVENT:
                            counts["puts"] += 1
    return {k: counts[k] for k in ("launches", "fetches", "puts")}


# --------------------------------------------------------------------------- pipelines


@dataclasses.dataclass(frozen=True)
class RigModels:
    """A scene rig's trained matcher and estimator, and what training them took."""

    matcher: Matcher
    estimator: Estimator
    settings: MatcherSettings  # the proposal settings chosen for the matcher, as train-matcher does
    seconds: float
    steps: int
    pretrained: Estimator  # the package's rig-agnostic estimator, set up for the rig
    pretrained_matcher: Matcher  # the package's rig-agnostic matcher, set up for the rig

    def for_pipeline(self, needs: bool | str) -> RigModels | None:
        """What a pipeline of `pipeline_configs` runs with: these models (True), none (False),
        the pretrained estimator alone ("pretrained"), or both shipped models ("shipped")."""
        if needs == "pretrained":
            return dataclasses.replace(self, matcher=None, estimator=self.pretrained)
        if needs == "shipped":
            return dataclasses.replace(
                self, matcher=self.pretrained_matcher, estimator=self.pretrained
            )
        return self if needs else None


def train_models(rig: Rig, tier: PipelineTier, seed: int = 0) -> RigModels:
    """A matcher (``tier.gat``) and an estimator (``tier.mlp``) for ``rig``'s cameras, trained for
    ``tier.train_steps`` steps on synthetic single-person recordings of that rig (no labels; 0
    steps: random weights, `scenes.matcher_for` and `scenes.estimator_for`), and the matcher's
    proposal settings chosen on frames composed from held-out recordings as ``mvpose-jax
    train-matcher`` chooses them (`matcher_settings.choose_matcher_settings`): what ``infer
    --matcher`` then reads. Chosen settings keep the proposals' people near the scene's however
    briefly the GAT was trained (at the paper's 0.5 a 3-step GAT proposes nobody)."""
    t0 = time.perf_counter()
    recs = generate_single_person_recordings(rig, num_recordings=4, num_frames=40, seed=seed)
    train, dev = recs[:3], recs[3:]
    names = tuple(rig.names)
    steps = tier.train_steps
    if steps == 0:
        matcher = scenes.matcher_for(rig, NUM_KEYPOINTS, tier.gat)
        estimator = scenes.estimator_for(rig, NUM_KEYPOINTS, tier.mlp)
    else:
        quick = MatcherConfig.quick()
        matcher_config = dataclasses.replace(
            quick,
            cameras=names,
            gat=tier.gat,
            train=dataclasses.replace(
                quick.train, batch_size=4, max_steps=steps, max_epochs=10**6, seed=seed
            ),
            samples_per_epoch=4 * steps,
            num_dev_samples=4,
        )
        matcher, _ = train_matcher(rig, train, dev, matcher_config, progress=False)
        xy, score = single_person_samples(train, names)
        dev_xy, dev_score = single_person_samples(dev, names)
        estimator_config = EstimatorConfig(
            train_cameras=names,
            infer_cameras=names,
            mlp=tier.mlp,
            train=TrainConfig(
                learning_rate=1e-3, batch_size=32, max_steps=steps, max_epochs=10**6, seed=seed
            ),
        )
        estimator, _ = train_estimator(
            rig, xy, score, dev_xy, dev_score, estimator_config, progress=False
        )
    settings = choose_matcher_settings(matcher, dev, num_samples=64, seed=seed)
    seconds = time.perf_counter() - t0
    return RigModels(
        matcher,
        estimator,
        settings,
        seconds,
        steps,
        load_estimator(PRETRAINED, rig),
        load_matcher(PRETRAINED, rig),
    )


def pipeline_configs(
    settings: MatcherSettings | None = None,
) -> dict[str, tuple[PipelineConfig, bool]]:
    """{name: (config, the models it needs)} of `PIPELINES`, each as `infer` resolves it for a
    matcher folder holding ``settings`` (None: a folder without chosen settings: the GAT at the
    paper's 0.5, `CombinedConfig()`). Needs: True (the rig's matcher and estimator), False
    (none), "pretrained" (the shipped estimator alone) or "shipped" (both shipped models,
    `RigModels.for_pipeline`)."""
    infer_matching = INFER_PIPELINE.matching
    threshold = settings.threshold if settings is not None else 0.5
    combined = settings.combined if settings is not None else CombinedConfig()
    return {
        # `resolve_pipeline(INFER_PIPELINE, matcher_folder, estimator=True)`: combined proposals
        # at the folder's settings, the blend.
        "default": (
            dataclasses.replace(
                INFER_PIPELINE,
                matching=dataclasses.replace(
                    infer_matching, proposals="combined", threshold=0.5, combined=combined
                ),
                lifting=dataclasses.replace(INFER_PIPELINE.lifting, method="blend"),
            ),
            True,
        ),
        "paper": (
            PipelineConfig(
                MatchingConfig("gat", threshold), LiftingConfig("mlp"), chunk_frames=CHUNK_FRAMES
            ),
            True,
        ),
        # `infer --method robust` without models: INFER_PIPELINE with epipolar proposals.
        "geometric": (
            dataclasses.replace(
                INFER_PIPELINE,
                matching=dataclasses.replace(infer_matching, proposals="epipolar", threshold=0.5),
                lifting=dataclasses.replace(INFER_PIPELINE.lifting, method="robust"),
            ),
            False,
        ),
        "dlt": (
            PipelineConfig(
                MatchingConfig("epipolar", 0.5), LiftingConfig("dlt"), chunk_frames=CHUNK_FRAMES
            ),
            False,
        ),
        # `infer --estimator pretrained`: epipolar proposals (no matcher), the blend.
        "pretrained": (
            dataclasses.replace(
                INFER_PIPELINE,
                matching=dataclasses.replace(infer_matching, proposals="epipolar", threshold=0.5),
                lifting=dataclasses.replace(INFER_PIPELINE.lifting, method="blend"),
            ),
            "pretrained",
        ),
        # `infer --matcher pretrained --estimator pretrained`, resolved as infer resolves it.
        "shipped": (
            resolve_pipeline(INFER_PIPELINE, PRETRAINED, estimator=True),
            "shipped",
        ),
    }


def _frames(det: Detections, stop: int | None) -> Detections:
    return Detections(*(np.asarray(a)[:stop] for a in det))


def _one_frame_chunks(det: Detections) -> list[tuple[int, Detections]]:
    return [
        (f, Detections(det.xy[f : f + 1], det.score[f : f + 1], det.count[f : f + 1]))
        for f in range(len(det.count))
    ]


def _pose_results(res: PipelineResult) -> PoseResults:
    return PoseResults(
        res.poses,
        res.confidence,
        res.members,
        res.identity,
        res.cameras,
        LAYOUT,
        None,
        res.track,
    )


def _filters(config: PipelineConfig) -> bool:
    """Whether `infer` filters the pipeline's results while assembling them (tracked, with a
    filter that does not run in the stream)."""
    filt = config.filtering
    return config.tracking is not None and not filt.streaming and filt.name != "none"


def _filter(config: PipelineConfig, res: PipelineResult, fps: float) -> None:
    """`infer`'s assembly filter on the whole result (`_filters` pipelines)."""
    filt = config.filtering
    smooth_poses(
        _pose_results(res),
        fps=fps,
        filter=filt.name,
        cutoff_hz=filt.cutoff_hz,
        fill_gap_s=filt.fill_gap_s,
        outlier_m=filt.outlier_m or None,
        one_euro=filt.one_euro,
    )


def _run_once(
    mode: str, rig: Rig, det: Detections, config: PipelineConfig, models: RigModels | None, fps
) -> dict:
    """One run: its wall time, the stages' times (seconds) and the people found."""
    kwargs = dict(
        matcher=models.matcher if models else None,
        estimator=models.estimator if models else None,
        layout=LAYOUT,
        fps=fps,
    )
    clock = {"matching": 0.0}
    people = 0
    seconds = Counter()
    with _matching_clock(clock):
        gc.collect()
        t0 = time.perf_counter()
        if mode == "live":
            chunks = _one_frame_chunks(det)
            for _, res in stream_pipeline(rig, chunks, config, **kwargs):
                seconds.update(res.seconds)
                people += int(np.asarray(res.poses.valid).sum())
            t_filter = time.perf_counter()
        else:
            res = run_pipeline(rig, det, config, **kwargs)
            seconds.update(res.seconds)
            people = int(np.asarray(res.poses.valid).sum())
            t_filter = time.perf_counter()
            if _filters(config):
                _filter(config, res, fps)
        t1 = time.perf_counter()
    stages = {
        "matching": clock["matching"],
        "proposals": seconds["proposals"] - clock["matching"],
        "3d": seconds["poses"],
        "tracking": seconds.get("tracking", 0.0),
        "filtering": t1 - t_filter if mode == "offline" and _filters(config) else 0.0,
    }
    stages["other"] = max(0.0, (t1 - t0) - sum(stages.values()))
    return {"seconds": t1 - t0, "stages": stages, "people": people}


def time_pipeline(
    mode: str,
    rig: Rig,
    det: Detections,
    config: PipelineConfig,
    models: RigModels | None,
    *,
    repeats: int,
    count_frames: int,
    fps: float = FPS,
) -> dict:
    """One (pipeline, mode) on one scene: a warm-up run, ``repeats`` timed runs and a counting
    run (the module docstring says what each number is)."""
    _listen_for_compilations()
    F = len(det.count)
    before = _compilations[0]
    _run_once(mode, rig, det, config, models, fps)  # warm-up: compiles, builds graphs
    warmup_compilations = _compilations[0] - before
    before = _compilations[0]
    runs = [_run_once(mode, rig, det, config, models, fps) for _ in range(repeats)]
    count_det = _frames(det, count_frames) if mode == "live" else det
    counts = _profile_counts(lambda: _run_once(mode, rig, count_det, config, models, fps))
    n_count = len(count_det.count)
    per_frame = [r["seconds"] / F * 1e3 for r in runs]
    # The stages of the median run (an odd number of runs: its total is the median), so that
    # they add up to ms_per_frame.
    middle = runs[int(np.argsort(per_frame)[(len(runs) - 1) // 2])]
    return {
        "frames": F,
        "ms_per_frame": float(np.median(per_frame)),
        "ms_per_frame_runs": per_frame,
        "stages_ms": {s: middle["stages"][s] / F * 1e3 for s in STAGES},
        "people_found": runs[0]["people"] / max(F, 1),
        "jit_calls_per_frame": counts["launches"] / max(n_count, 1),
        "host_round_trips_per_frame": counts["fetches"] / max(n_count, 1),
        "host_to_device_per_frame": counts["puts"] / max(n_count, 1),
        "counted_frames": n_count,
        "compilations": _compilations[0] - before,
        "compilations_warmup": warmup_compilations,
    }


# --------------------------------------------------------------------------- scenes


def real_scene(
    data: Path = REAL_DATA, frames: int | None = None
) -> tuple[Rig, Detections, float] | str:
    """The real two-person trial's rig (its paired cameras), raw ``pose/`` detections (coco18),
    as ``experiments.pose2sim_demo.raw_detections`` reads them, and the frame rate ``infer
    --session`` uses (the session's, else 30); or a note why not."""
    if not Path(data).is_dir():
        return f"{data} is missing: the real trial was skipped"
    trials = {t.name: t for t in find_trials(data, pose_folders=("pose",)).trials}
    if REAL_TRIAL not in trials:
        return f"{data} has no trial {REAL_TRIAL}: the real trial was skipped"
    trial = trials[REAL_TRIAL]
    session = SessionConfig(str(trial.folder), "unused", trc=False)
    infer = trial_config(session, trial)
    source = infer.detections
    rig = load_rig(str(trial.calibration), cameras=list(trial.cameras))
    recording = load_recording(source.path, layout=LAYOUT, rig=rig, **source.reading_options())
    return rig, _frames(Detections(*recording.detections), frames), infer.fps or FPS


def _scene_records(
    scene: str,
    rig: Rig,
    live: Detections,
    offline: Detections,
    people: float | None,
    models: RigModels,
    tier: PipelineTier,
    fps: float,
    pipelines: tuple[str, ...] = PIPELINES,
) -> list[dict]:
    """Every (pipeline, mode) record of one scene for ``pipelines`` (with "geometric"), with its
    ratio to ``geometric``."""
    if "geometric" not in pipelines:
        raise ValueError("the ratios need the geometric pipeline")
    records = []
    for mode in MODES:
        det = live if mode == "live" else offline
        by_name = {}
        for name in pipelines:
            config, needs_models = pipeline_configs(models.settings)[name]
            by_name[name] = time_pipeline(
                mode,
                rig,
                det,
                config,
                models.for_pipeline(needs_models),
                repeats=tier.repeats,
                count_frames=tier.count_frames,
                fps=fps,
            )
        geometric = by_name["geometric"]["ms_per_frame"]
        scene_people = people if people is not None else by_name["geometric"]["people_found"]
        for name in pipelines:
            r = by_name[name]
            config = pipeline_configs(models.settings)[name][0]
            records.append(
                {
                    "group": "pipeline",
                    "scene": scene,
                    "views": rig.num_cameras,
                    "people": scene_people,
                    "pipeline": name,
                    "mode": mode,
                    **r,
                    "ratio_to_geometric": r["ms_per_frame"] / geometric,
                    "tracked": config.tracking is not None,
                    "filter": config.filtering.name if config.tracking is not None else "none",
                    "proposals": config.matching.proposals,
                    "method": config.lifting.method,
                }
            )
    return records


def _training_record(models: RigModels) -> dict:
    return {
        "seconds": models.seconds,
        "steps": models.steps,
        "gat_threshold": models.settings.threshold,
        "combined_threshold": models.settings.combined.threshold,
        "epipolar_cutoff_px": models.settings.combined.epipolar_cutoff_px,
    }


def _true_people(rec) -> float:
    return float(np.asarray(rec.ground_truth.valid).sum(axis=1).mean())


def pipeline_group(tier_name: str) -> dict:
    """The group's result: one record per (scene, pipeline, mode), the models' training, the
    real trial's note and Pose2Sim's timing (or why not)."""
    tier = PIPELINE_TIERS[tier_name]
    records, training, notes = [], {}, []
    models = None
    for n in tier.people:
        rig, rec = scenes.recording(5, n, max(tier.live_frames, tier.offline_frames), seed=n)
        if models is None:
            models = train_models(rig, tier)
            training["panoptic5"] = _training_record(models)
        det = Detections(*(np.asarray(a) for a in rec.detections))
        records += _scene_records(
            f"panoptic5-{n}p",
            rig,
            _frames(det, tier.live_frames),
            _frames(det, tier.offline_frames),
            _true_people(rec),
            models,
            tier,
            FPS,
        )
    lengths = (tier.real_live_frames, tier.real_offline_frames)
    real = real_scene(frames=None if None in lengths else max(lengths))
    pose2sim = {"installed": importlib.util.find_spec("Pose2Sim") is not None}
    if isinstance(real, str):
        notes.append(real)
    else:
        real_rig, real_det, real_fps = real
        real_models = train_models(real_rig, tier)
        training["pose2sim-demo"] = _training_record(real_models)
        records += _scene_records(
            "pose2sim-demo-2p",
            real_rig,
            _frames(real_det, tier.real_live_frames),
            _frames(real_det, tier.real_offline_frames),
            None,
            real_models,
            tier,
            real_fps,
            tier.real_pipelines or PIPELINES,
        )
        if pose2sim["installed"]:
            whole = real_scene()  # Pose2Sim runs the whole trial: its frames are the divisor
            pose2sim.update(pose2sim_timing(REAL_DATA, len(whole[1].count)))
            ours = next(
                r
                for r in records
                if r["scene"] == "pose2sim-demo-2p"
                and r["pipeline"] == "default"
                and r["mode"] == "offline"
            )
            if pose2sim.get("ms_per_frame"):
                pose2sim["ratio_to_default_offline"] = (
                    pose2sim["ms_per_frame"] / ours["ms_per_frame"]
                )
    if not pose2sim["installed"]:
        pose2sim["note"] = (
            "Pose2Sim is not installed (the benchmarks' optional extra: pip install .[bench])"
        )
    return {
        "records": records,
        "training": training,
        "models": {"gat": dataclasses.asdict(tier.gat), "mlp": dataclasses.asdict(tier.mlp)},
        "chunk_frames": CHUNK_FRAMES,
        "repeats": tier.repeats,
        "notes": notes,
        "pose2sim": pose2sim,
        "how": HOW,
    }


# --------------------------------------------------------------------------- Pose2Sim


def pose2sim_timing(data: Path, frames: int) -> dict:
    """Pose2Sim's person association, triangulation and filtering on the real trial, each timed
    (seconds and ms per frame), on a copy of the session (Pose2Sim writes beside its input).

    Runs Pose2Sim's own entry points (``Pose2Sim.personAssociation``, ``triangulation``,
    ``filtering``) with the session's ``Config.toml`` from inside the trial folder, as its
    documentation runs them. Not exercised where Pose2Sim is not installed.
    """
    from Pose2Sim import Pose2Sim as p2s  # the benchmarks' optional extra

    out: dict = {"frames": frames}
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        session = Path(tmp) / Path(data).name
        shutil.copytree(data, session)
        trial = session / REAL_TRIAL
        for folder in ("pose-associated", "pose-3d"):  # the outputs it would otherwise reuse
            shutil.rmtree(trial / folder, ignore_errors=True)
        try:
            os.chdir(trial)
            seconds = {}
            for step in ("personAssociation", "triangulation", "filtering"):
                t = time.perf_counter()
                getattr(p2s, step)()
                seconds[step] = time.perf_counter() - t
        except Exception as e:  # its failure is a result, not the harness's
            return {**out, "error": f"{type(e).__name__}: {e}"}
        finally:
            os.chdir(cwd)
    total = sum(seconds.values())
    return {
        **out,
        "seconds": seconds,
        "ms_per_frame": total / frames * 1e3,
        "note": "the whole trial as Pose2Sim runs it (its files read and written)",
    }


# --------------------------------------------------------------------------- report


def markdown(result: dict) -> list[str]:
    """The group's tables (lines of Markdown)."""
    lines = [
        "",
        f"## Pipelines as users run them (ms per frame; median of {result['repeats']} runs after "
        "a warm-up)",
        "",
        "live: one frame per `stream_pipeline` call (tracker state kept); offline: "
        f"`run_pipeline` in chunks of {result['chunk_frames']} (+ the Butterworth filter where "
        "the pipeline has it). ratio: to `geometric` on the same scene and mode. Stages in ms "
        "per frame; jit: XLA executable launches per frame; d2h: device-to-host fetches per "
        "frame; recompiles: compilations after the warm-up.",
        "",
        "| scene | views | people | pipeline | mode | ms/frame | ratio | matching | proposals | "
        "3D | tracking | filtering | other | jit | d2h | recompiles |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["records"]:
        s = r["stages_ms"]
        lines.append(
            f"| {r['scene']} | {r['views']} | {r['people']:.1f} | {r['pipeline']} | {r['mode']} | "
            f"{r['ms_per_frame']:.2f} | {r['ratio_to_geometric']:.2f} | "
            + " | ".join(f"{s[k]:.2f}" for k in STAGES)
            + f" | {r['jit_calls_per_frame']:.1f} | {r['host_round_trips_per_frame']:.1f} | "
            f"{r['compilations']} |"
        )
    p2s = result.get("pose2sim") or {}
    if p2s.get("ms_per_frame"):
        lines += [
            "",
            f"Pose2Sim on the real trial: {p2s['ms_per_frame']:.1f} ms/frame (association + "
            f"triangulation + filtering), {p2s.get('ratio_to_default_offline', float('nan')):.0f}x "
            "our default offline.",
        ]
    else:
        lines += ["", f"Pose2Sim: {p2s.get('note') or p2s.get('error', 'not timed')}."]
    lines += [f"- {n}" for n in result.get("notes", [])]
    training = result.get("training") or {}
    if training:
        each = ", ".join(
            f"{rig} {t['steps']} steps in {t['seconds']:.0f} s" for rig, t in training.items()
        )
        lines += ["", f"Models (GAT and MLP, trained per rig): {each}."]
    return lines
