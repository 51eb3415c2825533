"""Matching as a clustering of the detections (the paper's Tables 3 and 4): the learned matcher
against the epipolar matcher on a split's scenes, and its table."""

from __future__ import annotations

import time

import numpy as np

from experiments.data import Data
from experiments.tables import mean_sd, seeds_line
from mvpose_jax.inference import run_pipeline
from mvpose_jax.matching import epipolar_match_distances, gat_match_table
from mvpose_jax.metrics import matching_scores
from mvpose_jax.proposals import choose_geometric_cutoff, choose_proposal_threshold

MATCHING_SCORES = ("ari", "homogeneity", "completeness", "v_measure")


def matching_rows(data: Data, split: str, matcher, cameras, fit: dict) -> dict:
    """The learned matcher (at the paper's threshold 0.5 and at its dev-chosen threshold) against
    the epipolar matcher (its dev-chosen cutoff) on a split's scenes (detected variant): per-frame
    means (the paper's protocol) and pooled scores."""
    det, ident, _, _ = data.detections(split, cameras)
    rig_i = data.rig.select(list(cameras))
    F = len(det.count)
    out = {}
    methods = {
        "gat": dict(matcher=matcher, proposals="gat"),
        "gat_chosen": dict(matcher=matcher, proposals="gat", threshold=fit["threshold"]),
        "geometric": dict(half_score_px=fit["geometric_cutoff_px"]),
    }
    for method, kwargs in methods.items():
        run_pipeline(rig_i, det, **kwargs)  # warm-up: compile every shape the scenes need
        t0 = time.perf_counter()
        res = run_pipeline(rig_i, det, **kwargs)
        seconds = time.perf_counter() - t0
        s = matching_scores(ident, res.identity, np.asarray(det.count))
        out[method] = {
            k: round(float(s[k]), 5)
            for k in MATCHING_SCORES + tuple(f"pooled_{m}" for m in MATCHING_SCORES)
        }
        out[method]["t_pp_ms"] = round(1000 * res.seconds["proposals"] / F, 3)
        out[method]["pipeline_ms_per_frame"] = round(1000 * seconds / F, 3)
    out["gat_chosen"]["threshold"] = fit["threshold"]
    out["geometric"]["cutoff_px"] = fit["geometric_cutoff_px"]
    if len(cameras) > 1 and split == "validation":
        # Diagnostics for choosing (validation scenes only, never the test scenes): each matcher's
        # per-frame ARI across its setting.
        rows, scores = gat_match_table(matcher, det)
        ari = choose_proposal_threshold(
            rows, scores, ident, det.count, thresholds=(0.05, 0.1, 0.2, 0.3, 0.5)
        )[1]
        out["gat"]["ari_by_threshold"] = {str(th): round(a, 5) for th, a in ari.items()}
        rows, d = epipolar_match_distances(rig_i, det)
        ari = choose_geometric_cutoff(
            rows, d, ident, det.count, cutoffs_px=(10.0, 20.0, 30.0, 50.0)
        )[1]
        out["geometric"]["ari_by_cutoff_px"] = {str(c): round(a, 5) for c, a in ari.items()}
    out["frames"] = F
    return out


def matching_table(runs: list[dict], split: str, paper: dict, title: str) -> list[str]:
    """Every matcher's scores by number of views (`matching_rows` of each run), beside the
    paper's (``paper``: views -> ARI, H, C, Vm)."""
    lines = [
        f"### {title}",
        "",
        seeds_line(runs) + " ARI, H, C, Vm: means of per-frame scores (the paper's "
        "protocol); pooled: all detections as one clustering.",
        "",
        "| views | method | ARI | H | C | Vm | pooled ARI | pooled Vm | t_pp ms/frame | training s (steps) | "
        "paper ARI | paper H | paper C | paper Vm |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for views in runs[0]["matching"][split]:
        p = paper.get(int(views))
        fit = [r["training"][f"matcher-{views}"] for r in runs]
        thresholds = ", ".join(str(f["threshold"]) for f in fit)
        cutoffs = ", ".join(f"{f['geometric_cutoff_px']:g}" for f in fit)
        names = {
            "gat": "ours (GAT, threshold 0.5: the paper's)",
            "gat_chosen": f"ours (GAT, threshold chosen on dev: {thresholds})",
            "geometric": f"epipolar (cutoff chosen on dev: {cutoffs} px)",
        }
        for m, name in names.items():
            row = f"matching/{split}/{views}/{m}"
            ref = " | ".join(f"{x:.4f}" for x in p) if (p and m == "gat") else " |  |  | "
            steps = "/".join(str(f["train_steps"]) for f in fit[:1])
            train = (
                "0 (none)"
                if m == "geometric"
                else f"{np.mean([f['train_seconds'] for f in fit]):.0f} ({steps})"
            )
            cells = " | ".join(
                mean_sd(runs, f"{row}/{k}", 4)
                for k in (*MATCHING_SCORES, "pooled_ari", "pooled_v_measure")
            )
            lines.append(
                f"| {views} | {name} | {cells} | {mean_sd(runs, f'{row}/t_pp_ms')} | {train} | {ref} |"
            )
    return lines + [""]
