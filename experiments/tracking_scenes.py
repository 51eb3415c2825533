"""Identities on crowded tracking scenes: ``python -m experiments.tracking_scenes``.

The tracking scenes of the experiments (`experiments.config.seed_stream`; ``panoptic5``, 1-8 people, 300 frames at 30 fps,
detector model on): validation seeds ``[0, 4, n]`` (every tracker setting is chosen on these),
test seeds ``[0, 6, n]`` (reported only). Each scene goes through the geometric pipeline
(epipolar proposals, ``--half-score-px``) with DLT and with robust triangulation, then through
the tracker with its old behaviour (``before``: no confirmation, no split-person handling, no
re-linking) and with its defaults (``after``), as `inference.run_pipeline(..., tracking=...)`
runs it. Identities are scored against the ground truth of the people at least one camera
detected (`metrics.identity_metrics`: IDF1, switches per 1,000 person-frames, MOTA).

Prints a Markdown table and writes it with the numbers to ``--out`` (JSON). ``--cache DIR``
keeps the pipeline's outputs between runs (outside the repository: it is only a speed-up).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from experiments.config import TRACKING_SPLITS, seed_stream
from experiments.data import seen_truth
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import group_people
from mvpose_jax.metrics import identity_metrics
from mvpose_jax.skeletons import Poses3D
from mvpose_jax.synthetic import generate_recording
from mvpose_jax.tracking import TrackingConfig, initial_state, track_frames

METHODS = ("dlt", "robust")
# The tracker as it was before confirmation, split handling and re-linking.
BEFORE = TrackingConfig(confirm_hits=1, keypoint_ttl_s=float("inf"), split_m=0.0, relink_gap_s=0.0)
TRACKERS = {"before": BEFORE, "after": TrackingConfig()}


def pipeline_output(
    rig, rec, method: str, half_score_px: float, cache: Path | None, key: str
) -> dict:
    """The untracked pipeline's people and their 2D skeletons (from ``cache`` when there)."""
    path = None
    if cache is not None:
        path = cache / f"{method}_{half_score_px:g}_{key}.npz"
        if path.exists():
            with np.load(path) as z:
                return dict(z)
    res = run_pipeline(rig, rec.detections, method=method, half_score_px=half_score_px)
    xy, score = group_people(
        np.asarray(rec.detections.xy), np.asarray(rec.detections.score), res.members
    )
    out = {
        "xyz": np.asarray(res.poses.xyz),
        "valid": np.asarray(res.poses.valid),
        "keypoint_valid": np.asarray(res.poses.keypoint_valid),
        "xy": xy,
        "score": score,
    }
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **out)
    return out


def track(rig, out: dict, config: TrackingConfig, fps: float) -> tuple[np.ndarray, float]:
    """Track ids (F, G) as the pipeline's tracking gives them, and the seconds it took."""
    t0 = time.perf_counter()
    _, ids = track_frames(
        initial_state(out["keypoint_valid"].shape[-1], rig.num_cameras),
        times=np.arange(len(out["valid"])) / fps,
        xyz=out["xyz"],
        keypoint_valid=out["keypoint_valid"],
        valid=out["valid"],
        xy=out["xy"],
        score=out["score"],
        rig=rig,
        config=config,
    )
    return ids, time.perf_counter() - t0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=[*TRACKING_SPLITS, "both"], default="both")
    parser.add_argument("--people", default="1-8", help="scene sizes, e.g. 1-8 or 6,8")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--half-score-px", type=float, default=30.0)
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    lo, _, hi = args.people.partition("-")
    people = list(range(int(lo), int(hi) + 1)) if hi else [int(p) for p in lo.split(",")]
    splits = list(TRACKING_SPLITS) if args.split == "both" else [args.split]
    rig = load_rig("panoptic5")
    rows, seconds, person_frames = [], {k: 0.0 for k in TRACKERS}, 0
    for split in splits:
        for n in people:
            rec = generate_recording(
                rig,
                num_people=n,
                num_frames=args.frames,
                seed=seed_stream(f"tracking/{split}", 0, n),
            )
            fps = 1.0 / float(np.median(np.diff(rec.timestamps)))
            gt = seen_truth(rec)
            for method in args.methods.split(","):
                key = f"{split}_{n}_{args.frames}"
                out = pipeline_output(rig, rec, method, args.half_score_px, args.cache, key)
                poses = Poses3D(out["xyz"], out["valid"], out["keypoint_valid"])
                person_frames += int(out["valid"].sum())
                for name, config in TRACKERS.items():
                    ids, s = track(rig, out, config, fps)
                    seconds[name] += s
                    m = identity_metrics(poses, ids, gt, layout=rec.layout)
                    rows.append({"split": split, "people": n, "method": method, "tracker": name})
                    rows[-1].update({k: m[k] for k in ("idf1", "mota", "id_switches")})
                    rows[-1].update({k: m[k] for k in ("switches_per_1000", "person_frames")})
                    rows[-1].update({k: m[k] for k in ("false_positives", "misses", "num_tracks")})
                    print(json.dumps(rows[-1]), flush=True)
    lines = table(rows)
    for name, s in seconds.items():
        lines.append(
            f"\nTracker `{name}`: {1000 * s / max(person_frames, 1):.4f} ms per person-frame "
            "(this machine, whole scenes)."
        )
    print("\n".join(lines))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"rows": rows, "table": lines}, indent=1))
    return 0


def table(rows: list[dict]) -> list[str]:
    """One row per split, method and scene size: IDF1, switches per 1,000, MOTA before/after."""
    lines = [
        "| split | method | people | IDF1 before | IDF1 after | sw/1000 before | sw/1000 after "
        "| MOTA before | MOTA after |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    keyed = {(r["split"], r["method"], r["people"], r["tracker"]): r for r in rows}
    for split, method, n in sorted({k[:3] for k in keyed}, key=lambda k: (k[0] != "validation", k)):
        b, a = keyed.get((split, method, n, "before")), keyed.get((split, method, n, "after"))
        cells = [split, method, str(n)]
        for key, nd in (("idf1", 4), ("switches_per_1000", 2), ("mota", 4)):
            cells += [f"{r[key]:.{nd}f}" if r else "-" for r in (b, a)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


if __name__ == "__main__":
    raise SystemExit(main())
