"""A matcher's proposal settings, chosen on multi-person frames composed from held-out
single-person recordings: a labelled set made without a single label (DESIGN.md §1.2)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from mvpose_jax.cameras import Rig
from mvpose_jax.graphs import compose_samples, make_pool
from mvpose_jax.matching import FRAMES_PER_CALL, combined_match_tables, gat_match_table
from mvpose_jax.proposals import (
    CombinedConfig,
    choose_combined_threshold,
    choose_geometric_cutoff,
    choose_proposal_threshold,
)
from mvpose_jax.skeletons import Detections
from mvpose_jax.trained import Matcher


def composed_frames(
    rig: Rig,
    recordings: Sequence,
    *,
    num_samples: int = 1024,
    seed: int = 0,
    max_people: int = 8,
    subset_probability: float = 0.5,
    min_views: int = 2,
    keypoint_dropout: float = 0.0,
) -> tuple[Detections, np.ndarray]:
    """Multi-person frames composed from single-person recordings, with their true identities.

    Composed as the matcher's training composes them (`graphs.compose_samples`), so held-out
    single-person recordings give a labelled multi-person set without a single label: the set
    every proposal setting is chosen on (the GAT's threshold, the epipolar matcher's cutoff).

    Args:
      rig: the cameras to compose in (every recording must hold them).
      recordings: single-person recordings.
      num_samples: composed frames; the other settings as `graphs.compose_samples`.
    Returns:
      (`Detections` (S, C, Q, ...) with each view's skeletons first, identity (S, C, Q): the
      frame's person of each skeleton, -1 for false detections and padding).
    """
    pool = make_pool(rig, recordings)
    _, valid, ident, xy, score = compose_samples(
        pool,
        np.random.default_rng([seed, 1 << 29]),
        num_samples,
        max_people=max_people,
        subset_probability=subset_probability,
        min_views=min_views,
        keypoint_dropout=keypoint_dropout,
        with_detections=True,
    )
    # Each view's skeletons first, padding after: the layout `count` describes.
    order = np.argsort(~valid, axis=-1, kind="stable")
    valid = np.take_along_axis(valid, order, axis=-1)
    xy = np.take_along_axis(xy, order[..., None, None], axis=2)
    score = np.take_along_axis(score, order[..., None], axis=2)
    ident = np.where(valid, np.take_along_axis(ident, order, axis=-1), -1)
    return Detections(
        xy.astype(np.float32), score.astype(np.float32), valid.sum(-1).astype(np.int32)
    ), ident


def composed_match_table(
    matcher: Matcher,
    recordings: Sequence,
    *,
    num_samples: int = 1024,
    seed: int = 0,
    frames_per_call: int = FRAMES_PER_CALL,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The matcher's scores on frames composed from single-person recordings (`composed_frames`,
    with the matcher's own composition settings), for `metrics.choose_proposal_threshold`.

    Returns:
      rows (M, 5) and scores (M,) as `gat_match_table`, identity (S, C, Q) and count (S, C).
    """
    det, ident = _composed_for(matcher, recordings, num_samples=num_samples, seed=seed)
    rows, scores = gat_match_table(matcher, det, frames_per_call=frames_per_call)
    return rows, scores, ident, np.asarray(det.count)


def _composed_for(
    matcher: Matcher, recordings: Sequence, *, num_samples: int, seed: int
) -> tuple[Detections, np.ndarray]:
    """`composed_frames` on the matcher's cameras with the matcher's own composition settings."""
    return composed_frames(
        matcher.rig,
        recordings,
        num_samples=num_samples,
        seed=seed,
        **matcher.config.composition(),
    )


def choose_matcher_threshold(
    matcher: Matcher, dev_recordings: Sequence, *, num_samples: int = 1024, seed: int = 0
) -> tuple[float, dict[float, float], int]:
    """A matcher's proposal threshold, chosen on frames composed from held-out single-person
    recordings (`composed_match_table`, `proposals.choose_proposal_threshold`).

    Returns:
      (the threshold, {threshold: per-frame ARI}, number of composed frames).
    """
    rows, scores, identity, count = composed_match_table(
        matcher, dev_recordings, num_samples=num_samples, seed=seed
    )
    threshold, ari = choose_proposal_threshold(rows, scores, identity, count)
    return threshold, ari, len(count)


class MatcherSettings(NamedTuple):
    """A matcher's proposal settings chosen on frames composed from dev recordings
    (`choose_matcher_settings`), with the per-frame ARI of every candidate."""

    threshold: float  # the GAT's proposal threshold
    ari_by_threshold: dict[float, float]
    geometric_cutoff_px: float  # the epipolar matcher's cutoff on the matcher's cameras
    ari_by_cutoff_px: dict[float, float]
    combined: CombinedConfig  # the combined matcher (its threshold and cutoff chosen here)
    ari_by_combined_threshold: dict[float, float]
    composed_frames: int


def choose_matcher_settings(
    matcher: Matcher,
    dev_recordings: Sequence,
    *,
    num_samples: int = 1024,
    seed: int = 0,
    combined: CombinedConfig = CombinedConfig(),
) -> MatcherSettings:
    """Every proposal setting of a matcher by one rule (the best per-frame ARI) on one set of
    frames composed from held-out single-person recordings: the GAT's threshold, the epipolar
    cutoff on the matcher's cameras, then the combined matcher's threshold at that cutoff
    (``combined``'s weight and half-score distance kept).
    """
    det, identity = _composed_for(matcher, dev_recordings, num_samples=num_samples, seed=seed)
    count = np.asarray(det.count)
    rows, scores, mean, median, shared = combined_match_tables(matcher, det)
    threshold, ari = choose_proposal_threshold(rows, scores, identity, count)
    cutoff, ari_cut = choose_geometric_cutoff(rows, mean, identity, count)
    config = dataclasses.replace(combined, epipolar_cutoff_px=cutoff)
    th, ari_comb = choose_combined_threshold(
        rows, scores, mean, median, identity, count, config=config, shared_keypoints=shared
    )
    return MatcherSettings(
        threshold,
        ari,
        cutoff,
        ari_cut,
        dataclasses.replace(config, threshold=th),
        ari_comb,
        len(count),
    )
