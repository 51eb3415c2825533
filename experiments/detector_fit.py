"""The simulated detector fitted to real recordings, beside today's defaults, and its check.

``python -m experiments.detector_fit --out DIR`` writes ``DIR/detector_fit.md`` and
``DIR/detector_fit.json``:

* the `synthetic.DetectorConfig` that `detector_fit.fit_detector` fits, without labels, to
  `../shared/real/`'s multi-person recordings (MVOR days 1-2, its three cameras' OpenPose
  detections; the Pose2Sim demo's two-person trial, its raw ``pose/`` detections), beside
  `DetectorConfig()`'s defaults;
* the synthetic check: a recording simulated on panoptic5 with a known detector
  (`SYNTHETIC_TRUTH`), the fitted value of each field beside the truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text, to_jsonable
from mvpose_jax.data.pose2sim import find_trials
from mvpose_jax.detector_fit import FIT_FRAMES, DetectorFit, fit_detector
from mvpose_jax.synthetic import DetectorConfig, SyntheticConfig, generate_recording

# The detector of the synthetic check: the brief's rates, limb mixing and a Beta score model
# (occluded keypoints' scores not lowered, so that the Beta is the whole score distribution).
SYNTHETIC_TRUTH = DetectorConfig(
    noise_relative=0.01,
    swap_rate=0.1,
    false_positive_rate=0.3,
    keypoint_drop_rate=0.1,
    miss_rate=0.05,
    limb_mix_rate=0.1,
    score_beta=(5.0, 2.0),
    occluded_score_factor=1.0,
)
SYNTHETIC_PEOPLE, SYNTHETIC_FRAMES, SYNTHETIC_SEED = 4, 300, 3
# The fields of the tables (keypoint_noise_scale is in the JSON).
TABLE_FIELDS = (
    "noise_relative",
    "swap_rate",
    "keypoint_drop_rate",
    "occluded_drop_rate",
    "miss_rate",
    "false_positive_rate",
    "limb_mix_rate",
    "border_margin",
    "score_beta",
    "score_max",
    "noise_tail_dof",
)


# The real recordings a detector is fitted to: (key, label).
REAL_RECORDINGS = (("mvor", "MVOR days 1-2"), ("pose2sim-demo", "Pose2Sim demo, 2 people"))


def fit_real_recording(name: str, max_frames: int = FIT_FRAMES) -> DetectorFit:
    """The detector fitted to real recording ``name`` (a `REAL_RECORDINGS` key): MVOR days 1-2,
    or the Pose2Sim demo's two-person trial."""
    from experiments.mvor import load_mvor
    from experiments.pose2sim_demo import DEFAULT_DATA, LAYOUT, MULTI_TRIAL, raw_detections

    if name == "mvor":
        mvor = load_mvor()
        return fit_detector(mvor.rig, mvor.detections, layout=mvor.layout, max_frames=max_frames)
    if name == "pose2sim-demo":
        trials = {t.name: t for t in find_trials(DEFAULT_DATA, pose_folders=("pose",)).trials}
        rig, det = raw_detections(trials[MULTI_TRIAL], None)
        return fit_detector(rig, det, layout=LAYOUT, max_frames=max_frames)
    keys = [k for k, _ in REAL_RECORDINGS]
    raise ValueError(f"no real recording {name!r} to fit a detector to (of {keys})")


def fit_real(max_frames: int) -> dict[str, DetectorFit]:
    """The detector fitted to each of `REAL_RECORDINGS`, by label."""
    return {label: fit_real_recording(key, max_frames) for key, label in REAL_RECORDINGS}


def synthetic_check(
    frames: int = SYNTHETIC_FRAMES, seed: int = SYNTHETIC_SEED
) -> tuple[DetectorConfig, DetectorFit]:
    """(truth, fit) on a panoptic5 recording simulated with `SYNTHETIC_TRUTH`."""
    rig = load_rig("panoptic5")
    rec = generate_recording(
        rig,
        num_people=SYNTHETIC_PEOPLE,
        num_frames=frames,
        config=SyntheticConfig(detector=SYNTHETIC_TRUTH),
        seed=seed,
    )
    return SYNTHETIC_TRUTH, fit_detector(rig, rec.detections, layout=rec.layout)


def _cell(fit: DetectorFit, name: str) -> str:
    f = fit.field(name)
    return f"{_value(f.value)} ({f.samples})" if f.fitted else f"{_value(f.value)} (not fitted)"


def _value(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, tuple):
        return "(" + ", ".join(f"{x:.3g}" for x in value) + ")"
    return f"{value:.4g}"


def tables(fits: dict[str, DetectorFit], truth: DetectorConfig, check: DetectorFit) -> list[str]:
    """The two markdown tables: real recordings beside the defaults; recovered beside true."""
    defaults = DetectorConfig()
    names = list(fits)
    lines = [
        "## The detector fitted to real recordings",
        "",
        "Fitted value (samples behind it); `mvpose_jax.detector_fit` says how each is measured.",
        "",
        "| field | default | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for name in TABLE_FIELDS:
        cells = [_cell(fits[n], name) for n in names]
        lines.append(f"| {name} | {_value(getattr(defaults, name))} | " + " | ".join(cells) + " |")
    lines.append(
        "| person-frames (frames) | | "
        + " | ".join(f"{f.num_people} ({f.num_frames})" for f in fits.values())
        + " |"
    )
    lines += [
        "",
        f"## Synthetic check (panoptic5, {SYNTHETIC_PEOPLE} people, {SYNTHETIC_FRAMES} frames, "
        f"seed {SYNTHETIC_SEED})",
        "",
        "| field | true | recovered | default |",
        "|---|---|---|---|",
    ]
    for name in TABLE_FIELDS:
        lines.append(
            f"| {name} | {_value(getattr(truth, name))} | {_cell(check, name)} | "
            f"{_value(getattr(defaults, name))} |"
        )
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--frames", type=int, default=2000, help="most frames fitted per recording")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.time()
    fits = fit_real(args.frames)
    truth, check = synthetic_check()
    lines = tables(fits, truth, check)
    lines += ["", f"({time.time() - start:.0f} s; `python -m experiments.detector_fit --out DIR`)"]
    atomic_write_text(out / "detector_fit.md", "\n".join(lines) + "\n")
    record = {
        "real": {name: fit.to_dict() for name, fit in fits.items()},
        "synthetic": {"truth": dataclasses.asdict(truth), "fit": check.to_dict()},
        "defaults": dataclasses.asdict(DetectorConfig()),
    }
    atomic_write_text(out / "detector_fit.json", _json(record))
    print("\n".join(lines))
    return 0


def _json(record) -> str:
    import json

    return json.dumps(to_jsonable(record), indent=1)


if __name__ == "__main__":
    raise SystemExit(main())
