"""Throughput of the synthetic-data generator.

    python -m benchmarks.synthetic [--quick] [--out results/benchmarks/synthetic.json]

Measures, on one CPU thread (BLAS and OpenMP pools are limited to one thread before numpy loads):
  * single-person training data: five-camera (panoptic5) frames per second, 20 recordings of
    500 frames per run (target: at least 10,000 frames/s);
  * a test scene: 8 people, 2,000 frames, the six arplab6 cameras, seconds per recording
    (target: under 10 s).
Each measurement is warmed up once (the rig's floor and capture area are computed and cached
then), repeated, and reported as median and interquartile range. Prints a table and writes JSON.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from mvpose_jax.data.calibration import load_rig  # noqa: E402
from mvpose_jax.data.files import atomic_write_text  # noqa: E402
from mvpose_jax.synthetic import generate_recording, generate_single_person_recordings  # noqa: E402


def _time(fn, repeats: int) -> np.ndarray:
    fn(0)  # warm-up: caches the rig's scene geometry
    out = []
    for i in range(repeats):
        t = time.perf_counter()
        fn(i + 1)
        out.append(time.perf_counter() - t)
    return np.asarray(out)


def _stats(seconds: np.ndarray, work: float) -> dict:
    q1, med, q3 = np.percentile(seconds, [25, 50, 75])
    return {
        "seconds_median": float(med),
        "seconds_iqr": [float(q1), float(q3)],
        "per_second_median": float(work / med),
        "per_second_iqr": [float(work / q3), float(work / q1)],
        "repeats": int(seconds.size),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats, smaller runs")
    parser.add_argument("--out", default="results/benchmarks/synthetic.json")
    args = parser.parse_args(argv)
    repeats = 2 if args.quick else 5

    panoptic, arplab = load_rig("panoptic5"), load_rig("arplab6")
    n_rec, n_frames = (4, 250) if args.quick else (20, 500)
    single = _time(
        lambda s: generate_single_person_recordings(
            panoptic, num_recordings=n_rec, num_frames=n_frames, seed=s
        ),
        repeats,
    )
    scene_frames = 500 if args.quick else 2000
    scene = _time(
        lambda s: generate_recording(arplab, num_people=8, num_frames=scene_frames, seed=s),
        max(2, repeats - 2),
    )
    results = {
        "benchmark": "synthetic",
        "machine": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        },
        "single_person": {
            "rig": "panoptic5",
            "cameras": 5,
            "recordings": n_rec,
            "frames_per_recording": n_frames,
            "target_frames_per_second": 10_000,
            **_stats(single, n_rec * n_frames),
        },
        "multi_person": {
            "rig": "arplab6",
            "cameras": 6,
            "people": 8,
            "frames": scene_frames,
            "target_seconds": 10.0,
            **_stats(scene, scene_frames),
        },
    }
    sp, mp = results["single_person"], results["multi_person"]
    print(
        f"single-person, panoptic5 (5 cameras): {sp['per_second_median']:,.0f} frames/s "
        f"(IQR {sp['per_second_iqr'][0]:,.0f}-{sp['per_second_iqr'][1]:,.0f}; target >= 10,000)"
    )
    print(
        f"8 people x {scene_frames} frames, arplab6 (6 cameras): {mp['seconds_median']:.2f} s "
        f"(IQR {mp['seconds_iqr'][0]:.2f}-{mp['seconds_iqr'][1]:.2f}; {mp['per_second_median']:,.0f} "
        f"frames/s; target < 10 s for 2,000 frames)"
    )
    out = Path(args.out)
    atomic_write_text(out, json.dumps(results, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
