"""Does a speed-up change what the pipelines compute? Writes, then compares, their outputs.

    python -m benchmarks.same_results --write before.npz     # on the old commit
    python -m benchmarks.same_results --write after.npz      # on the new one
    python -m benchmarks.same_results --compare before.npz after.npz

The pipeline group's pipelines (`benchmarks.pipeline.PIPELINES`, each as ``infer`` builds
it, with the group's untrained models of the CLI's default sizes and their chosen proposal
settings) run offline (`run_pipeline`, chunks of 256) and live (one-frame chunks, the first
`LIVE_FRAMES` frames) on synthetic panoptic5 scenes with 1, 4 and 8 people and on the real
two-person trial of Pose2Sim's demo (where ``../shared/real`` is present). ``--compare`` says
how many keypoint coordinates were compared and where two runs differ: groupings (members,
identity), validity, tracks exactly; keypoints of valid people within ``--atol`` metres
(default 1e-5), confidences within 1e-5.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from benchmarks import pipeline, scenes
from mvpose_jax.inference import concat_results, run_pipeline, stream_pipeline
from mvpose_jax.skeletons import Detections

# (people, frames, seed) of the synthetic scenes.
SYNTHETIC = ((1, 64, 3), (4, 256, 4), (8, 128, 11))
REAL_FRAMES = 256
LIVE_FRAMES = 40
FIELDS = ("xyz", "valid", "keypoint_valid", "members", "identity", "confidence", "track")


def _scenes():
    tier = pipeline.PIPELINE_TIERS["quick"]
    for people, frames, seed in SYNTHETIC:
        rig, rec = scenes.recording(5, people, frames, seed=seed)
        det = Detections(*(np.asarray(a) for a in rec.detections))
        yield f"panoptic5-{people}p", rig, det, pipeline.train_models(rig, tier), pipeline.FPS
    real = pipeline.real_scene(frames=REAL_FRAMES)
    if isinstance(real, str):
        print(real, file=sys.stderr)
        return
    rig, det, fps = real
    yield "pose2sim-demo-2p", rig, det, pipeline.train_models(rig, tier), fps


def outputs() -> dict[str, np.ndarray]:
    """{"scene/pipeline/mode/field": array} of every pipeline on every scene."""
    out = {}
    for scene, rig, det, models, fps in _scenes():
        for name, (config, needs) in pipeline.pipeline_configs(models.settings).items():
            used = models.for_pipeline(needs)
            kw = dict(
                matcher=used.matcher if used else None,
                estimator=used.estimator if used else None,
                layout=pipeline.LAYOUT,
                fps=fps,
            )
            live_chunks = pipeline._one_frame_chunks(pipeline._frames(det, LIVE_FRAMES))
            results = {
                "offline": run_pipeline(rig, det, config, **kw),
                "live": concat_results(
                    [r for _, r in stream_pipeline(rig, live_chunks, config, **kw)]
                ),
            }
            for mode, r in results.items():
                values = {
                    "xyz": r.poses.xyz,
                    "valid": r.poses.valid,
                    "keypoint_valid": r.poses.keypoint_valid,
                    "members": r.members,
                    "identity": r.identity,
                    "confidence": r.confidence,
                    "track": r.track if r.track is not None else np.zeros(0, np.int32),
                }
                for field, v in values.items():
                    out[f"{scene}/{name}/{mode}/{field}"] = np.asarray(v)
            print(f"{scene} {name}: {int(np.asarray(results['offline'].poses.valid).sum())} people")
    return out


def compare(a: dict, b: dict, atol: float = 1e-5) -> tuple[int, list[str]]:
    """(keypoint coordinates compared, the differences found)."""
    problems, compared = [], 0
    if set(a) != set(b):
        problems.append(f"different entries: {sorted(set(a) ^ set(b))[:6]}")
    for key in sorted(set(a) & set(b)):
        x, y = a[key], b[key]
        if x.shape != y.shape:
            problems.append(f"{key}: shape {x.shape} vs {y.shape}")
            continue
        field = key.rsplit("/", 1)[1]
        if field == "xyz":
            base = key.rsplit("/", 1)[0]
            used = a[f"{base}/valid"][..., None] & a[f"{base}/keypoint_valid"]
            compared += 3 * int(used.sum())
            diff = np.abs(np.where(used[..., None], x - y, 0.0))
            if diff.size and diff.max() > atol:
                problems.append(f"{key}: {diff.max():.2e} m apart")
        elif field == "confidence":
            if x.size and np.abs(x - y).max() > 1e-5:
                problems.append(f"{key}: {np.abs(x - y).max():.2e} apart")
        elif not np.array_equal(x, y):
            problems.append(f"{key}: {int((x != y).sum())} values differ")
    return compared, problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--write", metavar="FILE.npz", help="run every pipeline, save the outputs")
    action.add_argument("--compare", nargs=2, metavar="FILE.npz", help="two saved runs")
    parser.add_argument("--atol", type=float, default=1e-5, help="keypoints, metres")
    args = parser.parse_args(argv)
    if args.write:
        np.savez_compressed(args.write, **outputs())
        print(f"wrote {args.write}")
        return 0
    a, b = (dict(np.load(p)) for p in args.compare)
    compared, problems = compare(a, b, args.atol)
    print(
        f"{compared} keypoint coordinates compared (valid people, every scene, pipeline and "
        f"mode); groupings, validity and tracks compared exactly: "
        + ("identical" if not problems else f"{len(problems)} differences")
    )
    for p in problems:
        print("  " + p)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
