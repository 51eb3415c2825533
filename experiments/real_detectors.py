"""Simulated detectors that behave like the real recordings' detectors, for training on many rigs.

``default`` is the simulator's own detector (`synthetic.DetectorConfig()`); ``mvor`` and
``pose2sim-demo`` are the detectors fitted without a label (`detector_fit.fit_detector`) to the
detections of ``../shared/real/``'s labelled MVOR days and of the Pose2Sim demo's two-person
trial (the fits `experiments.detector_like` reports). A fitted `DetectorConfig` holds rates,
per-keypoint noise relative to the person's image height, score laws and a border margin relative
to the image: nothing tied to the recording's cameras, so it can drive the synthetic recordings
of any rig (the pretraining experiments draw rig ``i``'s recordings with detector ``i mod n``).
"""

from __future__ import annotations

from pathlib import Path

from experiments import pose2sim_demo as demo
from experiments.mvor import DEFAULT_ROOT, load_mvor
from mvpose_jax.data.pose2sim import find_trials
from mvpose_jax.detector_fit import DetectorFit, fit_detector
from mvpose_jax.synthetic import DetectorConfig

DETECTORS = ("default", "mvor", "pose2sim-demo")


def fit_real_detector(
    name: str, *, mvor_root: str | Path = DEFAULT_ROOT, pose2sim: str | Path = demo.DEFAULT_DATA
) -> DetectorFit:
    """The detector fitted to real recording ``name`` (``mvor`` or ``pose2sim-demo``)."""
    if name == "mvor":
        data = load_mvor(mvor_root)
        return fit_detector(data.rig, data.detections, layout=data.layout)
    if name == "pose2sim-demo":
        trials = {t.name: t for t in find_trials(Path(pose2sim), pose_folders=("pose",)).trials}
        rig, detections = demo.raw_detections(trials[demo.MULTI_TRIAL], None)
        return fit_detector(rig, detections, layout=demo.LAYOUT)
    raise ValueError(f"no real recording {name!r} to fit a detector to (of {DETECTORS[1:]})")


def training_detectors(
    names: tuple[str, ...], **paths
) -> tuple[tuple[DetectorConfig, ...], dict[str, dict]]:
    """The detectors ``names`` (of `DETECTORS`), in order, and a record of each: the fitted
    fields (`DetectorFit.to_dict`), or ``{"fitted": False}`` for ``default``."""
    if not names or len(set(names)) != len(names):
        raise ValueError(f"name each detector once, of {DETECTORS}: {names}")
    configs, record = [], {}
    for name in names:
        if name == "default":
            configs.append(DetectorConfig())
            record[name] = {"fitted": False}
            continue
        fit = fit_real_detector(name, **paths)
        configs.append(fit.config)
        record[name] = {"fitted": True, **fit.to_dict()}
    return tuple(configs), record
