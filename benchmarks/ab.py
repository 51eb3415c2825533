"""An older commit's pipelines and the working tree's, timed in one process, in turn.

    python -m benchmarks.ab --old 84d069e [--pipelines geometric default] [--repeats 9] [--out DIR]

On a shared 2-core VM the same run can take up to 50 % longer in a process started a few minutes
later (docs/performance.md, "December 7"): more than most speed-ups, so two harness runs, one per
commit, cannot tell them apart. Here one process holds both versions: the old commit's
``mvpose_jax`` and ``benchmarks`` are extracted from git and imported under other names
(``mvpose_jax_old``, ``benchmarks_old``, every import rewritten), beside the working tree's. Each
(scene, pipeline, mode) is set up in both, as the ``pipeline`` group sets it up
(`benchmarks.pipeline.pipeline_configs`, `train_models` at the quick tier: random weights of the
CLI's default sizes), run twice to warm up, then run in turn, old then new, ``repeats`` times,
so that a slow minute slows both. Modes: live (one-frame chunks of the first `LIVE_FRAMES`
frames, the tracker's state kept) and offline (the scene's frames in one `run_pipeline` call,
without the Butterworth pass). A record gives each version's best and median ms per frame and
the median, over the repeats, of new / old.

The old commit must have the ``pipeline`` group's functions (`pipeline_configs`,
`train_models`, `real_scene`, `_one_frame_chunks`, `_frames`; main since December 6).
"""

from __future__ import annotations

import argparse
import gc
import importlib
import json
import re
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from io import BytesIO
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from benchmarks import pipeline, scenes

REPO = Path(__file__).resolve().parents[1]
SUFFIX = "_old"
PACKAGES = ("mvpose_jax", "benchmarks")
LIVE_FRAMES = 64
OFFLINE_FRAMES = 256
SCENES = ("panoptic5-4p", "pose2sim-demo-2p")


def extract_old(rev: str, dest: Path, repo: Path = REPO) -> Path:
    """``rev``'s packages under ``dest`` as ``mvpose_jax_old`` and ``benchmarks_old``, their
    imports of each other rewritten (package data kept); returns ``dest`` (put it on sys.path).

    Raises:
      subprocess.CalledProcessError: ``rev`` is not a commit of ``repo``.
    """
    archive = subprocess.run(
        ["git", "-C", str(repo), "archive", "--format=tar", rev, *PACKAGES],
        check=True,
        capture_output=True,
    ).stdout
    safe = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}  # Python >= 3.11.4
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(dest, **safe)
    names = re.compile(r"\b(" + "|".join(PACKAGES) + r")\b")
    for package in PACKAGES:
        root = dest / (package + SUFFIX)
        (dest / package).rename(root)
        for path in root.rglob("*.py"):
            path.write_text(names.sub(lambda m: m.group(1) + SUFFIX, path.read_text()))
    return dest


def _setup(bench, inference, scene: str, names: list[str]) -> dict[str, tuple[Callable, ...]]:
    """{pipeline: (live run, offline run)} of one version on ``scene``; each run returns the
    frames it processed."""
    if scene == "pose2sim-demo-2p":
        # The real trial's folder as this tree finds it (the old copy's own path is elsewhere).
        real = bench.pipeline.real_scene(pipeline.REAL_DATA, frames=OFFLINE_FRAMES)
        if isinstance(real, str):
            raise FileNotFoundError(real)
        rig, det, fps = real
    else:
        rig, rec = bench.scenes.recording(5, 4, OFFLINE_FRAMES, seed=0)
        det, fps = rec.detections, pipeline.FPS
    models = bench.pipeline.train_models(rig, bench.pipeline.PIPELINE_TIERS["quick"])
    configs = bench.pipeline.pipeline_configs(models.settings)
    runs = {}
    for name in names:
        config, needs = configs[name]
        used = models.for_pipeline(needs)
        kw = dict(
            matcher=used.matcher if used else None,
            estimator=used.estimator if used else None,
            layout=bench.pipeline.LAYOUT,
            fps=fps,
        )
        chunks = bench.pipeline._one_frame_chunks(bench.pipeline._frames(det, LIVE_FRAMES))

        def live(rig=rig, chunks=chunks, config=config, kw=kw) -> int:
            for _ in inference.stream_pipeline(rig, chunks, config, **kw):
                pass
            return len(chunks)

        def offline(rig=rig, det=det, config=config, kw=kw) -> int:
            inference.run_pipeline(rig, det, config, **kw)
            return len(det.count)

        runs[name] = (live, offline)
    return runs


def compare(old: str, names: list[str], repeats: int, scene_names=SCENES) -> list[dict]:
    """The records of ``old`` against the working tree (module docstring)."""
    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, str(extract_old(old, Path(tmp))))
        try:
            old_pkgs = (
                SimpleNamespace(
                    pipeline=importlib.import_module("benchmarks" + SUFFIX + ".pipeline"),
                    scenes=importlib.import_module("benchmarks" + SUFFIX + ".scenes"),
                ),
                importlib.import_module("mvpose_jax" + SUFFIX + ".inference"),
            )
            from mvpose_jax import inference

            new_pkgs = (SimpleNamespace(pipeline=pipeline, scenes=scenes), inference)
            records = []
            for scene in scene_names:
                try:
                    a, b = _setup(*old_pkgs, scene, names), _setup(*new_pkgs, scene, names)
                except FileNotFoundError as e:
                    print(f"{scene}: {e}", file=sys.stderr)
                    continue
                for name in names:
                    for mode, i in (("live", 0), ("offline", 1)):
                        records.append(
                            _time_pair(scene, name, mode, a[name][i], b[name][i], repeats)
                        )
                        print(_row(records[-1]), flush=True)
            return records
        finally:
            sys.path.remove(tmp)


def _time_pair(scene: str, name: str, mode: str, old: Callable, new: Callable, repeats: int):
    for _ in range(2):  # compile every shape, build every graph
        old(), new()
    t_old, t_new = [], []
    for _ in range(repeats):
        for run, times in ((old, t_old), (new, t_new)):
            gc.collect()
            t0 = time.perf_counter()
            frames = run()
            times.append((time.perf_counter() - t0) / frames * 1e3)
    ratio = np.asarray(t_new) / np.asarray(t_old)
    return {
        "scene": scene,
        "pipeline": name,
        "mode": mode,
        "old_ms_best": min(t_old),
        "old_ms_median": float(np.median(t_old)),
        "new_ms_best": min(t_new),
        "new_ms_median": float(np.median(t_new)),
        "new_over_old": float(np.median(ratio)),
        "repeats": repeats,
    }


def _row(r: dict) -> str:
    return (
        f"| {r['scene']} | {r['pipeline']} | {r['mode']} | {r['old_ms_best']:.3f} | "
        f"{r['new_ms_best']:.3f} | {r['new_over_old']:.3f} |"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", required=True, help="the commit to compare with (any git rev)")
    parser.add_argument(
        "--pipelines", nargs="+", default=list(pipeline.PIPELINES), choices=pipeline.PIPELINES
    )
    parser.add_argument("--repeats", type=int, default=9, help="runs of each version, in turn")
    parser.add_argument("--out", type=Path, help="folder for ab.json and ab.md")
    args = parser.parse_args(argv)
    print("| scene | pipeline | mode | old, best ms/frame | new, best | new / old (median) |")
    print("|---|---|---|---|---|---|")
    records = compare(args.old, args.pipelines, args.repeats)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        head = ["| scene | pipeline | mode | old, best ms/frame | new, best | new / old (median) |"]
        text = "\n".join(head + ["|---|---|---|---|---|---|"] + [_row(r) for r in records]) + "\n"
        written = {"ab.json": json.dumps({"old": args.old, "records": records}, indent=1)}
        written["ab.md"] = text
        for name, body in written.items():
            tmp = args.out / (name + ".tmp")
            tmp.write_text(body)
            tmp.replace(args.out / name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
