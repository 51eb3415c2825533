"""Simulated detectors that behave like the real recordings' detectors, for training on many rigs.

``default`` is the simulator's own detector (`synthetic.DetectorConfig()`); ``mvor`` and
``pose2sim-demo`` are the detectors fitted without a label (`detector_fit.fit_detector`) to the
detections of ``../shared/real/``'s labelled MVOR days and of the Pose2Sim demo's two-person
trial (`experiments.detector_fit.fit_real_recording`, the fits `experiments.detector_fit` and
`experiments.detector_like` report). A fitted `DetectorConfig` holds rates, per-keypoint noise
relative to the person's image height, score laws and a border margin relative to the image:
nothing tied to the recording's cameras, so it can drive the synthetic recordings of any rig
(the pretraining experiments draw rig ``i``'s recordings with detector ``i mod n``).
"""

from __future__ import annotations

from experiments.detector_fit import REAL_RECORDINGS, fit_real_recording
from mvpose_jax.synthetic import DetectorConfig

DETECTORS = ("default", *(key for key, _ in REAL_RECORDINGS))


def training_detectors(
    names: tuple[str, ...],
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
        fit = fit_real_recording(name)
        configs.append(fit.config)
        record[name] = {"fitted": True, **fit.to_dict()}
    return tuple(configs), record
