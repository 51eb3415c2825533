"""The pipeline's stages by name: what a name in a config, a CLI choice or a manifest means.

One registry per stage a frame goes through (DESIGN.md §1.2-1.4):

* `PROPOSALS`: how skeletons are grouped into people (`matching`).
* `LIFTING`: the 3D method on grouped people (`lifting`), and whether it needs an estimator.
* `FILTERS`: per-track filtering over time (`smoothing`), and whether it runs in the stream
  (causal, chunk by chunk: ``one_euro_frames``) or over each track's chunks with their
  neighbours when the results are assembled (``smooth_chunk_files(..., filter=name)``).

An entry names its function as ``"module:function"``, imported only when the stage runs, so
reading the names (the CLI's choices and ``--help``) imports no jax. A new method is one
function and one `register` call; the CLI's choices, the manifest and the docs' tables read the
registries. Function contracts:

* proposals: ``fn(rig, detections, config: MatchingConfig, *, matcher) -> proposals.Proposals``
  with ``rig`` and ``detections`` on the proposal cameras.
* lifting: ``fn(rig, xy, score, config: LiftingConfig, *, estimator, min_views, layout) ->
  (Poses3D, confidence (F, G))`` on grouped people, xy (F, G, C, K, 2) pixels, score
  (F, G, C, K), C the proposal cameras (``rig``).
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable


@dataclasses.dataclass(frozen=True)
class Stage:
    """One method of one stage.

    Attributes:
      name: what configs, manifests and the CLI call it.
      target: the function, or ``"module:function"`` (imported when first used).
      summary: one line for ``--help`` and the docs.
      needs_estimator: lifting: runs a trained estimator (``--estimator``).
      needs_matcher: proposals: runs a trained matcher (``--matcher``).
      streaming: filters: runs causally in the stream (True) or over whole tracks while the
        results are assembled (False).
    """

    name: str
    target: str | Callable
    summary: str
    needs_estimator: bool = False
    needs_matcher: bool = False
    streaming: bool = False

    def function(self) -> Callable:
        if callable(self.target):
            return self.target
        module, _, attr = self.target.partition(":")
        return getattr(importlib.import_module(module), attr)


PROPOSALS: dict[str, Stage] = {}
LIFTING: dict[str, Stage] = {}
FILTERS: dict[str, Stage] = {}
_REGISTRIES = {"proposals": PROPOSALS, "lifting": LIFTING, "filters": FILTERS}


def register(kind: str, stage: Stage, *, replace: bool = False) -> Stage:
    """Adds ``stage`` to the registry ``kind`` ("proposals", "lifting" or "filters")."""
    registry = _REGISTRIES[kind]
    if stage.name in registry and not replace:
        raise ValueError(f"a {kind} stage named {stage.name!r} is registered already")
    registry[stage.name] = stage
    return stage


def unregister(kind: str, name: str) -> None:
    """Removes a stage (tests that register a toy one)."""
    _REGISTRIES[kind].pop(name, None)


def lookup(kind: str, name: str, *, what: str | None = None) -> Stage:
    """The stage ``name`` of ``kind``; an unknown name is a ValueError listing the known ones
    (called ``what``, default ``kind``)."""
    registry = _REGISTRIES[kind]
    if name not in registry:
        raise ValueError(f"{what or kind} must be one of {tuple(registry)}, not {name!r}")
    return registry[name]


def names(kind: str, **where: bool) -> tuple[str, ...]:
    """The registered names of ``kind`` in registration order, those whose attributes equal
    ``where`` (e.g. ``names("lifting", needs_estimator=False)``)."""
    return tuple(
        s.name
        for s in _REGISTRIES[kind].values()
        if all(getattr(s, k) == v for k, v in where.items())
    )


for _stage in (
    Stage(
        "combined",
        "mvpose_jax.matching:propose_combined_matcher",
        "the matcher's scores joined with epipolar geometry, each frame kept on the grouping "
        "that agrees better with the geometry",
        needs_matcher=True,
    ),
    Stage(
        "gat",
        "mvpose_jax.matching:propose_gat",
        "the learned matcher's scores alone at a threshold (the paper's)",
        needs_matcher=True,
    ),
    Stage(
        "gat-repaired",
        "mvpose_jax.matching:propose_gat_repaired",
        "as gat, then a person split by a duplicate or fragment skeleton made one again",
        needs_matcher=True,
    ),
    Stage(
        "epipolar",
        "mvpose_jax.matching:propose_epipolar",
        "symmetric epipolar distance of skeleton pairs, 2^(-d / half-score px); no model",
    ),
):
    register("proposals", _stage)

for _stage in (
    Stage(
        "mlp",
        "mvpose_jax.lifting:lift_mlp",
        "the estimator's output for every keypoint (the paper's)",
        needs_estimator=True,
    ),
    Stage(
        "blend",
        "mvpose_jax.lifting:lift_blend",
        "robust triangulation where 2+ inlier views see a keypoint, the estimator elsewhere",
        needs_estimator=True,
    ),
    Stage("dlt", "mvpose_jax.lifting:lift_dlt", "score-weighted DLT of keypoints in 2+ views"),
    Stage(
        "centroid",
        "mvpose_jax.lifting:lift_centroid",
        "the paper's baseline: centroid of pairwise triangulations",
    ),
    Stage(
        "robust",
        "mvpose_jax.lifting:lift_robust",
        "DLT that rejects a person's wrong views, then each keypoint's outlier views",
    ),
    Stage(
        "confident",
        "mvpose_jax.lifting:lift_confident",
        "views weighted by a learned p(inlier) (--confidence), unlikely ones dropped, then robust",
    ),
):
    register("lifting", _stage)

for _stage in (
    Stage(
        "none",
        "mvpose_jax.smoothing:smooth_chunk_files",
        "no filter (outliers are still dropped and short gaps filled)",
    ),
    Stage(
        "one-euro",
        "mvpose_jax.smoothing:one_euro_frames",
        "causal One-Euro filter per track, as a live stream runs it",
        streaming=True,
    ),
    Stage(
        "butterworth",
        "mvpose_jax.smoothing:smooth_chunk_files",
        "zero-phase Butterworth over each whole track, offline",
    ),
):
    register("filters", _stage)
del _stage


def markdown_table() -> str:
    """Every registered stage as a Markdown table (docs/architecture.md holds it; a test checks
    that it is current)."""
    needs = {"proposals": "needs_matcher", "lifting": "needs_estimator"}
    rows = ["| stage | name | needs | what it does |", "|---|---|---|---|"]
    for kind, registry in _REGISTRIES.items():
        for s in registry.values():
            need = ""
            if kind in needs and getattr(s, needs[kind]):
                need = "a matcher" if kind == "proposals" else "an estimator"
            elif kind == "filters":
                need = "tracks (in the stream)" if s.streaming else "tracks (while assembling)"
            rows.append(f"| {kind} | `{s.name}` | {need} | {s.summary} |")
    return "\n".join(rows) + "\n"
