"""Trained models as inference uses them: their configs, the bundles and the loaders.

`Matcher` and `Estimator` hold what inference needs (the model's graph definition, its
parameters and cameras); `load_matcher` / `load_estimator` rebuild them from a training run's
checkpoint folder by restoring the parameters alone, so nothing here imports an optimiser.
The configs are frozen dataclasses whose defaults are the paper's (DESIGN.md §1.2-1.3).
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, rig_centre_and_radius
from mvpose_jax.checkpoints import Checkpoints
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.models import GATConfig, MatchingGAT, MLPConfig, PoseMLP


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (defaults: the paper's for the 3D estimator).

    Attributes:
      learning_rate: Adam's step size (paper 1e-4).
      clip_norm: global gradient-norm clip (paper 10).
      batch_size: seed samples per step (augmented ones come on top).
      max_epochs: hard limit on passes over the training set.
      max_steps: optional hard limit on steps (None: epochs decide).
      eval_every: validate every this many epochs.
      patience: stop after this many validations without improvement (paper 20).
      seed: seeds initialisation, shuffling and augmentation.
      final_lr_fraction: 1.0 keeps the step size constant (the paper); below 1 it decays on a
        cosine to this fraction of ``learning_rate`` at the last step (shorter CPU runs).
      num_devices: None (default): one device, no mesh. n >= 1: data-parallel over the first n
        devices (of every process, `parallel.make_data_mesh`): the batch is split over them,
        parameters and optimiser state are replicated. The estimator needs ``batch_size``
        divisible by n; the matcher splits its graphs as evenly as they go.
      checkpoint_every_steps: with a checkpoint folder, also save the latest state every this
        many steps (besides each validation), so a killed run loses at most this many steps;
        0: only at validations.
      max_to_keep: latest checkpoints kept (older ones are deleted after a newer one is written).

    ``num_devices``, ``checkpoint_every_steps`` and ``max_to_keep`` change how a run is executed,
    not what it computes: a resumed run may change them (and its length), nothing else.
    """

    learning_rate: float = 1e-4
    clip_norm: float = 10.0
    batch_size: int = 256
    max_epochs: int = 10_000
    max_steps: int | None = None
    eval_every: int = 1
    patience: int = 20
    seed: int = 0
    final_lr_fraction: float = 1.0
    num_devices: int | None = None
    checkpoint_every_steps: int = 500
    max_to_keep: int = 3


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
    """A 3D estimator: its cameras, network and training.

    Attributes:
      train_cameras: names of C_t (None: every camera of the rig).
      infer_cameras: names of C_i, a subset of C_t (None: C_t).
      mlp: the network.
      train: optimisation.
      num_augment: derived view-subset samples per seed sample (paper: up to 4).
      loss_power: the per-sample loss is e_d ** loss_power, e_d the summed Manhattan
        reprojection error; 2 is the paper's. 1 weighs every sample alike, so a few samples
        with gross detector errors (swapped limbs, a false positive taken for the person)
        cannot drown the rest.
    """

    train_cameras: tuple[str, ...] | None = None
    infer_cameras: tuple[str, ...] | None = None
    mlp: MLPConfig = MLPConfig()
    train: TrainConfig = TrainConfig()
    num_augment: int = 4
    loss_power: float = 2.0


class Estimator(NamedTuple):
    """A trained 3D estimator: what inference needs."""

    graphdef: Any
    rest: Any
    params: Any
    rig_infer: Rig
    config: EstimatorConfig
    # (centre (3,), radius ()) of the normalised space: the TRAINING rig's (see
    # `features.estimator_inputs`).
    normalisation: tuple[Any, Any]


def estimator_config_from_dict(d: dict) -> EstimatorConfig:
    """Rebuilds an `EstimatorConfig` from its saved JSON form (`dataclasses.asdict`)."""
    tup = lambda v: None if v is None else tuple(v)  # noqa: E731
    try:
        mlp = MLPConfig(**{**d["mlp"], "widths": tuple(d["mlp"]["widths"])})
        return EstimatorConfig(
            train_cameras=tup(d["train_cameras"]),
            infer_cameras=tup(d["infer_cameras"]),
            mlp=mlp,
            train=TrainConfig(**d["train"]),
            num_augment=d["num_augment"],
            loss_power=d["loss_power"],
        )
    except (KeyError, TypeError) as e:
        raise InputError(f"not an estimator config ({e})", field="config") from None


def load_estimator(directory: str | Path, rig: Rig, which: str = "best") -> Estimator:
    """Restores an estimator saved by `train_estimator` (its config comes with the checkpoint).

    Args:
      directory: the ``checkpoint_dir`` of training.
      rig: a rig holding the estimator's inference cameras (by name).
    """
    checkpoints = Checkpoints(_trained_folder(directory, which, "train-estimator"))
    try:
        saved = checkpoints.read_config(which)
        config = estimator_config_from_dict(saved)
        if "num_keypoints" not in saved:
            raise InputError(
                "checkpoint config lacks num_keypoints", file=directory, field="config"
            )
        rig_infer = rig.select(list(config.infer_cameras or config.train_cameras or rig.names))
        K = int(saved["num_keypoints"])
        graphdef, params, rest = nnx.split(
            PoseMLP(rig_infer.num_cameras, K, config.mlp, rngs=nnx.Rngs(0)), nnx.Param, ...
        )
        params = checkpoints.restore_params(jax.eval_shape(lambda: params), which)
    finally:
        checkpoints.close()
    # Checkpoints from before the normalisation was saved used the inference rig's own.
    normalisation = rig_centre_and_radius(rig_infer)
    if "frame" in saved:
        f = np.asarray(saved["frame"], np.float32)
        if f.shape != (4,) or not np.isfinite(f).all() or f[3] <= 0:
            raise InputError(
                "the saved normalisation frame is not [cx, cy, cz, radius > 0]",
                file=directory,
                field="config.frame",
            )
        normalisation = (jnp.asarray(f[:3]), jnp.asarray(f[3]))
    _warn_if_worse_than_triangulation(Path(directory))
    return Estimator(graphdef, rest, params, rig_infer, config, normalisation)


# Written by `train.train_estimator` beside the checkpoints.
DEV_QUALITY_FILE = "dev_reprojection.json"


class ModelQualityWarning(MvposeWarning):
    """A trained model does worse on its own dev data than the geometry it should improve on."""


def _warn_if_worse_than_triangulation(directory: Path) -> None:
    path = directory / DEV_QUALITY_FILE
    if not path.is_file():
        return  # trained before the comparison was written
    try:
        q = json.loads(path.read_text())
        est, tri = float(q["estimator_px"]), float(q["triangulation_px"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"unreadable ({e})", file=path) from None
    if est > tri:
        warnings.warn(
            f"{directory}: on its dev recordings this estimator reprojects {est:.2f} px per keypoint "
            f"where triangulation reprojects {tri:.2f} px (same keypoints): it is likely trained "
            "too briefly or on other data; triangulation (no --estimator) may serve better",
            ModelQualityWarning,
            stacklevel=3,
        )


# =========================================================================== skeleton matching


MATCHER_TRAIN = TrainConfig(
    learning_rate=1e-4, batch_size=15, max_epochs=1000, eval_every=5, patience=5
)


@dataclasses.dataclass(frozen=True)
class MatcherConfig:
    """A skeleton matcher: its cameras, network, training and training-sample composition.

    Attributes:
      cameras: names of the inference cameras C_i (None: every camera of the rig).
      gat: the network.
      train: optimisation; ``batch_size`` counts graphs (frames) per step.
      max_people: most single-person frames composed into one training frame. The paper draws
        up to the number of recordings; we cap it (default 8, the largest test scene) so graph
        sizes stay those of real scenes however many recordings there are.
      samples_per_epoch: composed training frames per epoch (samples are streamed, never stored).
      num_dev_samples: composed validation frames, drawn once from the dev recordings.
      subset_probability: share of samples that keep only a random subset of the views.
      min_views: the smallest view subset kept by augmentation.
      keypoint_dropout: largest per-skeleton keypoint-drop rate of the missing-keypoint
        augmentation (`graphs.compose_samples`); 0 = none (the paper).
    """

    cameras: tuple[str, ...] | None = None
    gat: GATConfig = GATConfig()
    train: TrainConfig = MATCHER_TRAIN
    max_people: int = 8
    samples_per_epoch: int = 1500
    num_dev_samples: int = 300
    subset_probability: float = 0.5
    min_views: int = 2
    keypoint_dropout: float = 0.0

    @property
    def steps_per_epoch(self) -> int:
        return max(1, self.samples_per_epoch // self.train.batch_size)

    @classmethod
    def quick(cls, cameras: tuple[str, ...] | None = None) -> MatcherConfig:
        """The small network, a larger step size and short epochs (tests, quick experiments)."""
        train = dataclasses.replace(MATCHER_TRAIN, learning_rate=1e-3, max_epochs=50, eval_every=2)
        return cls(
            cameras=cameras,
            gat=GATConfig.quick(),
            train=train,
            samples_per_epoch=300,
            num_dev_samples=90,
        )


class Matcher(NamedTuple):
    """A trained skeleton matcher: what inference needs."""

    graphdef: Any
    rest: Any
    params: Any
    rig: Rig  # the inference cameras C_i, in the order of the features' camera slots
    config: MatcherConfig


def matcher_config_from_dict(d: dict) -> MatcherConfig:
    """Rebuilds a `MatcherConfig` from its saved JSON form (`dataclasses.asdict`)."""
    try:
        gat = GATConfig(
            **{**d["gat"], "widths": tuple(d["gat"]["widths"]), "heads": tuple(d["gat"]["heads"])}
        )
        fields = {f.name for f in dataclasses.fields(MatcherConfig)} - {"cameras", "gat", "train"}
        return MatcherConfig(
            cameras=None if d["cameras"] is None else tuple(d["cameras"]),
            gat=gat,
            train=TrainConfig(**d["train"]),
            **{k: d[k] for k in fields if k in d},
        )
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"not a matcher config ({e})", field="config") from None


def load_matcher(
    directory: str | Path,
    rig: Rig,
    config: MatcherConfig | None = None,
    num_keypoints: int | None = None,
    which: str = "best",
) -> Matcher:
    """Restores a matcher saved by `train_matcher`.

    ``config`` and ``num_keypoints`` default to those saved with the checkpoint (checkpoints of
    older runs lack the keypoint count and need it passed).
    """
    _trained_folder(directory, which, "train-matcher")
    if config is None or num_keypoints is None:
        checkpoints = Checkpoints(directory)
        try:
            saved = checkpoints.read_config(which)
        finally:
            checkpoints.close()
        config = config or matcher_config_from_dict(saved)
        if num_keypoints is None:
            if "num_keypoints" not in saved:
                raise InputError(
                    "checkpoint config lacks num_keypoints; pass it", file=directory, field="config"
                )
            num_keypoints = int(saved["num_keypoints"])
    rig_infer = rig.select(list(config.cameras or rig.names))
    model = MatchingGAT(rig_infer.num_cameras, num_keypoints, config.gat, rngs=nnx.Rngs(0))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    checkpoints = Checkpoints(directory)
    try:
        params = checkpoints.restore_params(jax.eval_shape(lambda: params), which)
    finally:
        checkpoints.close()
    return Matcher(graphdef, rest, params, rig_infer, config)


def _trained_folder(directory: str | Path, which: str, command: str) -> Path:
    """The folder of a training run, refused before anything opens it (orbax would create the
    checkpoint folders of a mistyped path, leaving empty ``best/`` and ``latest/`` behind)."""
    path = Path(directory)
    if not (path / which).is_dir():
        what = "no such folder" if not path.exists() else f"no {which}/ checkpoint folder in it"
        raise InputError(
            f"not a trained model ({what}; `mvpose-jax {command} --out` writes one)", file=path
        )
    return path
