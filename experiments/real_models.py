"""Models for the real recordings, trained without a label, as a user gets them.

Two recipes, each a matcher and an estimator kept as model folders (`fitting.cached_models`:
``matcher/``, ``estimator/``, ``fit.json``; ``mvpose-jax infer --matcher DIR/matcher --estimator
DIR/estimator`` runs them):

* **synthetic recordings of the rig** (`synthetic_models`): single-person recordings simulated on
  the real rig's cameras, their floor measured from the recording's own people
  (`floor.estimate_floor_from_detections`, what ``mvpose-jax generate --floor-from`` does: the
  feet, or where they are hidden, as in MVOR's operating room, upright people's shoulders and a
  standing-height prior; up from their torsos where the calibration has none) and jittered by
  generate's training jitter (0.3 m);
* **a session's own single-person trials** (`trial_models`, the paper's recipe on real data): the
  estimator on their frames, the matcher on multi-person frames composed from them;
* **both mixed** (`mixed_models`): the synthetic recordings and the real trials together.

The budget (`REAL_SCALE`) is the experiments' quick recipe (300 x 20 training frames, the
paper's GAT, the small residual MLP) with fewer steps, so that ``python -m experiments.real``
trains its three model pairs within its 20 minutes on 2 cores; ``--smoke`` uses the smoke scale.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from experiments.config import SCALES, Scale, estimator_config
from experiments.data import Data, make_data
from experiments.fitting import Models, cached_models
from mvpose_jax.cameras import Rig
from mvpose_jax.floor import FloorEstimate
from mvpose_jax.jobs.generate import TRAINING_FLOOR_JITTER_M
from mvpose_jax.models import MLPConfig
from mvpose_jax.synthetic import DetectorConfig

# Steps by number of views: the quick scale's (3 views 20000, 5-6 views 6000) cut to fit the
# benchmark's budget (about 3 minutes per model pair on 2 cores).
REAL_SCALE = dataclasses.replace(
    SCALES["quick"],
    matcher_steps={2: 3000, 3: 3000, 4: 2500, 5: 2000, 6: 2000},
    estimator=estimator_config(MLPConfig.quick(), steps=2000),
    threshold_frames=512,
    train_floor_jitter_m=TRAINING_FLOOR_JITTER_M,
)
SMOKE_SCALE = dataclasses.replace(
    SCALES["smoke"],
    matcher_steps={v: 4 for v in range(2, 11)},
    train_floor_jitter_m=TRAINING_FLOOR_JITTER_M,
)
SEED = 0
# Real recordings among synthetic ones (`mixed_models`): repeated so that they weigh (the demo's
# 104 real frames x 10 against 6000 synthetic ones: about 15 % of the training frames).
REAL_REPEATS = 10
MODELS_RECIPE = (
    "matcher (the paper's GAT) and estimator (small residual MLP) trained without labels on 300 "
    "synthetic single-person recordings of 20 frames on the rig (10 x 50 dev frames), the floor "
    "measured from the recording's own people (feet, else upright shoulders and a 1.39 m "
    "standing shoulder height; up from their torsos where the calibration has none) with "
    "generate's 0.3 m training jitter; matcher steps 3000 (3 "
    "views) / 2500 (4 views), estimator 2000 steps; the GAT's and the combined matcher's "
    "thresholds chosen on 512 frames composed from the dev recordings; training seed 0"
)


def scale(smoke: bool) -> Scale:
    """`SMOKE_SCALE` or `REAL_SCALE`."""
    return SMOKE_SCALE if smoke else REAL_SCALE


def synthetic_models(
    rig: Rig,
    floor: FloorEstimate,
    folder: Path,
    *,
    smoke: bool,
    progress: bool = False,
    detector: DetectorConfig | None = None,
    seed: int = SEED,
) -> Models:
    """The matcher and estimator of ``rig`` trained on synthetic recordings of it with the
    measured ``floor`` (loaded from ``folder`` when it holds them). ``detector``: the
    recordings' simulated detector, such as one fitted to the real recording's own detections
    (`detector_fit.fit_detector`, what ``mvpose-jax generate --detector-like`` does), so that
    the models see its jitter, misses and false skeletons while they train; None: the default
    one. ``seed``: the recordings' and the training's."""
    return cached_models(
        rig,
        folder,
        seed=seed,
        scale=scale(smoke),
        progress=progress,
        floor_height=floor.height,
        up=floor.measured_up,
        detector=detector,
    )


def trial_models(
    rig: Rig, train: list, dev: list, folder: Path, *, smoke: bool, progress: bool = False
) -> Models:
    """The matcher and estimator of ``rig`` trained on real single-person recordings ``train``
    (settings chosen on ``dev``, multi-person frames composed from them)."""
    data = Data(rig, list(train), list(dev), {})
    return cached_models(rig, folder, seed=SEED, scale=scale(smoke), progress=progress, data=data)


def mixed_models(
    rig: Rig,
    floor: FloorEstimate,
    train: list,
    dev: list,
    folder: Path,
    *,
    smoke: bool,
    progress: bool = False,
) -> Models:
    """The matcher and estimator of ``rig`` trained on synthetic recordings of it (as
    `synthetic_models` makes them) mixed with real single-person recordings ``train`` (each
    repeated `REAL_REPEATS` times, so that the few real frames weigh) and chosen on both dev
    sets."""
    sc = scale(smoke)
    synthetic = make_data(
        rig, {}, sc, SEED, progress, floor_height=floor.height, up=floor.measured_up
    )
    data = Data(rig, synthetic.train + list(train) * REAL_REPEATS, synthetic.dev + list(dev), {})
    return cached_models(rig, folder, seed=SEED, scale=sc, progress=progress, data=data)


def training_record(models: Models, floor: FloorEstimate | None = None) -> dict:
    """What the report says of a model pair: its training and the settings chosen with it."""
    fit = models.fit
    out = {
        "seed": models.seed,
        "matcher_steps": fit.get("train_steps"),
        "matcher_seconds": fit.get("train_seconds"),
        "gat_threshold": fit.get("threshold"),
        "combined_threshold": fit.get("combined", {}).get("threshold"),
        "epipolar_cutoff_px": fit.get("geometric_cutoff_px"),
        "composed_dev_ari_gat": _best(fit.get("dev_ari_by_threshold")),
        "composed_dev_ari_combined": _best(fit.get("dev_ari_by_combined_threshold")),
    }
    if floor is not None:
        out["floor"] = dataclasses.asdict(floor)
    return out


def _best(by_setting: dict | None) -> float | None:
    return max(by_setting.values()) if by_setting else None
