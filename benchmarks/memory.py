"""Peak memory of ``mvpose-jax infer`` against the recording's length (group ``infer_memory``).

    python -m benchmarks.memory [--frames 1000 10000 100000] [--out results/benchmarks]

For each length, a recording of that many frames (4 people, the 5 cameras of ``panoptic5``) is
written as ``.npz`` and ``mvpose-jax infer`` (geometric matcher, DLT) runs on it in its own
process; its peak resident set is that process's ``ru_maxrss`` (`os.wait4`), so each length's
number is its own. The target: the peaks of every length within 10 % of each other.

The input is built without simulating every frame: a few hundred frames from
`mvpose_jax.synthetic.generate_recording`, repeated (frame ``f`` is frame ``f % base`` of the
simulation, timestamps continue), and written member by member straight into the archive
(deflated), a block of frames at a time, so the builder's memory does not grow with the length
either. The archive holds what a 2D detector gives: ``xy``, ``score``, ``count``, ``timestamps``.

For comparison, lengths up to ``whole_max_frames`` also run the library the way ``infer`` did
before it streamed: `data.load_recording`, `inference.run_pipeline` (all chunks joined) and
`data.poses.save_poses`, in a process of their own.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BASE_FRAMES = 300
PEOPLE = 4
FLAT_TOLERANCE = 0.10  # the target: peaks within 10 % of each other

# The whole-recording path, as ``infer`` ran before it streamed (argv: detections, out, chunk).
_WHOLE = """
import sys
from mvpose_jax.data import load_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.poses import PoseResults, save_poses
from mvpose_jax.inference import run_pipeline
rig = load_rig("panoptic5")
rec = load_recording(sys.argv[1], rig=rig)
res = run_pipeline(rig.select(list(rec.cameras)), rec.detections, chunk_frames=int(sys.argv[3]))
save_poses(PoseResults(res.poses, res.confidence, res.members, res.identity, res.cameras,
                       rec.layout, rec.timestamps), sys.argv[2])
"""


def write_tiled_npz(path: str | os.PathLike, num_frames: int, *, seed: int = 0) -> dict:
    """Writes a ``num_frames`` recording (module docstring) to ``path``; returns its description."""
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.synthetic import generate_recording

    base_frames = min(BASE_FRAMES, num_frames)
    rec = generate_recording(
        load_rig("panoptic5"), num_people=PEOPLE, num_frames=base_frames, seed=seed
    )
    det = rec.detections
    base = {
        "xy": np.asarray(det.xy, np.float32),
        "score": np.asarray(det.score, np.float32),
        "count": np.asarray(det.count, np.int32),
    }
    ts = np.asarray(rec.timestamps, np.float64)
    step = float(np.median(np.diff(ts))) if len(ts) > 1 else 1 / 30
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, value in (
            ("version", np.asarray(1, np.int32)),
            ("layout", np.asarray(rec.layout, dtype=str)),
            ("cameras", np.asarray(rec.cameras, dtype=str)),
        ):
            with zf.open(name + ".npy", "w") as f:
                np.lib.format.write_array(f, value, allow_pickle=False)
        for name, rows in (*base.items(), ("timestamps", None)):
            dtype = np.dtype(np.float64 if rows is None else rows.dtype)
            shape = (num_frames, *(() if rows is None else rows.shape[1:]))
            header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False}
            with zf.open(name + ".npy", "w", force_zip64=True) as f:
                np.lib.format.write_array_header_2_0(f, {**header, "shape": shape})
                for start in range(0, num_frames, base_frames):
                    n = min(base_frames, num_frames - start)
                    block = (start + np.arange(n)) * step if rows is None else rows[:n]
                    f.write(np.ascontiguousarray(block, dtype).tobytes())
    return {
        "frames": num_frames,
        "simulated_frames": base_frames,
        "people": PEOPLE,
        "cameras": len(rec.cameras),
        "skeletons_per_view": int(base["xy"].shape[2]),
        "file_mb": Path(path).stat().st_size / 2**20,
    }


def run_measured(cmd: list[str], log: Path) -> dict:
    """Runs ``cmd`` in its own process: its peak RSS (MB), wall seconds and exit status."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    t = time.perf_counter()
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
    return {
        "maxrss_mb": usage.ru_maxrss / 1024.0,  # Linux: kilobytes
        "seconds": time.perf_counter() - t,
        "exit": proc.returncode,
    }


def infer_memory(
    frames: tuple[int, ...], *, chunk_frames: int = 256, whole_max_frames: int = 10_000
) -> dict:
    """Peak RSS of ``infer`` (and of the whole-recording path) for each length in ``frames``."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for n in frames:
            path = tmp / f"rec_{n}.npz"
            t = time.perf_counter()
            row = write_tiled_npz(path, n)
            row["build_seconds"] = time.perf_counter() - t
            cmd = [sys.executable, "-m", "mvpose_jax.cli", "infer", "--rig", "panoptic5"]
            cmd += ["--detections", str(path), "--out", str(tmp / f"out_{n}")]
            cmd += ["--chunk-frames", str(chunk_frames)]
            row["infer"] = run_measured(cmd, tmp / f"infer_{n}.log")
            if row["infer"]["exit"] != 0:
                raise RuntimeError(
                    f"infer failed on {n} frames: {(tmp / f'infer_{n}.log').read_text()[-2000:]}"
                )
            row["infer"]["frames_per_s"] = n / row["infer"]["seconds"]
            if n <= whole_max_frames:
                cmd = [sys.executable, "-c", _WHOLE, str(path), str(tmp / f"whole_{n}")]
                row["whole"] = run_measured(cmd + [str(chunk_frames)], tmp / f"whole_{n}.log")
            path.unlink()
            rows.append(row)
            print(f"[infer_memory] {json.dumps(row)}", flush=True)
    peaks = [r["infer"]["maxrss_mb"] for r in rows]
    spread = max(peaks) / min(peaks) - 1 if peaks else None
    return {
        "chunk_frames": chunk_frames,
        "rows": rows,
        "spread": spread,
        "target": FLAT_TOLERANCE,
        "flat": None if spread is None else spread <= FLAT_TOLERANCE,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[1000, 10_000, 100_000])
    parser.add_argument("--chunk-frames", type=int, default=256)
    parser.add_argument("--whole-max-frames", type=int, default=10_000)
    parser.add_argument("--out", default="results/benchmarks")
    args = parser.parse_args(argv)
    result = infer_memory(
        tuple(args.frames),
        chunk_frames=args.chunk_frames,
        whole_max_frames=args.whole_max_frames,
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "infer_memory.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
