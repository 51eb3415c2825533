"""Trained models as inference uses them: their configs, the bundles, the loaders and the folder.

`Matcher` and `Estimator` hold what inference needs (the model's graph definition, its
parameters and cameras); `load_matcher` / `load_estimator` rebuild them from a model folder by
restoring the parameters alone, so nothing here imports an optimiser. The configs are frozen
dataclasses whose defaults are the paper's (DESIGN.md §1.2-1.3).

`ModelFolder` is the one owner of a model folder's layout: training (`train`), adaptation
(`adapt`) and the loaders read and write its checkpoints, config, chosen proposal settings and
reports through it, and nothing else opens a file inside one by name.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, rig_centre_and_radius, up_vector
from mvpose_jax.checkpoints import Checkpoints, TrainState
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.features import rig_agnostic_frame
from mvpose_jax.models import (
    GATConfig,
    MLPConfig,
    PoseMLP,
    estimator_model,
    matcher_model,
    rotation_to_z_up,
    unfilled,
)
from mvpose_jax.proposals import CombinedConfig


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
        mlp = dict(d["mlp"])
        mlp["widths"] = tuple(mlp["widths"])
        if "view_widths" in mlp:
            mlp["view_widths"] = tuple(mlp["view_widths"])
        mlp = MLPConfig(**mlp)
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


# The name `load_estimator` (and so ``infer --estimator``, ``adapt``, ``train-estimator --start``)
# takes for the rig-agnostic estimator shipped in the package.
PRETRAINED = "pretrained"


def pretrained_folder(kind: str) -> Path:
    """The shipped rig-agnostic ``kind`` ("estimator" or "matcher") model folder (package data,
    `mvpose_jax/pretrained/KIND`). Raises `InputError` when this installation lacks it."""
    folder = Path(__file__).resolve().parent / "pretrained" / kind
    if not (folder / "best").is_dir():
        experiment = {"estimator": "pretrain", "matcher": "pretrain_matcher"}[kind]
        raise InputError(
            f"this installation holds no pretrained {kind} (mvpose_jax/pretrained/{kind}); "
            f"reinstall the package, or train one: python -m experiments.{experiment} --ship",
            file=folder,
        )
    return folder


def resolve_model_folder(directory: str | Path, kind: str) -> Path:
    """``directory``, or the shipped ``kind`` ("estimator" or "matcher") folder for the name
    `PRETRAINED`."""
    return pretrained_folder(kind) if str(directory) == PRETRAINED else Path(directory)


def load_estimator(directory: str | Path, rig: Rig, which: str = "best") -> Estimator:
    """Restores an estimator saved by `train_estimator` (its config comes with the checkpoint).

    Args:
      directory: the ``checkpoint_dir`` of training (a `ModelFolder`), or `PRETRAINED` for the
        rig-agnostic estimator shipped in the package.
      rig: a rig holding the estimator's inference cameras (by name); a rig-agnostic estimator
        takes all of its cameras.
    """
    directory = resolve_model_folder(directory, "estimator")
    folder = ModelFolder(directory).require(which, "train-estimator")
    saved = folder.read_config(which)
    config = estimator_config_from_dict(saved)
    if "num_keypoints" not in saved:
        raise InputError("checkpoint config lacks num_keypoints", file=directory, field="config")
    if config.mlp.views == "pooled":
        graphdef, params, rest = unfilled(
            lambda: estimator_model(0, int(saved["num_keypoints"]), config.mlp, rngs=nnx.Rngs(0))
        )
        params = folder.restore_params(params, which)
        return rig_agnostic_estimator(graphdef, rest, params, config, rig)
    rig_infer = rig.select(list(config.infer_cameras or config.train_cameras or rig.names))
    K = int(saved["num_keypoints"])
    graphdef, params, rest = unfilled(
        lambda: PoseMLP(rig_infer.num_cameras, K, config.mlp, rngs=nnx.Rngs(0))
    )
    params = folder.restore_params(params, which)
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
    _warn_if_worse_than_triangulation(folder)
    return Estimator(graphdef, rest, params, rig_infer, config, normalisation)


def rig_agnostic_estimator(graphdef, rest, params, config: EstimatorConfig, rig: Rig) -> Estimator:
    """A rig-agnostic estimator (`models.ViewPooledMLP`) set up for ``rig``: every camera is an
    inference camera, the frame is the rig's (`features.rig_agnostic_frame`) and the model turns
    the rig's up (`cameras.up_vector`) to the +z it was trained with."""
    model = nnx.merge(graphdef, params, rest)
    model.rotation[...] = jnp.asarray(rotation_to_z_up(up_vector(rig)), jnp.float32)
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    return Estimator(graphdef, rest, params, rig, config, rig_agnostic_frame(rig))


class ModelQualityWarning(MvposeWarning):
    """A trained model does worse on its own dev data than the geometry it should improve on."""


def _warn_if_worse_than_triangulation(folder: ModelFolder) -> None:
    q = folder.read_dev_quality()
    if q is None:
        return  # trained before the comparison was written
    try:
        est, tri = float(q["estimator_px"]), float(q["triangulation_px"])
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(f"unreadable ({e})", file=folder.path / DEV_QUALITY_FILE) from None
    if est > tri:
        warnings.warn(
            f"{folder.path}: on its dev recordings this estimator reprojects {est:.2f} px per "
            f"keypoint where triangulation reprojects {tri:.2f} px (same keypoints): it is likely "
            "trained too briefly or on other data; triangulation (no --estimator) may serve better",
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

    def composition(self) -> dict:
        """How training frames are composed (`graphs.compose_samples`' keyword arguments)."""
        return dict(
            max_people=self.max_people,
            subset_probability=self.subset_probability,
            min_views=self.min_views,
            keypoint_dropout=self.keypoint_dropout,
        )

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
        gat = dict(d["gat"])
        for k in ("widths", "heads", "encoder_widths"):
            if k in gat:
                gat[k] = tuple(gat[k])
        gat = GATConfig(**gat)
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
    """Restores a matcher saved by `train_matcher` (from a `ModelFolder`), or `PRETRAINED`: the
    rig-agnostic matcher shipped in the package, set up for ``rig`` (all its cameras).

    ``config`` and ``num_keypoints`` default to those saved with the checkpoint (checkpoints of
    older runs lack the keypoint count and need it passed).
    """
    directory = resolve_model_folder(directory, "matcher")
    folder = ModelFolder(directory).require(which, "train-matcher")
    if config is None or num_keypoints is None:
        saved = folder.read_config(which)
        config = config or matcher_config_from_dict(saved)
        if num_keypoints is None:
            if "num_keypoints" not in saved:
                raise InputError(
                    "checkpoint config lacks num_keypoints; pass it", file=directory, field="config"
                )
            num_keypoints = int(saved["num_keypoints"])
    rig_infer = rig.select(list(config.cameras or rig.names))
    graphdef, params, rest = unfilled(
        lambda: matcher_model(rig_infer.num_cameras, num_keypoints, config.gat, rngs=nnx.Rngs(0))
    )
    params = folder.restore_params(params, which)
    if config.gat.views == "pooled":
        return rig_agnostic_matcher(graphdef, rest, params, config, rig_infer)
    return Matcher(graphdef, rest, params, rig_infer, config)


def rig_agnostic_matcher(graphdef, rest, params, config: MatcherConfig, rig: Rig) -> Matcher:
    """A rig-agnostic matcher (`models.RigAgnosticGAT`) set up for ``rig``: its features come in
    the rig's normalised frame (`features.keypoint_features`), so the model's `FrameScale` is
    the rig's radius (metres again), and its rotation turns the rig's up
    (`cameras.up_vector`) to the +z it was trained with."""
    model = nnx.merge(graphdef, params, rest)
    model.rotation[...] = jnp.asarray(rotation_to_z_up(up_vector(rig)), jnp.float32)
    model.scale[...] = jnp.asarray(rig_centre_and_radius(rig)[1], jnp.float32)
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    return Matcher(graphdef, rest, params, rig, config)


# =========================================================================== the model folder

# The files beside a model folder's checkpoints. Their names are those folders have always been
# written with, so that every folder written before `ModelFolder` loads as it did.
DEV_QUALITY_FILE = "dev_reprojection.json"
PROPOSAL_THRESHOLD_FILE = "proposal_threshold.json"
ADAPT_REPORT_FILE = "adapt_report.json"
PIPELINE_FILE = "pipeline.json"
PRETRAIN_REPORT_FILE = "pretrain_report.json"


class ModelFolder:
    """A trained model's folder: the one place that knows its layout.

    Layout (``path/``):
      ``best/``, ``latest/``: orbax checkpoints (`checkpoints.Checkpoints`), each with the run's
        config as JSON (`kind`: "estimator" with an ``mlp`` entry, "matcher" with a ``gat`` one;
        an ``adapted`` entry marks an adapted model, whose folder has ``best/`` alone);
      ``dev_reprojection.json``: an estimator against triangulation on its dev people
        (`write_dev_quality`; `load_estimator` warns from it);
      ``proposal_threshold.json``: a matcher's chosen proposal settings (`write_proposal_settings`);
      ``adapt_report.json``: what an adaptation did (`write_adapt_report`);
      ``pipeline.json``: the pipeline the model was trained and its settings chosen for
        (`inference.PipelineConfig.to_dict`; `write_pipeline`), what ``infer`` with this model
        and no other option runs.

    Opening one reads nothing; `require` refuses a path that is no model folder before orbax
    could create checkpoint folders in it.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"ModelFolder({str(self.path)!r})"

    # ---------------------------------------------------------------- checkpoints and config

    def checkpoints(self, max_to_keep: int = 3) -> Checkpoints:
        """The folder's `Checkpoints` (created when missing), for training to write and resume;
        the caller closes it."""
        return Checkpoints(self.path, max_to_keep=max_to_keep)

    def require(self, which: str = "best", command: str = "train-estimator") -> ModelFolder:
        """Itself, when it holds a ``which`` checkpoint folder; else `InputError` naming the
        ``mvpose-jax`` command that writes one (orbax would otherwise create the checkpoint
        folders of a mistyped path, leaving empty ``best/`` and ``latest/`` behind)."""
        if not (self.path / which).is_dir():
            what = (
                "no such folder"
                if not self.path.exists()
                else f"no {which}/ checkpoint folder in it"
            )
            raise InputError(
                f"not a trained model ({what}; `mvpose-jax {command} --out` writes one)",
                file=self.path,
            )
        return self

    def read_config(self, which: str = "best") -> dict:
        """The run config saved with the ``which`` checkpoint."""
        checkpoints = Checkpoints(self.path)
        try:
            return checkpoints.read_config(which)
        finally:
            checkpoints.close()

    def restore_params(self, abstract_params, which: str = "best"):
        """The trained parameters alone (`Checkpoints.restore_params`; no optimiser needed)."""
        checkpoints = Checkpoints(self.path)
        try:
            return checkpoints.restore_params(abstract_params, which)
        finally:
            checkpoints.close()

    def kind(self, which: str = "best") -> str:
        """ "estimator" or "matcher", from the saved config; `InputError` when it is neither."""
        saved = self.read_config(which)
        if "mlp" in saved:
            return "estimator"
        if "gat" in saved:
            return "matcher"
        raise InputError("holds neither an estimator nor a matcher", file=self.path, field="config")

    def is_adapted(self, which: str = "best") -> bool:
        """Whether the model was adapted to a recording (`adapt`) rather than trained."""
        return "adapted" in self.read_config(which)

    def save_params(self, params, step: int, config: dict, val_loss: float) -> None:
        """Saves parameters alone (no optimiser state) as the ``best`` checkpoint of ``step``,
        with ``config``: the form of an adapted model, which `load_estimator` / `load_matcher`
        read as they read a trained one."""
        state = TrainState(jnp.asarray(step, jnp.int32), jax.device_put(params), ())
        checkpoints = Checkpoints(self.path)
        try:
            checkpoints.save_best(state, config, val_loss)
        finally:
            checkpoints.close()

    @classmethod
    @contextlib.contextmanager
    def create(cls, directory: str | os.PathLike) -> Iterator[ModelFolder]:
        """A new model folder, assembled under a temporary name beside ``directory`` and renamed
        into place when the ``with`` block ends without error: an interrupted writer leaves no
        half-written model.

        Raises:
          InputError when ``directory`` holds something already.
        """
        out = Path(directory)
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise InputError("exists and is not an empty folder; choose a new one", file=out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        try:
            yield cls(tmp)
            if out.exists():
                out.rmdir()  # empty (checked above)
            os.replace(tmp, out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    # ---------------------------------------------------------------- reports

    def write_dev_quality(self, quality: dict) -> Path:
        """Writes the estimator-against-triangulation comparison (`train.compare_with_triangulation`)."""
        return self._write_json(DEV_QUALITY_FILE, quality)

    def read_dev_quality(self) -> dict | None:
        """The comparison `write_dev_quality` wrote (None: a folder without one)."""
        return self._read_json(DEV_QUALITY_FILE)

    @property
    def adapt_report_path(self) -> Path:
        """Where `write_adapt_report` writes (for messages)."""
        return self.path / ADAPT_REPORT_FILE

    def write_pretrain_report(self, report: dict) -> Path:
        """Writes how a rig-agnostic model was pretrained and how it did on rigs it never saw
        (`experiments.pretrain`): its data, seed, steps and validation table."""
        return self._write_json(PRETRAIN_REPORT_FILE, report)

    def read_pretrain_report(self) -> dict | None:
        return self._read_json(PRETRAIN_REPORT_FILE)

    def write_adapt_report(self, report: dict) -> Path:
        """Writes what an adaptation did (`adapt.AdaptReport.to_json`)."""
        return self._write_json(ADAPT_REPORT_FILE, report)

    def read_adapt_report(self) -> dict | None:
        """The report `write_adapt_report` wrote (None: not an adapted folder)."""
        return self._read_json(ADAPT_REPORT_FILE)

    # ---------------------------------------------------------------- chosen proposal settings

    def write_proposal_settings(
        self,
        threshold: float,
        ari: dict[float, float],
        composed_frames: int,
        *,
        combined: CombinedConfig | None = None,
        combined_ari: dict[float, float] | None = None,
    ) -> Path:
        """Writes a matcher's chosen proposal threshold with the ARI of each threshold tried on
        ``composed_frames`` frames (and, when given, the combined matcher's settings and ARIs);
        chosen by `proposals.choose_proposal_threshold` / `choose_combined_threshold`."""
        record = {
            "threshold": threshold,
            "ari_by_threshold": {str(k): round(v, 6) for k, v in ari.items()},
            "composed_frames": int(composed_frames),
            "how": "the best per-frame adjusted Rand index of the proposals on multi-person frames "
            "composed from the dev recordings (inference.choose_matcher_threshold)",
        }
        if combined is not None:
            record["combined"] = dataclasses.asdict(combined)
            if combined_ari is not None:
                record["combined"]["ari_by_threshold"] = {
                    str(k): round(v, 6) for k, v in combined_ari.items()
                }
        return self._write_json(PROPOSAL_THRESHOLD_FILE, record)

    def set_proposal_threshold(
        self, threshold: float, ari: dict[float, float], frames: int, how: str
    ) -> Path:
        """Writes the GAT's proposal threshold (with the ARI of each threshold tried on
        ``frames`` frames, and ``how`` it was chosen), keeping the combined matcher's settings
        already written here."""
        record = self._read_json(PROPOSAL_THRESHOLD_FILE) or {}
        record.pop("composed_frames", None)
        record.update(
            threshold=float(threshold),
            ari_by_threshold={str(k): round(v, 6) for k, v in ari.items()},
            frames=int(frames),
            how=how,
        )
        return self._write_json(PROPOSAL_THRESHOLD_FILE, record)

    def read_proposal_threshold(self, given: float | None = None) -> float:
        """``given``, else the chosen threshold, else the paper's 0.5."""
        if given is not None:
            return given
        path = self.path / PROPOSAL_THRESHOLD_FILE
        if not path.exists():
            return 0.5
        try:
            return float(json.loads(path.read_text())["threshold"])
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(
                f"unreadable proposal threshold ({e})", file=path, field="threshold"
            ) from e

    def read_combined_config(self) -> CombinedConfig:
        """The combined matcher's chosen settings, else `CombinedConfig`'s defaults."""
        path = self.path / PROPOSAL_THRESHOLD_FILE
        if not path.exists():
            return CombinedConfig()
        try:
            record = json.loads(path.read_text()).get("combined")
            if record is None:
                return CombinedConfig()
            # Each setting as its field's type: numbers as floats; a switch only as a JSON
            # boolean (bool("false") would be True).
            types = {f.name: type(f.default) for f in dataclasses.fields(CombinedConfig)}
            for k, v in record.items():
                if types.get(k) is bool and not isinstance(v, bool):
                    raise TypeError(f"{k} must be true or false, not {v!r}")
            return CombinedConfig(**{k: types[k](v) for k, v in record.items() if k in types})
        except (ValueError, AttributeError, TypeError) as e:
            raise InputError(
                f"unreadable combined matcher settings ({e})", file=path, field="combined"
            ) from e

    def copy_proposal_settings(self, source: ModelFolder) -> bool:
        """Copies ``source``'s chosen proposal settings here as they are; False: it has none."""
        path = source.path / PROPOSAL_THRESHOLD_FILE
        if not path.exists():
            return False
        shutil.copyfile(path, self.path / PROPOSAL_THRESHOLD_FILE)
        return True

    # ---------------------------------------------------------------- the pipeline it serves

    def write_pipeline(self, record: dict) -> Path:
        """Writes the pipeline config (`inference.PipelineConfig.to_dict`) the model serves."""
        return self._write_json(PIPELINE_FILE, record)

    def read_pipeline(self) -> dict | None:
        """The record `write_pipeline` wrote (None: a folder from before it was written)."""
        return self._read_json(PIPELINE_FILE)

    # ---------------------------------------------------------------- plumbing

    def _write_json(self, name: str, record: dict) -> Path:
        path = self.path / name
        atomic_write_text(path, json.dumps(record, indent=1) + "\n")
        return path

    def _read_json(self, name: str) -> dict | None:
        path = self.path / name
        if not path.is_file():
            return None
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise InputError(f"unreadable ({e})", file=path) from None


def write_proposal_threshold(
    folder: str | os.PathLike,
    threshold: float,
    ari: dict[float, float],
    composed_frames: int,
    *,
    combined: CombinedConfig | None = None,
    combined_ari: dict[float, float] | None = None,
) -> Path:
    """`ModelFolder.write_proposal_settings` of the matcher folder ``folder``."""
    return ModelFolder(folder).write_proposal_settings(
        threshold, ari, composed_frames, combined=combined, combined_ari=combined_ari
    )


def read_proposal_threshold(folder: str | os.PathLike | None, given: float | None = None) -> float:
    """The proposal threshold: ``given``, else the matcher folder's chosen one, else the paper's 0.5."""
    if given is not None or not folder:
        return 0.5 if given is None else given
    return ModelFolder(resolve_model_folder(folder, "matcher")).read_proposal_threshold(given)


def read_combined_config(folder: str | os.PathLike | None) -> CombinedConfig:
    """The combined matcher's settings recorded in a matcher folder (`write_proposal_threshold`),
    else `CombinedConfig`'s defaults."""
    return (
        ModelFolder(resolve_model_folder(folder, "matcher")).read_combined_config()
        if folder
        else CombinedConfig()
    )
