"""Training the experiments' models, and keeping them as model folders.

`fit_matcher` and `fit_estimator` train one model on a training seed's data as every experiment
does (and choose the matcher's proposal settings on frames composed from the dev recordings).
`cached_models` keeps the seed-0 5-view matcher and estimator of ``panoptic5`` (by default at
the "quick-long" scale, which the side studies' tables were measured with) in a folder that the
side studies share: the model folders ``mvpose-jax train-matcher`` and
``train-estimator`` write (``matcher/``, ``estimator/``; ``mvpose-jax infer --matcher
DIR/matcher --estimator DIR/estimator`` runs them), and ``fit.json``, the matcher's fit record
(written last: a folder without it is an unfinished cache).
"""

from __future__ import annotations

import dataclasses
import gc
import json
import time
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from experiments.config import SCALES, Scale
from experiments.data import Data, make_data
from mvpose_jax.cameras import Rig
from mvpose_jax.data.files import atomic_write_text, to_jsonable
from mvpose_jax.errors import InputError
from mvpose_jax.estimator_training import train_estimator
from mvpose_jax.features import single_person_samples
from mvpose_jax.matcher_settings import composed_frames
from mvpose_jax.matcher_training import train_matcher
from mvpose_jax.matching import (
    epipolar_distances_of_rows,
    epipolar_match_distances,
    gat_match_table,
)
from mvpose_jax.proposals import (
    CombinedConfig,
    choose_combined_threshold,
    choose_geometric_cutoff,
    choose_proposal_threshold,
)
from mvpose_jax.synthetic import DetectorConfig
from mvpose_jax.trained import (
    Estimator,
    Matcher,
    load_estimator,
    load_matcher,
    write_proposal_threshold,
)


def free_compiled_programs() -> None:
    """Drops every compiled program of the process (the next call of a function compiles again).

    Each XLA:CPU executable holds its own memory maps, and one experiment process compiles
    thousands: every model's training step at each padded shape, then the pipelines' programs
    at each chunk shape. Kept all along, they brought one seed of paper-panoptic close to Linux's
    default ``vm.max_map_count`` (65,530); with slightly larger programs it passed it, and the
    next compile died ("LLVM ERROR: Unable to allocate section memory"). Called after each
    training, whose programs nothing else runs, and at the start of each training seed (the
    previous seed's evaluation programs)."""
    gc.collect()  # programs held only by dead closures (a finished model's train step)
    jax.clear_caches()


def fit_matcher(
    data: Data, sc: Scale, cameras, seed: int, progress: bool, folder: Path | None = None
) -> tuple[Matcher, dict]:
    """Trains the matcher of ``cameras`` on a training seed's data and chooses its settings.

    Args:
      data: the training seed's `Data` (its training and dev recordings).
      sc: the scale (the matcher's configuration and steps by number of views).
      cameras: the matcher's cameras (names of ``data.rig``).
      seed: the training seed (initialisation, batches and the composed dev frames).
      folder: where to write the matcher as a model folder (as ``mvpose-jax train-matcher --out``
        writes it: checkpoints and the chosen proposal settings; `trained.load_matcher` reads
        it); None: kept in memory only.
    Returns:
      (the matcher, its fit record: training time, steps and history, and the settings chosen on
      frames composed from the dev recordings).
    """
    train = dataclasses.replace(
        sc.matcher.train, max_epochs=10**6, max_steps=sc.matcher_steps[len(cameras)], seed=seed
    )
    config = dataclasses.replace(sc.matcher, cameras=tuple(cameras), train=train)
    t0 = time.perf_counter()
    matcher, fit = train_matcher(
        data.rig, data.train, data.dev, config, checkpoint_dir=folder, progress=progress
    )
    seconds = time.perf_counter() - t0
    free_compiled_programs()
    return matcher, {
        "train_seconds": round(seconds, 1),
        "train_steps": fit.steps,
        "best_val_loss": fit.best_val_loss,
        "history": fit.history,
        **choose_settings_on_dev(matcher, data, sc.threshold_frames, seed, folder),
    }


def choose_settings_on_dev(
    matcher: Matcher, data: Data, num_frames: int, seed: int, folder: Path | None = None
) -> dict:
    """A trained matcher's proposal settings, chosen on ``num_frames`` multi-person frames
    composed from the dev recordings of ``data`` (and written into its model ``folder`` when
    given): the GAT's threshold, the epipolar matcher's cutoff and the combined matcher's
    threshold at that cutoff; returns them with the ARI of every candidate."""
    # Both matchers' settings are chosen by one rule on multi-person frames composed from the dev
    # recordings (no scene, no label beyond the composition's own): the GAT's proposal threshold
    # (the paper's is 0.5) and the epipolar matcher's distance cutoff.
    composed, identity = composed_frames(
        matcher.rig, data.dev, num_samples=num_frames, seed=seed, **matcher.config.composition()
    )
    gat_rows, gat_scores = gat_match_table(matcher, composed)
    threshold, ari = choose_proposal_threshold(gat_rows, gat_scores, identity, composed.count)
    rows, distances = epipolar_match_distances(matcher.rig, composed)
    cutoff, ari_geo = choose_geometric_cutoff(rows, distances, identity, composed.count)
    # The combined matcher's threshold by the same rule, at that cutoff (its weight and
    # half-score distance are the library's defaults, chosen on the domain-shift validation scenes).
    combined = CombinedConfig(epipolar_cutoff_px=cutoff)
    mean, median, shared = epipolar_distances_of_rows(matcher.rig, composed, gat_rows)
    combined_threshold, ari_comb = choose_combined_threshold(
        gat_rows,
        gat_scores,
        mean,
        median,
        identity,
        composed.count,
        config=combined,
        shared_keypoints=shared,
    )
    if folder is not None:  # what `infer --matcher` reads beside the checkpoints
        write_proposal_threshold(
            folder,
            threshold,
            ari,
            len(np.asarray(composed.count)),
            combined=dataclasses.replace(combined, threshold=combined_threshold),
            combined_ari=ari_comb,
        )
    return {
        "threshold": threshold,
        "dev_ari_by_threshold": {str(k): round(v, 5) for k, v in ari.items()},
        "geometric_cutoff_px": cutoff,
        "dev_ari_by_cutoff_px": {str(k): round(v, 5) for k, v in ari_geo.items()},
        "combined": dataclasses.asdict(dataclasses.replace(combined, threshold=combined_threshold)),
        "dev_ari_by_combined_threshold": {str(k): round(v, 5) for k, v in ari_comb.items()},
    }


def fit_estimator(
    data: Data,
    sc: Scale,
    train_cams,
    infer_cams,
    seed: int,
    progress: bool,
    folder: Path | None = None,
) -> tuple[Estimator, dict]:
    """Trains the 3D estimator on a training seed's single-person recordings (no 3D label).

    Args:
      train_cams, infer_cams: its training and inference cameras (names of ``data.rig``).
      seed: the training seed.
      folder: where to write the estimator as a model folder (as ``mvpose-jax train-estimator
        --out`` writes it; `trained.load_estimator` reads it); None: kept in memory only.
    Returns:
      (the estimator, its fit record: training time, steps, people and history).
    """
    xy, score = single_person_samples(data.train, train_cams)
    dev_xy, dev_score = single_person_samples(data.dev, train_cams)
    config = dataclasses.replace(
        sc.estimator,
        train_cameras=tuple(train_cams),
        infer_cameras=tuple(infer_cams),
        train=dataclasses.replace(sc.estimator.train, seed=seed),
    )
    t0 = time.perf_counter()
    est, fit = train_estimator(
        data.rig.select(list(train_cams)),
        xy,
        score,
        dev_xy,
        dev_score,
        config,
        checkpoint_dir=folder,
        progress=progress,
    )
    seconds = round(time.perf_counter() - t0, 1)
    free_compiled_programs()
    return est, {
        "train_seconds": seconds,
        "train_steps": fit.steps,
        "train_people": int(len(xy)),
        "best_val_loss": fit.best_val_loss,
        "history": fit.history,
    }


def combined_config(fit: dict) -> CombinedConfig:
    """The combined matcher's settings chosen with a matcher (`fit_matcher`'s record); for a
    matcher fitted before they were recorded, the defaults at its epipolar cutoff."""
    if "combined" in fit:
        return CombinedConfig(**fit["combined"])
    return CombinedConfig(epipolar_cutoff_px=fit["geometric_cutoff_px"])


class Models(NamedTuple):
    """A trained 5-view matcher and estimator with the matcher's fit record (`fit_matcher`)."""

    matcher: Matcher
    estimator: Estimator
    fit: dict
    seed: int  # the training seed


FIT_FILE = "fit.json"


def cached_models(
    rig: Rig,
    folder: Path | None,
    *,
    seed: int = 0,
    scale: str | Scale = "quick-long",
    progress: bool = True,
    floor_height: float | None = None,
    up: tuple[float, float, float] | None = None,
    data: Data | None = None,
    detector: DetectorConfig | None = None,
) -> Models:
    """The matcher and estimator of ``rig`` (every camera) trained as the experiments train them
    (``scale``, a name of `SCALES` or a `Scale`; training seed ``seed``), loaded from ``folder``
    when it holds them, else trained and, with a ``folder``, written there (see the module's
    docstring for its layout). ``floor_height``, ``up``: the training recordings' (`make_data`);
    ``data``: train on these recordings instead of generating them (real single-person ones);
    ``detector``: the generated recordings' simulated detector (None: the default one).

    Raises:
      InputError: ``folder`` is a file (such as the pickles these caches were before), or a
        folder that holds something else or an unfinished cache.
    """
    if folder is not None and folder.exists() and not _empty_folder(folder):
        return load_models(rig, folder)
    sc = SCALES[scale] if isinstance(scale, str) else scale
    if data is None:
        data = make_data(
            rig, {}, sc, seed, progress, floor_height=floor_height, up=up, detector=detector
        )
    matcher, fit = fit_matcher(
        data, sc, rig.names, seed, progress, None if folder is None else folder / "matcher"
    )
    estimator, estimator_fit = fit_estimator(
        data,
        sc,
        rig.names,
        rig.names,
        seed,
        progress,
        None if folder is None else folder / "estimator",
    )
    if folder is not None:
        record = {
            "seed": seed,
            "scale": scale if isinstance(scale, str) else "custom",
            "floor_height": floor_height,
            "up": up,
            "detector": None if detector is None else dataclasses.asdict(detector),
            "fit": fit,
            "estimator_fit": estimator_fit,
        }
        atomic_write_text(folder / FIT_FILE, json.dumps(to_jsonable(record), indent=1) + "\n")
    return Models(matcher, estimator, fit, seed)


def load_models(rig: Rig, folder: Path) -> Models:
    """The models `cached_models` wrote into ``folder``.

    Raises:
      InputError: ``folder`` is not such a folder (a file, such as an old pickle; a folder
        without ``fit.json``, ``matcher/`` or ``estimator/``).
    """
    if not folder.is_dir():
        raise InputError(
            "not a models folder: the models are kept as model folders now (matcher/, "
            "estimator/, fit.json), not pickles; give a folder (made if missing)",
            file=folder,
        )
    if not (folder / FIT_FILE).is_file():
        raise InputError(
            f"no {FIT_FILE} in it: not a models folder, or an unfinished one (delete it and "
            "run again to train the models)",
            file=folder,
        )
    try:
        record = json.loads((folder / FIT_FILE).read_text())
        fit, seed = record["fit"], int(record["seed"])
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(f"unreadable models record ({e})", file=folder / FIT_FILE) from None
    matcher = load_matcher(folder / "matcher", rig)
    estimator = load_estimator(folder / "estimator", rig)
    return Models(matcher, estimator, fit, seed)


def _empty_folder(path: Path) -> bool:
    return path.is_dir() and not any(path.iterdir())
