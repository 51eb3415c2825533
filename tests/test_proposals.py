"""proposals.py: the proposal step's settings chosen by one rule (hand-built frames with known
answers), and the chosen threshold written beside a matcher and read back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mvpose_jax.errors import InputError
from mvpose_jax.metrics import matching_scores
from mvpose_jax.proposals import (
    PROPOSAL_THRESHOLD_FILE,
    PROPOSAL_THRESHOLDS,
    choose_geometric_cutoff,
    choose_proposal_threshold,
    propose_people,
    read_proposal_threshold,
    write_proposal_threshold,
)


def test_choose_proposal_threshold_takes_the_band_that_separates_true_from_false_pairs():
    # Camera 0 sees people A and B, camera 1 sees A and a false detection X.
    identity = np.array([[[0, 1], [0, -1]]])
    count = np.array([[2, 2]])
    rows = np.array([[0, 0, 0, 1, 0],   # A-A, true
                     [0, 0, 1, 1, 1],   # B-X, false
                     [0, 0, 0, 1, 1],   # A-X, false
                     [0, 0, 1, 1, 0]])  # B-A, false  # fmt: skip
    scores = np.array([0.3, 0.1, 0.05, 0.04])
    best, ari = choose_proposal_threshold(rows, scores, identity, count)
    # A pair is taken when its score is above the threshold: from 0.1 (B-X refused) to below 0.3
    # (A-A taken) every threshold is perfect, and 0.2 is the nearest to 0.5.
    assert best == 0.2
    assert ari[0.1] == ari[0.15] == ari[0.2] == pytest.approx(1.0)
    assert ari[0.05] < 1.0 and ari[0.3] < 1.0 and ari[0.5] < 1.0


def test_choose_geometric_cutoff_is_a_pixel_distance_with_the_same_rule():
    # The frame of the threshold test, with distances instead of scores: A-A at 7 px, the false
    # pairs at 13, 18 and 22 px. Cutoffs from 8 to 12 px keep A-A alone (ARI 1); 12 is nearest 30.
    identity = np.array([[[0, 1], [0, -1]]])
    count = np.array([[2, 2]])
    rows = np.array([[0, 0, 0, 1, 0], [0, 0, 1, 1, 1], [0, 0, 0, 1, 1], [0, 0, 1, 1, 0]])
    d = np.array([7.0, 13.0, 18.0, 22.0])
    best, ari = choose_geometric_cutoff(rows, d, identity, count)
    assert best == 12.0
    assert ari[8.0] == ari[10.0] == ari[12.0] == pytest.approx(1.0)
    assert ari[6.0] < 1.0 and ari[15.0] < 1.0
    # The same as the GAT rule applied to the pipeline's scores 2^(-d / cutoff) at threshold 0.5.
    p = propose_people(rows, np.exp2(-d / best), count, num_skeletons=2, threshold=0.5)
    assert matching_scores(identity, p.identity, count)["ari"] == pytest.approx(1.0)


def test_matcher_threshold_is_chosen_written_and_read_back(tmp_path):
    from flax import nnx

    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.inference import choose_matcher_threshold
    from mvpose_jax.models import GATConfig, MatchingGAT
    from mvpose_jax.synthetic import generate_single_person_recordings
    from mvpose_jax.trained import Matcher, MatcherConfig

    rig = load_rig("panoptic5")
    recs = generate_single_person_recordings(rig, num_recordings=4, num_frames=3, seed=5)
    tiny = GATConfig(widths=(8, 1), heads=(2, 1))
    graphdef, params, rest = nnx.split(MatchingGAT(rig.num_cameras, recs[0].num_keypoints, tiny, rngs=nnx.Rngs(0)),
                                       nnx.Param, ...)  # fmt: skip
    matcher = Matcher(graphdef, rest, params, rig, MatcherConfig(gat=tiny, max_people=3))
    threshold, ari, composed = choose_matcher_threshold(matcher, recs, num_samples=24)
    write_proposal_threshold(tmp_path, threshold, ari, composed)
    assert threshold in PROPOSAL_THRESHOLDS and ari[threshold] == max(ari.values())
    record = json.loads((tmp_path / PROPOSAL_THRESHOLD_FILE).read_text())
    assert record["threshold"] == threshold and record["composed_frames"] == 24
    assert read_proposal_threshold(str(tmp_path), None) == threshold
    assert read_proposal_threshold(str(tmp_path), 0.7) == 0.7  # --threshold wins
    assert read_proposal_threshold(None, None) == 0.5  # geometric matcher: the paper's
    assert read_proposal_threshold(str(tmp_path / "elsewhere"), None) == 0.5  # a folder without the file
    (tmp_path / PROPOSAL_THRESHOLD_FILE).write_text("{")
    with pytest.raises(InputError, match=PROPOSAL_THRESHOLD_FILE):
        read_proposal_threshold(str(tmp_path), None)
