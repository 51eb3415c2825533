"""Skeleton-matching acceptance (the paper's Tables 3 and 4) on synthetic data.

``python -m experiments.matching [--quick] [--out results/matching] [--only NAME ...]``

For each setup (rig, inference cameras) a matcher is trained FROM SCRATCH on this machine from
single-person synthetic recordings (no association labels: they come from composing recordings),
then evaluated on held-out multi-person recordings with 1-8 people (detector model on: noise,
misses, occlusion, false positives). Beside it, the geometric baseline (symmetric epipolar
distance, the same proposal step). Matching is scored as a clustering of the detections: ARI,
homogeneity, completeness, V-measure, pooled over every detection of the test set (false
positives and detections left out of every proposal are singletons). Times: training seconds and
inference milliseconds per frame (scores + proposals, after a warm-up).

Writes ``metrics.json`` and ``tables.md`` in the output folder (atomic writes).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np

from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.formats import select_cameras
from mvpose_jax.data.synthetic import generate_recording, generate_single_person_recordings
from mvpose_jax.inference import gat_match_table, geometric_match_table, propose_people
from mvpose_jax.metrics import matching_scores
from mvpose_jax.models import GATConfig
from mvpose_jax.train import MATCHER_TRAIN, MatcherConfig, train_matcher

# name -> (rig preset, inference cameras (None: all), paper ARI)
SETUPS = {
    "panoptic5-2": ("panoptic5", ("trackera", "trackerb"), 0.9875),
    "panoptic5-3": ("panoptic5", ("trackera", "trackerb", "trackerc"), 0.9977),
    "panoptic5-5": ("panoptic5", None, 0.9941),
    "arplab6-2": ("arplab6", ("orinbot_l", "orinbot_r"), 0.9770),
    "arplab6-6": ("arplab6", None, 0.9842),
}
GEOMETRIC_HALF_SCORE_PX = 30.0


@dataclasses.dataclass(frozen=True)
class Scale:
    """Data and training sizes of a run.

    Attributes:
      train_recordings, train_frames: single-person training recordings and their length.
      dev_recordings, dev_frames: single-person validation recordings.
      test_frames: frames of each multi-person test recording (one per people count 1..8).
      matcher: the matcher configuration (cameras filled in per setup).
    """

    train_recordings: int
    train_frames: int
    dev_recordings: int
    dev_frames: int
    test_frames: int
    matcher: MatcherConfig


def scale(quick: bool) -> Scale:
    if quick:
        return Scale(8, 150, 3, 100, 10, MatcherConfig.quick())
    # The paper's GAT, 15 graphs a batch, validation every 5 epochs and patience 5. To fit a
    # 2-core CPU, Adam starts at 1e-3 (paper 1e-4, about 10x more steps to the same loss) and
    # decays (cosine) to 5e-5 over a per-setup epoch budget (`EPOCHS`: graphs of few views are
    # cheap). Many short recordings (150 people of 100 frames) rather than a few long ones: with
    # 16 people the GAT overfit their bodies and paths.
    train = dataclasses.replace(MATCHER_TRAIN, learning_rate=1e-3, max_epochs=40)
    matcher = MatcherConfig(gat=GATConfig(), train=dataclasses.replace(train, final_lr_fraction=0.05))
    return Scale(150, 100, 20, 50, 50, matcher)


# Full-tier epochs (of 100 steps) per number of inference views: steps cost ~13 ms with 2
# views, ~30 ms with 3 and ~80 ms with 5-6 on this CPU.
EPOCHS = {2: 150, 3: 80, 5: 40, 6: 40}


def run_setup(name: str, sc: Scale, seed: int, progress: bool, quick: bool) -> dict:
    rig_name, cameras, paper_ari = SETUPS[name]
    rig = load_rig(rig_name)
    cams = tuple(cameras or rig.names)
    # Seeds: training, dev and test data never share a generator stream.
    train = generate_single_person_recordings(rig, num_recordings=sc.train_recordings, num_frames=sc.train_frames,
                                              seed=[seed, 1])  # fmt: skip
    dev = generate_single_person_recordings(rig, num_recordings=sc.dev_recordings, num_frames=sc.dev_frames,
                                            seed=[seed, 2])  # fmt: skip
    tests = [select_cameras(generate_recording(rig, num_people=n, num_frames=sc.test_frames, seed=[seed, 3, n]), cams)
             for n in range(1, 9)]  # fmt: skip
    config = dataclasses.replace(sc.matcher, cameras=cams)
    if not quick:
        config = dataclasses.replace(config, train=dataclasses.replace(config.train, max_epochs=EPOCHS[len(cams)]))
    t0 = time.perf_counter()
    matcher, fit = train_matcher(rig, train, dev, config, progress=progress)
    train_s = time.perf_counter() - t0
    rig_i = rig.select(list(cams))

    # All test frames as one padded recording (P padded to the largest view).
    P = max(np.shape(t.detections.score)[2] for t in tests)
    pad = lambda a, fill=0: np.pad(np.asarray(a), [(0, 0), (0, 0), (0, P - np.shape(a)[2])]  # noqa: E731
                                   + [(0, 0)] * (np.ndim(a) - 3), constant_values=fill)  # fmt: skip
    from mvpose_jax.skeletons import Detections

    det = Detections(np.concatenate([pad(t.detections.xy) for t in tests]),
                     np.concatenate([pad(t.detections.score) for t in tests]),
                     np.concatenate([np.asarray(t.detections.count) for t in tests]))  # fmt: skip
    truth = np.concatenate([pad(t.identity, -1) for t in tests])
    F = len(det.count)

    methods = {
        "gat": lambda: gat_match_table(matcher, det),
        "geometric": lambda: geometric_match_table(rig_i, det, half_score_px=GEOMETRIC_HALF_SCORE_PX),
    }
    out = {"setup": name, "rig": rig_name, "cameras": list(cams), "paper_ari": paper_ari, "test_frames": F,
           "train_seconds": round(train_s, 1), "train_steps": fit.steps, "best_val_loss": fit.best_val_loss,
           "history": fit.history}  # fmt: skip
    for method, table in methods.items():
        table()  # warm-up: compile every shape this test set needs
        t0 = time.perf_counter()
        rows, scores = table()
        proposals = propose_people(rows, scores, det.count, num_skeletons=P)
        ms = 1000 * (time.perf_counter() - t0) / F
        scores_ = matching_scores(truth, proposals.identity, np.asarray(det.count))
        out[method] = {**{k: round(v, 5) for k, v in scores_.items()}, "ms_per_frame": round(ms, 3)}
        # Diagnostic only (chosen on the test set, so never a reported result): how the proposal
        # threshold trades joining against splitting.
        out[method]["ari_by_threshold"] = {
            str(th): round(matching_scores(truth, propose_people(rows, scores, det.count, num_skeletons=P,
                                                                 threshold=th).identity,
                                           np.asarray(det.count))["ari"], 5)
            for th in (0.2, 0.3, 0.4, 0.5, 0.6)
        }  # fmt: skip
    return out


def tables(results: list[dict], quick: bool, command: str) -> str:
    lines = [
        "# Skeleton matching on synthetic data" + (" (QUICK tier)" if quick else ""),
        "",
        f"Command: `{command}`. Device: {jax.devices()[0].device_kind} ({jax.devices()[0].platform}).",
        "Test: held-out multi-person recordings with 1-8 people, detector model on; scores pooled over "
        "every detection (false positives and unassigned detections are singletons).",
        "",
        "| setup | cameras | method | ARI | H | C | Vm | paper ARI | train s | ms/frame |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for m in ("gat", "geometric"):
            s = r[m]
            lines.append(
                f"| {r['setup']} | {len(r['cameras'])} | {m} | {s['ari']:.4f} | {s['homogeneity']:.4f} | "
                f"{s['completeness']:.4f} | {s['v_measure']:.4f} | {r['paper_ari'] if m == 'gat' else ''} | "
                f"{r['train_seconds'] if m == 'gat' else ''} | {s['ms_per_frame']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small data and network (minutes)")
    parser.add_argument("--out", default="results/matching")
    parser.add_argument("--only", nargs="*", choices=sorted(SETUPS), help="run only these setups")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    sc = scale(args.quick)
    out = Path(args.out)
    command = "python -m experiments.matching" + (" --quick" if args.quick else "") + (
        f" --only {' '.join(args.only)}" if args.only else "")  # fmt: skip
    results = []
    previous = out / "metrics.json"
    if args.only and previous.exists():  # keep the other setups of an earlier run
        results = [r for r in json.loads(previous.read_text())["results"] if r["setup"] not in args.only]
    for name in args.only or SETUPS:
        print(f"== {name}", flush=True)
        r = run_setup(name, sc, args.seed, not args.no_progress, args.quick)
        print(json.dumps({k: r[k] for k in ("setup", "train_seconds", "gat", "geometric")}), flush=True)
        results.append(r)
        results.sort(key=lambda r: list(SETUPS).index(r["setup"]))
        atomic_write_text(out / "metrics.json", json.dumps(
            {"quick": args.quick, "command": command, "scale": _jsonable(dataclasses.asdict(sc)),
             "results": results}, indent=1))  # fmt: skip
        atomic_write_text(out / "tables.md", tables(results, args.quick, command))
    print(tables(results, args.quick, command))
    return 0


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return v


if __name__ == "__main__":
    raise SystemExit(main())
