"""The Butterworth cut-off on the validation tracking scenes, for the learned and the geometric
pipeline: ``python -m experiments.filter_cutoffs [--splits validation] [--cutoffs 1.5,2,3]``.

Trains the seed-0 quick-scale 5-view matcher and estimator as ``experiments.run`` does (or loads
them from ``--models``, a models folder: `experiments.fitting.cached_models`, shared with
`experiments.combined_matching`; old pickles are refused), runs both pipelines with tracking on each
tracking scene (``[0, 4, n]`` validation, ``[0, 6, n]`` test; 1-8 people, 300 frames), and prints
for each cut-off the jitter (times the ground truth's), MPJPE and PCP, with the unfiltered row
and the identity metrics. docs/tracking.md's table of cut-offs comes from the validation split.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments.config import SCALES
from experiments.data import make_tracking_scenes, pooled_tracks, tracking_truth
from experiments.fitting import cached_models
from mvpose_jax.cameras import up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.errors import InputError
from mvpose_jax.inference import run_pipeline
from mvpose_jax.metrics import identity_metrics, jitter, pose_metrics
from mvpose_jax.smoothing import smooth_poses
from mvpose_jax.tracking import TrackingConfig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.filter_cutoffs")
    ap.add_argument("--splits", default="validation", help="validation and/or test (comma list)")
    ap.add_argument("--cutoffs", default="1.5,1.75,2,3", help="Butterworth cut-offs (Hz)")
    ap.add_argument(
        "--models",
        type=Path,
        metavar="DIR",
        help="models folder (experiments.fitting.cached_models: matcher/ and estimator/ model "
        "folders and fit.json; trained and written there if missing; old .pkl files are refused)",
    )
    ap.add_argument("--out", type=Path, help="write every number as JSON")
    args = ap.parse_args(argv)
    rig = load_rig("panoptic5")
    try:
        m = cached_models(rig, args.models)
    except InputError as e:
        raise SystemExit(str(e)) from None
    scenes = make_tracking_scenes(rig, SCALES["quick"], 0)
    fps, out = 30.0, {}
    pipelines = {
        "gat_mlp": {
            "matcher": m.matcher,
            "estimator": m.estimator,
            "proposals": "gat",
            "threshold": m.fit["threshold"],
        },
        "epipolar_dlt": {"half_score_px": m.fit["geometric_cutoff_px"]},
    }
    for split in args.splits.split(","):
        recs = scenes[split]
        gt, ids = tracking_truth(recs)
        gt_jitter = jitter(gt.xyz, gt.keypoint_valid, gt.valid, np.where(gt.valid, ids, -1))
        scoring = {"up": up_vector(rig), "person_ids": ids}
        for name, kwargs in pipelines.items():
            results = []
            for rec in recs:
                res = run_pipeline(
                    rig, rec.detections, tracking=TrackingConfig(), fps=fps, **kwargs
                )
                results.append(
                    PoseResults(
                        res.poses, res.confidence, res.members, res.identity, res.cameras,
                        rec.layout, rec.timestamps, res.track,
                    )
                )  # fmt: skip
            raw, track = pooled_tracks([r.poses for r in results], [r.track for r in results])
            row = {"identity": identity_metrics(raw, track, gt, gt_ids=ids)}
            variants = {"none": results}
            for c in args.cutoffs.split(","):
                variants[f"{float(c):g} Hz"] = [
                    smooth_poses(r, fps=fps, filter="butterworth", cutoff_hz=float(c))
                    for r in results
                ]
            for key, rs in variants.items():
                poses, trk = pooled_tracks([r.poses for r in rs], [r.track for r in rs])
                pm = pose_metrics(poses, gt, **scoring)
                row[key] = {
                    "jitter_x_truth": jitter(poses.xyz, poses.keypoint_valid, poses.valid, trk)
                    / gt_jitter,
                    "mpjpe_mm": pm["mpjpe_mm"],
                    "pcp": pm["pcp"],
                }
                print(
                    f"{split:10s} {name:12s} {key:8s} jitter x{row[key]['jitter_x_truth']:.2f} "
                    f"MPJPE {pm['mpjpe_mm']:.1f} mm PCP {pm['pcp']:.2f}",
                    flush=True,
                )
            ident = row["identity"]
            print(
                f"{split:10s} {name:12s} IDF1 {ident['idf1']:.4f}, "
                f"{ident['switches_per_1000']:.2f} switches per 1,000 person-frames",
                flush=True,
            )
            out[f"{split}/{name}"] = row
    if args.out:
        args.out.write_text(json.dumps(out, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
