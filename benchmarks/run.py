"""The benchmark harness: per-frame latency, offline and training throughput, peak memory, targets.

    python -m benchmarks.run [--quick | --smoke] [--out results/benchmarks] [--groups latency,offline]

Runs five groups, each in its own Python process so that its peak memory is its own (`measure`):
``peaks`` (float32 matmul peak, memory bandwidth), ``latency`` (t_pp, t_3Dg, t_3Di per frame over
views x people x model size, the triangulation rows, and the time breakdown of the target
configuration), ``offline`` (a long recording in batches), ``training`` (train-step
throughput, compile times), ``tracking`` (the tracker and One-Euro filter per frame) and
``infer_memory`` (peak RSS of ``mvpose-jax infer`` against the recording's length,
`benchmarks.memory`) and ``adapt`` and ``adapt_matcher`` (seconds per 1,000 frames of `adapt.adapt_estimator` and
`adapt.adapt_matcher`) and ``pipeline`` (what users run: `infer`'s default with models, the
paper's method, the geometric default and epipolar + DLT, live and offline, per stage;
`benchmarks.pipeline`) and ``batch`` (many recordings on a local Ray with 1 and 2 workers, and
a worker's start-up cost; `benchmarks.batch`). Writes ``run.json`` and ``run.md`` under ``--out`` with the machine,
the git commit, every measurement, the targets with pass/miss, and where the time goes.

``--quick`` (under 3 minutes on 2 cores) shrinks the grid and the frame counts but keeps every
section; ``--smoke`` is a seconds-long check of the harness itself (tests), without ``batch``
unless named (starting Ray and a worker costs ~15 s: ``--smoke --groups batch``;
tests/test_batch.py covers the job itself). On a GPU machine the
same command runs there, and the report names the device. See benchmarks/README.md.
"""

from __future__ import annotations

import os

# Host-side numpy and OpenCV on one thread (the synthetic benchmark's convention), set before numpy
# loads; XLA's own CPU thread pool is not affected and uses every core.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MEMORY_METHOD = (
    "each group in its own process; peak RSS = its getrusage ru_maxrss, growth = peak minus "
    "the RSS right after its imports; device peak = jax memory_stats() peak_bytes_in_use "
    "where the backend reports it (GPU), else -"
)


DEFAULT_GROUPS = (
    "peaks,latency,offline,training,tracking,infer_memory,adapt,adapt_matcher,pipeline,batch"
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    tier = parser.add_mutually_exclusive_group()
    tier.add_argument(
        "--quick", action="store_true", help="a smaller grid and fewer frames (under 3 minutes)"
    )
    tier.add_argument(
        "--smoke", action="store_true", help="one tiny configuration: checks the harness (tests)"
    )
    parser.add_argument(
        "--out", default="results/benchmarks", help="folder for run.json and run.md"
    )
    parser.add_argument(
        "--groups",
        default=None,
        help=f"comma-separated groups to run (default: {DEFAULT_GROUPS}; --smoke: all but batch)",
    )
    parser.add_argument(
        "--in-process",
        action="store_true",
        help="run the groups in this process (debugging; peak memory is then cumulative)",
    )
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--tier", help=argparse.SUPPRESS)
    parser.add_argument("--child-out", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        return _child(args.child, args.tier, Path(args.child_out))

    tier = "smoke" if args.smoke else "quick" if args.quick else "full"
    names = args.groups or DEFAULT_GROUPS
    groups = [g.strip() for g in names.split(",") if g.strip()]
    if args.groups is None and args.smoke:
        groups.remove("batch")
    from benchmarks.measure import GROUPS

    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        parser.error(f"unknown groups {unknown}; groups: {list(GROUPS)}")
    start = time.perf_counter()
    load_before = _loadavg()
    run: dict = {
        "benchmark": "run",
        "tier": tier,
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "git": _git(),
        "memory_method": MEMORY_METHOD,
        "memory": {},
        "errors": {},
    }
    # The machine's peaks are measured again at the end: the bounds are the better of the two, and
    # a large difference says the machine's load changed during the run.
    steps = [(g, g) for g in groups] + (
        [("peaks", "peaks_end")] if "peaks" in groups and len(groups) > 1 else []
    )
    for group, key in steps:
        print(f"[benchmarks] {key} ({tier}) ...", flush=True)
        t = time.perf_counter()
        result, memory, error = (_in_process if args.in_process else _subprocess)(group, tier)
        if error:
            run["errors"][key] = error
            print(f"[benchmarks] {key} FAILED: {error}", file=sys.stderr, flush=True)
        elif key == "peaks_end":
            if "peaks" in run:
                run["peaks"] = _merge_peaks(run["peaks"], result)
        else:
            run[key] = result
            run["memory"][key] = {**memory, "seconds": time.perf_counter() - t}
            print(f"[benchmarks] {key} done in {time.perf_counter() - t:.0f} s", flush=True)
    run["machine"] = _machine(load_before, _loadavg())
    if args.in_process:
        run["memory_method"] = "in-process run: ru_maxrss is cumulative over the groups run before"

    from benchmarks.report import markdown, profile_notes, targets

    run["targets"] = targets(run)
    run["profile"] = profile_notes(run)
    run["seconds"] = time.perf_counter() - start
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from mvpose_jax.data.files import atomic_write_text, to_jsonable

    text = markdown(run)
    atomic_write_text(out / "run.json", json.dumps(to_jsonable(run), indent=1) + "\n")
    atomic_write_text(out / "run.md", text)
    print(text)
    print(f"wrote {out / 'run.json'} and {out / 'run.md'} ({run['seconds']:.0f} s)")
    return 1 if run["errors"] else 0


def _merge_peaks(start: dict, end: dict) -> dict:
    """The better of two peak measurements, with both kept and their spread."""
    out = dict(start)
    for key in ("matmul_gflops", "bandwidth_gbs"):
        out[key] = max(start[key], end[key])
        out[f"{key}_start_end"] = [start[key], end[key]]
    out["spread"] = max(
        abs(start[k] - end[k]) / max(start[k], end[k]) for k in ("matmul_gflops", "bandwidth_gbs")
    )
    return out


# --------------------------------------------------------------------------- group processes


def _subprocess(group: str, tier: str) -> tuple[dict | None, dict | None, str | None]:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{group}.json"
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
        cmd = [
            sys.executable,
            "-m",
            "benchmarks.run",
            "--child",
            group,
            "--tier",
            tier,
            "--child-out",
            str(path),
        ]
        proc = subprocess.run(
            cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        if proc.returncode != 0 or not path.exists():
            return None, None, f"exit {proc.returncode}: {proc.stdout[-2000:]}"
        data = json.loads(path.read_text())
    return data["result"], data["memory"], None


def _in_process(group: str, tier: str) -> tuple[dict | None, dict | None, str | None]:
    from benchmarks.measure import GROUPS, TIERS

    rss = _rss_mb()
    try:
        result = GROUPS[group](TIERS[tier])
    except Exception as e:
        return None, None, f"{type(e).__name__}: {e}"
    return (
        result,
        {"maxrss_mb": _rss_mb(), "rss_after_import_mb": rss, "device_peak_mb": _device_peak_mb()},
        None,
    )


# Groups whose figures leave compilation out (every timed run follows an untimed warm-up), and
# whose own process therefore keeps its compiled programs on disk between runs, as `infer` and
# the experiments do (`compiled.enable_compilation_cache`): a second `--quick` run of
# ``pipeline`` skips most of its compiling (169 -> 82 s on 2 cores), and a cached program is the
# program a compile gives. Not in `--in-process` runs, where the cache would reach the groups
# after it, some of which time their compiles.
CACHED_GROUPS = ("pipeline",)


def _child(group: str, tier: str, out: Path) -> int:
    import jax

    from benchmarks.measure import GROUPS, TIERS
    from mvpose_jax.compiled import enable_compilation_cache
    from mvpose_jax.data.files import to_jsonable

    cache = enable_compilation_cache() if group in CACHED_GROUPS else None
    jax.devices()  # the backend's own memory belongs to the baseline
    rss = _current_rss_mb()
    result = GROUPS[group](TIERS[tier])
    if cache is not None and isinstance(result, dict):
        result.setdefault("notes", []).append(
            f"compiled programs kept between runs in {cache} (the warm-ups compile only what "
            "is not there; no timed run includes compiling)"
        )
    memory = {
        "maxrss_mb": _rss_mb(),
        "rss_after_import_mb": rss,
        "device_peak_mb": _device_peak_mb(),
    }
    out.write_text(json.dumps(to_jsonable({"result": result, "memory": memory})))
    return 0


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def _current_rss_mb() -> float:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return _rss_mb()


def _device_peak_mb() -> float | None:
    import jax

    stats = jax.devices()[0].memory_stats()
    if not stats or "peak_bytes_in_use" not in stats:
        return None
    return stats["peak_bytes_in_use"] / 2**20


# --------------------------------------------------------------------------- machine description


def _machine(load_before, load_after) -> dict:
    import cv2
    import flax
    import jax
    import jaxlib
    import numpy as np

    dev = jax.devices()[0]
    cores = os.cpu_count() or 1
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cores
    return {
        "cpu_model": _cpu_model(),
        "cpu_count": cores,
        "cores_usable": usable,
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "flax": flax.__version__,
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "device": f"{dev.platform}: {getattr(dev, 'device_kind', '')} x{jax.device_count()}".strip(),
        "gpu": dev.platform == "gpu",
        "platform": platform.platform(),
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_before": load_before,
        "load_after": load_after,
        # The run itself keeps every core busy (load ~ cores at its end): other work shows as load
        # before it, or as load well above the cores after it.
        "loaded": load_before[0] > 0.5 * usable or load_after[0] > 1.25 * usable,
    }


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _loadavg() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return [0.0, 0.0, 0.0]


def _git() -> dict:
    def git(*cmd):
        try:
            return subprocess.run(
                ["git", *cmd], cwd=REPO, capture_output=True, text=True, check=True
            ).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return ""

    return {
        "commit": git("rev-parse", "HEAD") or "unknown",
        "dirty": bool(git("status", "--porcelain", "-uno")),
    }


if __name__ == "__main__":
    sys.exit(main())
