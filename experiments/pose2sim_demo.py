"""Pose2Sim's demo session without labels: ``python -m experiments.pose2sim_demo --out DIR``.

Evaluation only (nothing is tuned on it): Pose2Sim's demo session (`../shared/real/
pose2sim-demo-s00`, 4 cameras, OpenPose BODY_25B, 60 fps, no 3D ground truth), processed by our
pipelines without models and by Pose2Sim itself, every result scored by the label-free score
(`label_free.label_free_score`) against the same detections: the RAW ones, ``pose/``.

Rows of the two-person trial (``S00_P01_T02_Participants1-2``):

* ours, through the library job ``infer --session`` runs (`jobs.session.trial_config` ->
  `jobs.infer.run_infer`: tracked, Butterworth-filtered): the geometric default (epipolar
  grouping + robust triangulation, ``--method robust``) and epipolar + DLT (``--method dlt``),
  each on the raw detections ``pose/`` (the fair input for a matcher: ``pose-associated/`` is
  Pose2Sim's own person association) and on ``pose-associated/``;
* Pose2Sim's own ``pose-3d/*.trc``, raw and Butterworth-filtered (not the LSTM-augmented ones),
  one person per TRC file (`read_trc`, `pose2sim_people`), as a peer row.

A result that was not made from ``pose/`` (Pose2Sim's, ours on ``pose-associated/``) says nothing
about which of ``pose/``'s skeletons are whose: its identity is made by `assign_identity` (per
frame and camera, Hungarian assignment of the skeletons to the projected people on the mean pixel
distance over the keypoints both have, gated at `GATE_PX` with at least `MIN_SHARED` keypoints).
Ours on ``pose/`` keep their own grouping.

Pose2Sim's TRC files hold BODY_25B markers without the eyes and ears, in metres (the ``Units``
field) in axes Y up: `TRC_TO_COCO18` maps them to our coco18 keypoints by name; coco18's ``neck``
is the mean of the shoulders (as our reader builds it from the detections; Pose2Sim's ``Neck`` is
BODY_25B's upper neck below the chin, another point), and its eyes and ears are missing (misses in
the score: the rows on the 14 keypoints every row has are in a second table). The TRC's axes are
rotated back to the calibration's world by the one of the 24 axis rotations that reprojects best
(`trc_axes`; reported).

With models (`run`'s ``models``; `experiments.real` trains them with `demo_models`), the
`MODEL_ROWS` of the two-person trial on ``pose/``: the ``infer`` default (combined + blend) and
the paper's GAT + MLP, with models trained on synthetic recordings of the rig (the floor and up
measured from the trial's people) and with models trained on the session's single-person trials
(`trial_recordings`, the paper's recipe on real data).

The single-person trials: our geometric default against Pose2Sim's filtered TRC.

Writes ``DIR/pose2sim_demo.md`` and ``DIR/pose2sim_demo.json`` (deterministic), and the wall time
of each of our rows to ``DIR/timings.json`` and ``DIR/pose2sim_demo_timed.md`` (the tables with a
seconds column). ``--smoke``: the first `SMOKE_FRAMES` frames of the two-person trial only.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

from experiments.records import report_json
from mvpose_jax.cameras import Rig, point_depths, project_points
from mvpose_jax.data import Recording, load_recording, slice_frames
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.pose2sim import Pose2SimTrial, find_trials
from mvpose_jax.data.poses import PoseResults, load_poses
from mvpose_jax.errors import InputError
from mvpose_jax.floor import estimate_floor_from_detections
from mvpose_jax.inference import PipelineConfig
from mvpose_jax.jobs.common import read_dev_quality
from mvpose_jax.jobs.infer import INFER_PIPELINE, run_infer
from mvpose_jax.jobs.score import summary_lines
from mvpose_jax.jobs.session import SessionConfig, trial_config
from mvpose_jax.label_free import LabelFreeReport, label_free_score
from mvpose_jax.lifting import LiftingConfig
from mvpose_jax.skeletons import Detections, Poses3D, get_layout

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "real" / "pose2sim-demo-s00"
MULTI_TRIAL = "S00_P01_T02_Participants1-2"
SPLIT = "Pose2Sim demo session, no labels: evaluation only"
LAYOUT = "coco18"
SMOKE_FRAMES = 6
# Identity of a result's people in a camera's skeletons: a skeleton goes to a projected person
# when their mean distance over shared keypoints is at most GATE_PX (about a head's width in
# these 1088x1920 images at 3-4 m) over at least MIN_SHARED keypoints.
GATE_PX = 50.0
MIN_SHARED = 3
# Pose2Sim's BODY_25B markers (TRC names) -> coco18 keypoints. Not mapped: Neck (the upper neck,
# not coco18's neck), Head (the head top), the feet; coco18's neck is built from the shoulders.
TRC_TO_COCO18 = {
    "Nose": "nose",
    "RShoulder": "r_shoulder",
    "LShoulder": "l_shoulder",
    "RElbow": "r_elbow",
    "LElbow": "l_elbow",
    "RWrist": "r_wrist",
    "LWrist": "l_wrist",
    "RHip": "r_hip",
    "LHip": "l_hip",
    "RKnee": "r_knee",
    "LKnee": "l_knee",
    "RAnkle": "r_ankle",
    "LAnkle": "l_ankle",
}
_DERIVED = {"neck": ("r_shoulder", "l_shoulder")}
_TRC_UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}
# (label, lifting method, detections folder) of our rows.
OUR_ROWS = (
    ("ours: geometric default (epipolar + robust), pose/", "robust", "pose"),
    ("ours: epipolar + DLT, pose/", "dlt", "pose"),
    ("ours: geometric default (epipolar + robust), pose-associated/", "robust", "pose-associated"),
    ("ours: epipolar + DLT, pose-associated/", "dlt", "pose-associated"),
)
PEER_ROWS = (("Pose2Sim, raw TRC", "raw"), ("Pose2Sim, Butterworth TRC", "filt_butterworth"))
# With models (`demo_models`; rows only when `run` is given them), on pose/: (label, which model
# pair, pipeline). "default": ``infer``'s with models (combined + blend); "paper": GAT + MLP.
MODEL_SOURCES = {
    "synthetic": "models from synthetic recordings of the rig",
    "trials": "models from the single-person trials",
    "mixed": "models from both, mixed",
    # Made by `experiments.detector_like` (not by `demo_models`): synthetic recordings whose
    # detector is fitted to the two-person trial's own detections.
    "detector-like": "models from synthetic recordings with a detector fitted to the trial",
}
MODEL_ROWS = tuple(
    (f"ours, {MODEL_SOURCES[source]}: {what}, pose/", source, pipeline)
    for source in MODEL_SOURCES
    for what, pipeline in (
        ("infer default (combined + blend)", "default"),
        ("paper's method (GAT + MLP)", "paper"),
    )
)
# The single-person trials as the models' training and dev recordings: the balancing trial's
# last BALANCE_DEV_FRAMES frames and participant 2's static trial are the dev recordings (two
# recordings, so that dev frames of two people can be composed).
BALANCE_TRIAL = "S00_P00_T01_BalancingTrial"
DEV_TRIAL = "S00_P01_T01_StaticTrialParticipant2"
BALANCE_DEV_FRAMES = 20


class Trc(NamedTuple):
    """One TRC file. N frames, M markers.

    names: M marker names; frame: (N,) Frame# (numbered from 1); time: (N,) seconds; xyz: (N, M,
    3) metres (converted from ``units``), the file's axes, NaN where a marker is absent;
    present: (N, M) bool; units: the header's ``Units``; rate: ``DataRate`` (frames per second).
    """

    names: tuple[str, ...]
    frame: np.ndarray
    time: np.ndarray
    xyz: np.ndarray
    present: np.ndarray
    units: str
    rate: float


def read_trc(path: str | Path) -> Trc:
    """Reads a TRC file (PathFileType 4: Pose2Sim's, OpenSim's and `data.exports.write_trc`'s).

    Empty or ``nan`` fields are absent markers; a row may end with a tab.

    Raises:
      InputError naming the file, the line and the field for a header or row that does not fit.
    """
    path = Path(path)
    lines = path.read_text().splitlines()
    if len(lines) < 5:
        raise InputError(f"{len(lines)} lines, a TRC header has 5", file=path)
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    header = dict(zip((k.strip() for k in keys), (v.strip() for v in values), strict=False))
    for key in ("DataRate", "NumMarkers", "Units"):
        if key not in header:
            raise InputError(f"no {key} in the header's second line", file=path, field=key)
    units = header["Units"]
    if units not in _TRC_UNITS:
        raise InputError(f"unknown units {units!r}", file=path, field="Units")
    M = int(header["NumMarkers"])
    names = tuple(n.strip() for n in lines[3].split("\t")[2:] if n.strip())
    if len(names) != M:
        raise InputError(
            f"{len(names)} marker names, NumMarkers says {M}", file=path, field="names"
        )
    frames, times, rows = [], [], []
    for number, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        fields = line.rstrip("\n").split("\t")
        values = fields[2 : 2 + 3 * M]
        # Absent last markers may be left out of a row; more values than markers is an error.
        if len(fields) < 2 or any(v.strip() for v in fields[2 + 3 * M :]):
            raise InputError(
                f"line {number}: {len(fields)} fields for {M} markers", file=path, field="row"
            )
        values += [""] * (3 * M - len(values))
        try:
            frames.append(int(float(fields[0])))
            times.append(float(fields[1]))
            rows.append([float(v) if v.strip() else math.nan for v in values])
        except ValueError as e:
            raise InputError(f"line {number}: {e}", file=path, field="row") from None
    xyz = np.asarray(rows, np.float64).reshape(-1, M, 3) * _TRC_UNITS[units]
    present = np.isfinite(xyz).all(-1)
    xyz[~present] = math.nan
    return Trc(
        names, np.asarray(frames), np.asarray(times), xyz, present, units, float(header["DataRate"])
    )


def trc_keypoints(trc: Trc, frames: int, layout: str = LAYOUT) -> tuple[np.ndarray, np.ndarray]:
    """One TRC person as ``layout``'s keypoints over the recording's first ``frames`` frames (row
    Frame# n is frame n - 1; `TRC_TO_COCO18` by name, the neck from the shoulders).

    Returns:
      xyz (frames, K, 3) in the TRC's axes, metres (0 where absent); present (frames, K) bool.
    """
    keypoints = get_layout(layout).keypoints
    xyz = np.zeros((frames, len(keypoints), 3))
    present = np.zeros((frames, len(keypoints)), bool)
    rows = trc.frame - 1
    keep = (rows >= 0) & (rows < frames)
    for marker, name in TRC_TO_COCO18.items():
        if marker in trc.names and name in keypoints:
            m, k = trc.names.index(marker), keypoints.index(name)
            xyz[rows[keep], k] = np.nan_to_num(trc.xyz[keep, m])
            present[rows[keep], k] = trc.present[keep, m]
    for name, (a, b) in _DERIVED.items():
        if name in keypoints:
            k, ia, ib = keypoints.index(name), keypoints.index(a), keypoints.index(b)
            present[:, k] = present[:, ia] & present[:, ib]
            xyz[:, k] = np.where(present[:, k, None], (xyz[:, ia] + xyz[:, ib]) / 2, 0.0)
    return xyz, present


def axis_rotations() -> list[np.ndarray]:
    """The 24 rotations that permute the axes and flip their signs (det +1)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            r[range(3), perm] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    return out


def trc_axes(
    xyz: np.ndarray, present: np.ndarray, rig: Rig, detections: Detections
) -> tuple[np.ndarray, float, float]:
    """The axis rotation ``p_world = R @ p_trc`` that puts the TRC people where the detections
    are: of `axis_rotations`, the least median over cameras and frames of each projected
    person's nearest skeleton (mean px over shared keypoints).

    Args:
      xyz: (F, G, K, 3) TRC axes; present: (F, G, K).
    Returns:
      (R, its median px, the second best rotation's median px).
    """
    scored = []
    for r in axis_rotations():
        dist = _pair_distances(xyz @ r.T, present, rig, detections)[0]  # (F, C, G, P)
        nearest = np.min(np.where(np.isfinite(dist), dist, np.inf), axis=-1)
        finite = nearest[np.isfinite(nearest)]
        scored.append((float(np.median(finite)) if finite.size else math.inf, r))
    scored.sort(key=lambda s: s[0])
    return scored[0][1], scored[0][0], scored[1][0]


def assign_identity(
    xyz: np.ndarray,
    present: np.ndarray,
    rig: Rig,
    detections: Detections,
    *,
    gate_px: float = GATE_PX,
    min_shared: int = MIN_SHARED,
) -> tuple[np.ndarray, np.ndarray]:
    """Which skeleton of each camera is which person of a 3D result made from other detections.

    Per frame and camera: the cost of person g and skeleton p is the mean pixel distance between
    g's projection (in front of the camera) and p's keypoints (score > 0) over the keypoints both
    have; pairs with fewer than ``min_shared`` such keypoints or a cost above ``gate_px`` are not
    allowed; the Hungarian assignment (`scipy.optimize.linear_sum_assignment`) of the rest.

    Args:
      xyz: (F, G, K, 3) world metres; present: (F, G, K) bool.
      rig: the cameras of ``detections``, in its camera order.
      detections: xy (F, C, P, K, 2), score (F, C, P, K), count (F, C).
    Returns:
      members (F, G, C): person g's skeleton in camera c, -1 none; identity (F, C, P): skeleton
      p's person, -1 none.
    """
    dist, _ = _pair_distances(xyz, present, rig, detections, min_shared)
    F, C, G, P = dist.shape
    members = np.full((F, G, C), -1, np.int32)
    identity = np.full((F, C, P), -1, np.int32)
    for f, c in itertools.product(range(F), range(C)):
        cost = np.where(np.isfinite(dist[f, c]) & (dist[f, c] <= gate_px), dist[f, c], np.inf)
        if not np.isfinite(cost).any():
            continue
        rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, 1e9))
        for g, p in zip(rows, cols, strict=True):
            if np.isfinite(cost[g, p]):
                members[f, g, c], identity[f, c, p] = p, g
    return members, identity


def pose_results(
    xyz: np.ndarray,
    present: np.ndarray,
    members: np.ndarray,
    identity: np.ndarray,
    cameras: Sequence[str],
    fps: float,
) -> PoseResults:
    """A result of G people tracked over F frames (person g is track g in every frame it has a
    keypoint), for the label-free score."""
    valid = present.any(-1)
    G = xyz.shape[1]
    return PoseResults(
        poses=Poses3D(xyz.astype(np.float32), valid, present & valid[..., None]),
        confidence=valid.astype(np.float32),
        members=np.where(valid[..., None], members, -1),
        identity=identity,
        cameras=tuple(cameras),
        layout=LAYOUT,
        timestamps=np.arange(len(xyz)) / fps,
        track=np.where(valid, np.arange(G)[None], -1),
    )


def pose2sim_people(
    trial_folder: Path, kind: str, frames: int, rig: Rig, detections: Detections
) -> tuple[PoseResults, dict]:
    """Pose2Sim's ``pose-3d`` of one kind ("raw" or "filt_butterworth"), one person per TRC file
    (sorted by name), axes found by `trc_axes`, identity by `assign_identity`.

    Returns:
      (the result on ``rig``'s cameras, {"files", "rotation", "median_px", "next_best_px",
      "units", "rate"}).
    """
    trcs = sorted((trial_folder / "pose-3d").glob("*.trc"))
    if kind == "raw":
        trcs = [p for p in trcs if "_filt_" not in p.name and "LSTM" not in p.name]
    else:
        trcs = [p for p in trcs if p.stem.endswith("_" + kind)]
    if not trcs:
        raise InputError(f"no {kind} TRC file", file=trial_folder / "pose-3d")
    read = [read_trc(p) for p in trcs]
    people = [trc_keypoints(t, frames) for t in read]
    xyz = np.stack([p[0] for p in people], axis=1)  # (F, G, K, 3) TRC axes
    present = np.stack([p[1] for p in people], axis=1)
    rotation, median_px, next_px = trc_axes(xyz, present, rig, detections)
    world = np.where(present[..., None], xyz @ rotation.T, 0.0)
    members, identity = assign_identity(world, present, rig, detections)
    info = {
        "files": [p.name for p in trcs],
        "rotation_world_from_trc": rotation.astype(int).tolist(),
        "axes_median_px": median_px,
        "axes_next_best_median_px": next_px,
        "units": sorted({t.units for t in read}),
        "rate": read[0].rate,
    }
    return pose_results(world, present, members, identity, rig.names, read[0].rate), info


def our_result(
    trial: Pose2SimTrial,
    method: str | None,
    out: Path,
    frames: int | None,
    *,
    models: Path | None = None,
    proposals: str | None = None,
    pipeline: PipelineConfig | None = None,
) -> tuple[PoseResults, float]:
    """Our pipeline on one trial as ``infer --session`` runs it, with ``--method`` (None: the
    job's default) and, with ``models`` (a folder of ``matcher/`` and ``estimator/``), ``--matcher
    --estimator`` and ``--proposals``; or, given ``pipeline``, that whole config (``method`` and
    ``proposals`` unused). Returns the poses and the job's wall time in seconds."""
    if pipeline is None:
        pipeline = dataclasses.replace(
            INFER_PIPELINE,
            matching=dataclasses.replace(INFER_PIPELINE.matching, proposals=proposals),
            lifting=LiftingConfig(method),
        )
    session = SessionConfig(
        str(trial.folder),
        str(out),
        pipeline,
        matcher=None if models is None else str(models / "matcher"),
        estimator=None if models is None else str(models / "estimator"),
        trc=False,
        progress=False,
    )
    config = trial_config(session, trial)
    if frames is not None:
        config = dataclasses.replace(config, frames=(0, frames))
    start = time.perf_counter()
    result = run_infer(config)
    seconds = time.perf_counter() - start
    return load_poses(result.written.npz), seconds


def raw_detections(trial: Pose2SimTrial, frames: int | None) -> tuple[Rig, Detections]:
    """The trial's calibration (its paired cameras, in order) and detections (coco18)."""
    session = SessionConfig(str(trial.folder), "unused", trc=False)
    source = trial_config(session, trial).detections
    rig = load_rig(str(trial.calibration), cameras=list(trial.cameras))
    recording = load_recording(source.path, layout=LAYOUT, rig=rig, **source.reading_options())
    stop = frames if frames is not None else None
    return rig, Detections(*(np.asarray(a)[:stop] for a in recording.detections))


def trial_recordings(data: Path) -> tuple[list[Recording], list[Recording]]:
    """The single-person trials as (training, dev) recordings (coco18, raw ``pose/``): dev is
    the balancing trial's last `BALANCE_DEV_FRAMES` frames and `DEV_TRIAL`, training the rest."""
    trials = {t.name: t for t in find_trials(data, pose_folders=("pose",)).trials}
    train, dev = [], []
    for name in sorted(trials):
        if name == MULTI_TRIAL:
            continue
        rig, det = raw_detections(trials[name], None)
        rec = Recording(det, tuple(rig.names), LAYOUT)
        if name == BALANCE_TRIAL:
            F = int(det.score.shape[0])
            train.append(slice_frames(rec, 0, F - BALANCE_DEV_FRAMES))
            dev.append(slice_frames(rec, F - BALANCE_DEV_FRAMES, F))
        else:
            (dev if name == DEV_TRIAL else train).append(rec)
    return train, dev


def demo_models(data: Path, folder: Path, smoke: bool) -> dict:
    """The three model pairs of the demo's rig, trained (or loaded from ``folder``): on synthetic
    recordings of the rig, the floor (and up) measured from the two-person trial's people
    (`real_models.synthetic_models`); on the single-person trials (`trial_recordings`,
    `real_models.trial_models`); on both mixed (`real_models.mixed_models`). Returns
    {`MODEL_SOURCES` key: (folder, training record)}; ``smoke``: the synthetic pair only, at
    smoke size."""
    from experiments.real_models import (
        mixed_models,
        synthetic_models,
        training_record,
        trial_models,
    )

    trial = {t.name: t for t in find_trials(data, pose_folders=("pose",)).trials}[MULTI_TRIAL]
    rig, detections = raw_detections(trial, None)
    floor = estimate_floor_from_detections(rig, detections, layout=LAYOUT)
    train, dev = trial_recordings(data)
    frames = {
        "train_frames": sum(r.num_frames for r in train),
        "dev_frames": sum(r.num_frames for r in dev),
    }
    models = {"synthetic": synthetic_models(rig, floor, folder / "synthetic", smoke=smoke)}
    # A smoke run (CI) trains the one pair: the other two differ only in their recordings
    # (`trial_recordings` is tested on its own), and each pair costs a training and two runs.
    if not smoke:
        models["trials"] = trial_models(rig, train, dev, folder / "trials", smoke=smoke)
        models["mixed"] = mixed_models(rig, floor, train, dev, folder / "mixed", smoke=smoke)
    out = {}
    for source, pair in models.items():
        record = training_record(pair, None if source == "trials" else floor)
        if source != "synthetic":
            record |= frames
        record["estimator_dev"] = read_dev_quality(str(folder / source / "estimator"))
        out[source] = (folder / source, record)
    return out


def reassigned(result: PoseResults, rig: Rig, detections: Detections) -> PoseResults:
    """``result`` with its identity in ``detections`` made by `assign_identity` (for results made
    from other detections)."""
    xyz = np.asarray(result.poses.xyz, np.float64)
    present = np.asarray(result.poses.keypoint_valid, bool)
    members, identity = assign_identity(xyz, present, rig.select(result.cameras), detections)
    return dataclasses.replace(result, members=members, identity=identity)


def shared_keypoints_only(detections: Detections, keypoints: Sequence[str]) -> Detections:
    """The detections with every keypoint outside ``keypoints`` unseen (score 0)."""
    names = get_layout(LAYOUT).keypoints
    keep = np.array([n in keypoints for n in names])
    return detections._replace(score=np.where(keep, np.asarray(detections.score), 0.0))


def score_row(result: PoseResults, rig: Rig, detections: Detections) -> dict:
    """The label-free score's numbers of one result (`summary_lines`' and a few more)."""
    report = label_free_score(result, rig, detections, layout=LAYOUT)
    return _numbers(report)


def run(
    data: Path,
    smoke: bool = False,
    work: Path | None = None,
    models: Mapping[str, Path] | None = None,
) -> dict:
    """Every row (module docstring), and with ``models`` ({`MODEL_SOURCES` key: folder of
    ``matcher/`` and ``estimator/``}) the `MODEL_ROWS` of those; returns the report (JSON-able)."""
    frames = SMOKE_FRAMES if smoke else None
    raw = {t.name: t for t in find_trials(data, pose_folders=("pose",)).trials}
    associated = {t.name: t for t in find_trials(data, pose_folders=("pose-associated",)).trials}
    if MULTI_TRIAL not in raw:
        raise InputError(f"no trial {MULTI_TRIAL}", file=data)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(work or tmp)
        multi = _trial_rows(
            raw[MULTI_TRIAL], associated[MULTI_TRIAL], frames, work, smoke, models or {}
        )
        singles = []
        if not smoke:
            for name in sorted(raw):
                if name != MULTI_TRIAL:
                    singles.append(_single_trial(raw[name], work))
    return {
        "split": SPLIT,
        "data": "pose2sim-demo-s00 (Pose2Sim's S00_Demo_Session, commit a948c205)",
        "smoke": smoke,
        "detections_scored_against": "pose/ (the raw OpenPose detections), coco18",
        "identity": (
            f"results not made from pose/: per frame and camera, Hungarian assignment of the "
            f"skeletons to the projected people on the mean px distance over shared keypoints "
            f"(score > 0), gate {GATE_PX:g} px, at least {MIN_SHARED} shared keypoints"
        ),
        "trc_mapping": {
            **TRC_TO_COCO18,
            "neck": "mean of RShoulder and LShoulder (Pose2Sim's Neck is the upper neck)",
            "l_eye, r_eye, l_ear, r_ear": "not in Pose2Sim's TRC: misses",
        },
        "multi_person": multi,
        "single_person": singles,
    }


def _trial_rows(
    trial: Pose2SimTrial,
    trial_associated: Pose2SimTrial,
    frames,
    work: Path,
    smoke: bool,
    models: Mapping[str, Path],
) -> dict:
    rig, detections = raw_detections(trial, frames)
    F = int(detections.score.shape[0])
    results, seconds = {}, {}
    for label, method, folder in OUR_ROWS:
        source = trial if folder == "pose" else trial_associated
        out = work / f"{trial.name}_{method}_{folder}"
        result, seconds[label] = our_result(source, method, out, frames)
        if folder != "pose":
            result = reassigned(result, rig, detections)
        results[label] = result
    for label, source, pipeline in MODEL_ROWS:
        if source in models:
            out = work / f"{trial.name}_{source}_{pipeline}"
            proposals, method = ("gat", "mlp") if pipeline == "paper" else (None, None)
            results[label], seconds[label] = our_result(
                trial, method, out, frames, models=models[source], proposals=proposals
            )
    axes = {}
    for label, kind in PEER_ROWS:
        results[label], axes[label] = pose2sim_people(trial.folder, kind, F, rig, detections)
    # The keypoints every row can have: coco18 less the eyes and ears Pose2Sim's TRC lacks.
    common = [k for k in get_layout(LAYOUT).keypoints if k in TRC_TO_COCO18.values()] + ["neck"]
    common_detections = shared_keypoints_only(detections, common)
    rows, lines = [], {}
    for label, result in results.items():
        report = label_free_score(result, rig, detections, layout=LAYOUT)
        lines[label] = summary_lines(report)
        row = {
            "row": label,
            "seconds": seconds.get(label),
            "all_keypoints": _numbers(report),
            "common_keypoints": score_row(result, rig, common_detections),
        }
        rows.append(row)
    return {
        "trial": trial.name,
        "frames": F,
        "cameras": list(rig.names),
        "common_keypoints": common,
        "pose2sim_trc": axes,
        "rows": rows,
        "summary_lines": lines,
    }


def _single_trial(trial: Pose2SimTrial, work: Path) -> dict:
    rig, detections = raw_detections(trial, None)
    F = int(detections.score.shape[0])
    label = OUR_ROWS[0][0]
    ours, seconds = our_result(trial, "robust", work / f"{trial.name}_robust", None)
    peer, axes = pose2sim_people(trial.folder, "filt_butterworth", F, rig, detections)
    return {
        "trial": trial.name,
        "frames": F,
        "pose2sim_trc": axes,
        "rows": [
            {"row": label, "seconds": seconds, "all_keypoints": score_row(ours, rig, detections)},
            {
                "row": PEER_ROWS[1][0],
                "seconds": None,
                "all_keypoints": score_row(peer, rig, detections),
            },
        ],
    }


def _numbers(report: LabelFreeReport) -> dict:
    r, loo = report.result.overall, report.leave_one_out.overall
    return {
        "within_20px_all_skeletons": report.share_of_all_within_px["20"],
        "within_10px_all_skeletons": report.share_of_all_within_px["10"],
        "coverage": r.coverage,
        "median_px": r.median_px,
        "loo_median_px": loo.median_px,
        "loo_within_20px": loo.share_within_px["20"],
        "loo_blind": loo.blind,
        "loo_visible": loo.visible,
        "bone_cv": report.bone_spread.median_cv if report.bone_spread else None,
        "bone_cv_by_track": report.bone_spread.by_track if report.bone_spread else None,
        "jitter_m_s2": report.jitter_m_s2,
        "people_per_frame": report.people_count.mean_result,
        "views_median_people": report.people_count.mean_median_of_views,
        "tracks": report.tracks.num_tracks if report.tracks else None,
        "short_tracks": report.tracks.short_tracks if report.tracks else None,
        "unmatched_skeletons": sum(report.unmatched_skeletons.values()),
    }


def _pair_distances(
    xyz: np.ndarray,
    present: np.ndarray,
    rig: Rig,
    detections: Detections,
    min_shared: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean pixel distance of every projected person to every skeleton of every camera.

    Args:
      xyz: (F, G, K, 3) world metres; present: (F, G, K).
    Returns:
      dist (F, C, G, P): mean over the keypoints both have (the person's, in front of the
      camera; the skeleton's, score > 0), NaN with fewer than ``min_shared`` of them or for a
      padding skeleton; shared (F, C, G, P) their count.
    """
    xy = np.asarray(detections.xy, np.float64)  # (F, C, P, K, 2)
    score = np.asarray(detections.score)
    count = np.asarray(detections.count)  # (F, C)
    P = xy.shape[2]
    proj = np.asarray(project_points(rig, xyz), np.float64)  # (C, F, G, K, 2)
    front = np.asarray(point_depths(rig, xyz)) > 0  # (C, F, G, K)
    proj = np.moveaxis(proj, 0, 1)  # (F, C, G, K, 2)
    have = np.moveaxis(front, 0, 1) & present[:, None]  # (F, C, G, K)
    seen = (score > 0) & (
        np.arange(P)[None, None, :, None] < count[..., None, None]
    )  # (F, C, P, K)
    both = have[:, :, :, None] & seen[:, :, None]  # (F, C, G, P, K)
    gap = np.linalg.norm(proj[:, :, :, None] - xy[:, :, None], axis=-1)  # (F, C, G, P, K)
    shared = both.sum(-1)
    total = np.where(both, gap, 0.0).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        dist = np.where(shared >= max(min_shared, 1), total / shared, np.nan)
    return dist, shared


_COLUMNS = (
    ("within 20 px (all skeletons)", "within_20px_all_skeletons", "pct"),
    ("coverage", "coverage", "pct"),
    ("median px", "median_px", "num"),
    ("leave-one-out median px", "loo_median_px", "num"),
    ("leave-one-out within 20 px", "loo_within_20px", "pct"),
    ("bone-length CV per track", "bone_cv", "pct"),
    ("jitter m/s²", "jitter_m_s2", "num"),
    ("people / frame", "people_per_frame", "num"),
    ("tracks (short)", None, "tracks"),
)


def markdown(report: dict, timings: dict | None = None, level: int = 1) -> str:
    """The report as Markdown tables (``timings``: {row: seconds} adds a column; ``level``: the
    title's heading level, the sections one below)."""
    multi = report["multi_person"]
    h = "#" * level
    lines = [
        f"{h} Pose2Sim's demo session, processed by Pose2Sim and by us, scored without labels",
        "",
        f"Split: **{report['split']}**. Data: {report['data']}."
        + (" SMOKE RUN: a few frames only." if report["smoke"] else ""),
        "",
        f"Every row is scored by `label_free.label_free_score` against the same detections: "
        f"{report['detections_scored_against']}. Identity of {report['identity']}.",
        "",
        f"{h}# {multi['trial']} (two people, {multi['frames']} frames, "
        f"{len(multi['cameras'])} cameras)",
        "",
        "All 18 coco18 keypoints (Pose2Sim's TRC has no eyes or ears: they count as misses):",
        "",
        *_table(multi["rows"], "all_keypoints", timings),
        "",
        f"The {len(multi['common_keypoints'])} keypoints every row has "
        f"({', '.join(multi['common_keypoints'])}; the detections' eyes and ears left out):",
        "",
        *_table(multi["rows"], "common_keypoints", None),
        "",
        "Pose2Sim's TRC axes, found by reprojection among the 24 axis rotations "
        "(`p_world = R @ p_trc`):",
        "",
    ]
    for label, info in multi["pose2sim_trc"].items():
        lines.append(
            f"- {label}: {', '.join(info['files'])}; units {', '.join(info['units'])}; "
            f"R = {info['rotation_world_from_trc']} (median {info['axes_median_px']:.1f} px, the "
            f"next best rotation {info['axes_next_best_median_px']:.1f} px)"
        )
    lines += _models_markdown(report.get("models") or {}, h)
    if report["single_person"]:
        lines += ["", f"{h}# Single-person trials (all 18 keypoints)", ""]
        for trial in report["single_person"]:
            lines += [f"{h}## {trial['trial']} ({trial['frames']} frames)", ""]
            lines += [
                *_table(trial["rows"], "all_keypoints", timings and timings.get(trial["trial"])),
                "",
            ]
    lines += [
        "",
        f"{h}# How to read it",
        "",
        "- *within 20 px (all skeletons)*: the share of every visible keypoint of every skeleton "
        "of every camera (false positives included) that the result's projection puts within "
        "20 px: the same denominator for every row; read it first.",
        "- *coverage*: keypoints the cameras show of the result's people that the result "
        "produces; *median px*: over those produced.",
        "- *leave-one-out*: each person re-triangulated from the other cameras' skeletons the "
        "identity gives it, projected into the left-out camera: the grouping's reference, not "
        "the 3D method's.",
        "- No ground truth, so no noise floor of its own: the score measures agreement with "
        "OpenPose. On a real recording with ground truth (issue 36) the truth itself reprojected "
        "12.6 px (median) from OpenPose's detections: medians of 9-13 px are at that floor, and a "
        "difference of a px or two between rows does not show better 3D. Rows differ in what "
        "they are above it: people reconstructed (a person left out leaves its skeletons outside "
        "the 20 px share), keypoints produced (coverage), jitter and bone-length spread.",
    ]
    return "\n".join(lines) + "\n"


def _models_markdown(models: dict, h: str) -> list[str]:
    """How the model rows' models were trained (`demo_models`' records)."""
    if not models:
        return []
    lines = ["", f"{h}# The models of the rows with models", ""]
    for source, r in models.items():
        text = (
            f"- {MODEL_SOURCES[source]}: matcher {r['matcher_steps']} steps, GAT threshold "
            f"{r['gat_threshold']}, combined threshold {r['combined_threshold']} (best ARI on "
            f"frames composed from the dev recordings: GAT {_num(r['composed_dev_ari_gat'])}, "
            f"combined {_num(r['composed_dev_ari_combined'])})"
        )
        if "floor" in r:
            f = r["floor"]
            text += (
                f"; training floor {f['height']:.3f} m along up, measured from the "
                f"{MULTI_TRIAL} people ({f['basis']}, spread {f['spread']:.3f} m over "
                f"{f['num_samples']} person-frames)"
            )
        if "train_frames" in r:
            text += f"; {r['train_frames']} real training frames, {r['dev_frames']} real dev frames"
        dev = r.get("estimator_dev") or {}
        if dev:
            text += (
                f"; estimator on its dev people {dev['estimator_px']} px per keypoint, "
                f"triangulation {dev['triangulation_px']} px"
            )
        lines.append(text + ".")
    return lines


def _table(rows: list[dict], which: str, timings: dict | None) -> list[str]:
    head = ["result", *(c[0] for c in _COLUMNS)] + (["seconds"] if timings else [])
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        n = row[which]
        cells = [row["row"]]
        for _, key, kind in _COLUMNS:
            if kind == "tracks":
                cells.append("-" if n["tracks"] is None else f"{n['tracks']} ({n['short_tracks']})")
            elif kind == "pct":
                cells.append(_pct(n[key]))
            else:
                cells.append(_num(n[key]))
        if timings:
            t = timings.get(row["row"])
            cells.append("-" if t is None else f"{t:.1f}")
        out.append("| " + " | ".join(cells) + " |")
    return out


def _pct(v) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{100 * v:.1f} %"


def _num(v) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.2f}"


def timings_of(report: dict) -> dict:
    """{row: seconds} of the two-person trial, and {trial: {row: seconds}} of the others."""
    out = {r["row"]: r["seconds"] for r in report["multi_person"]["rows"]}
    for trial in report["single_person"]:
        out[trial["trial"]] = {r["row"]: r["seconds"] for r in trial["rows"]}
    return out


def without_timings(value):
    if isinstance(value, dict):
        return {k: without_timings(v) for k, v in value.items() if k != "seconds"}
    if isinstance(value, list):
        return [without_timings(v) for v in value]
    return value


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="the demo session folder")
    parser.add_argument(
        "--smoke", action="store_true", help=f"{SMOKE_FRAMES} frames, two-person trial only"
    )
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = run(Path(args.data), smoke=args.smoke)
    timings = timings_of(report)
    clean = without_timings(report)
    # The tables and numbers are deterministic; the wall times go to their own file.
    atomic_write_text(out / "pose2sim_demo.json", report_json(clean))
    atomic_write_text(out / "pose2sim_demo.md", markdown(clean))
    atomic_write_text(out / "timings.json", json.dumps(timings, indent=1) + "\n")
    atomic_write_text(out / "pose2sim_demo_timed.md", markdown(clean, timings))
    print((out / "pose2sim_demo.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
