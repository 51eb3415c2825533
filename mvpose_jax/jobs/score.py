"""The ``score`` job: the label-free score of any pose result (`label_free.label_free_score`)
against the detections it was made from, written as a JSON report and a figure.

`run_score(ScoreConfig) -> (LabelFreeReport, (json path, png path))` is what ``mvpose-jax score``
runs; `summary_lines` is the handful of numbers a person reads first.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from mvpose_jax.data.poses import PoseResults
from mvpose_jax.errors import InputError
from mvpose_jax.jobs.common import DetectionsSource, RigSource, detections_of, poses_on_rig
from mvpose_jax.label_free import (
    LabelFreeConfig,
    LabelFreeReport,
    label_free_score,
    reference_reprojection,
    write_label_free_report,
)
from mvpose_jax.skeletons import Detections


@dataclasses.dataclass(frozen=True)
class ScoreConfig:
    """One ``score`` run.

    Attributes:
      poses: ``poses.npz`` / ``poses.json`` (or their folder), as ``infer`` writes them.
      rig: the calibration.
      detections: the detections the poses were made from (read on the poses' cameras, in the
        poses' layout).
      out: a ``.json`` file (the figure beside it, ``.png``) or a folder (``label_free.json``
        and ``label_free.png`` in it).
      label_free: the score's settings.
      noise_floor: when the recording holds 3D ground truth and each skeleton's person (a
        synthetic recording), state the detections' spread around it with the report
        (`label_free.reference_reprojection`).
    """

    poses: str
    rig: RigSource
    detections: DetectionsSource
    out: str
    label_free: LabelFreeConfig = LabelFreeConfig()
    noise_floor: bool = True


def run_score(config: ScoreConfig) -> tuple[LabelFreeReport, tuple[Path, Path]]:
    """Scores the poses against their detections; writes the report and its figure atomically.

    Partial results (an interrupted ``infer``, `PoseResults.frames_total`) are scored on the
    frames they cover.

    Returns:
      (the report, (JSON path, PNG path)).
    Raises:
      InputError: poses whose cameras are not in the calibration, detections that lack one of
        them, or detections that do not fit the poses (frame count, keypoints, or a skeleton
        the poses use that the detections do not have), naming file, frame, camera and field.
    """
    poses, rig_all = poses_on_rig(config.poses, config.rig)
    recording = detections_of(poses, rig_all, config.detections)
    frames = _checked_frames(poses, recording.detections, config)
    detections = Detections(*(np.asarray(a)[:frames] for a in recording.detections))
    _check_skeletons(poses, detections, config.detections.path)
    floor = None
    truth = recording.ground_truth
    if config.noise_floor and truth is not None and recording.identity is not None:
        floor = reference_reprojection(
            np.asarray(truth.xyz)[:frames],
            (np.asarray(truth.keypoint_valid) & np.asarray(truth.valid)[..., None])[:frames],
            rig_all,
            detections,
            np.asarray(recording.identity)[:frames],
            cameras=poses.cameras,
            layout=poses.layout,
            config=config.label_free,
        )
    try:
        report = label_free_score(
            poses,
            rig_all,
            detections,
            layout=poses.layout,
            config=config.label_free,
            noise_floor=floor,
        )
    except InputError as e:
        raise e.at(file=config.detections.path) from None
    return report, write_label_free_report(report, config.out)


def summary_lines(report: LabelFreeReport) -> list[str]:
    """The few numbers a person reads first, one line each (what follows the colon is the
    number and its unit; "-" where there is none)."""
    radius = _key(max(report.config.thresholds_px))
    r, loo = report.result.overall, report.leave_one_out.overall
    lines = [
        f"frames: {report.frames}, cameras: {', '.join(report.cameras)}, layout: {report.layout}",
        f"skeletons' keypoints within {radius} px (all skeletons; read this first): "
        f"{_pct(report.share_of_all_within_px[radius])}",
        f"coverage (keypoints the cameras show of the result's people that it produces): "
        f"{_pct(r.coverage)}",
        f"median reprojection (result vs its people's skeletons): {_px(r.median_px)}",
        f"leave-one-camera-out median (the grouping's reference): {_px(loo.median_px)}, "
        f"within {radius} px {_pct(loo.share_within_px[radius])}, "
        f"{loo.blind} of {loo.visible} keypoints without a held-out check",
    ]
    if report.bone_spread is not None:
        lines.append(
            f"bone-length spread per track (median CV): {_pct(report.bone_spread.median_cv)}"
        )
        lines.append(f"jitter (mean acceleration): {_num(report.jitter_m_s2, 'm/s²')}")
    else:
        lines.append("bone-length spread, jitter, track fragments: - (not tracked)")
    pc = report.people_count
    lines.append(
        f"people per frame: {_num(pc.mean_result)} vs the views' median {_num(pc.mean_median_of_views)}"
        f" (mean |difference| {_num(pc.mean_abs_diff_median)})"
    )
    if report.tracks is not None:
        t = report.tracks
        lines.append(
            f"tracks: {t.num_tracks}, {t.short_tracks} shorter than {t.short_track_frames} frames"
        )
    unmatched = sum(report.unmatched_skeletons.values())
    lines.append(f"skeletons in no person of the result: {unmatched}")
    if report.noise_floor is not None:
        nf = report.noise_floor.overall
        lines.append(
            f"noise floor (detections vs the reference): median {_px(nf.median_px)}, within "
            f"{radius} px {_pct(nf.share_within_px[radius])}; differences below it are the "
            "detector's, not the result's"
        )
    else:
        lines.append("noise floor: unknown (no reference such as a ground truth)")
    lines.append(
        "blind: a keypoint fewer than two other views show has no held-out check; a person or "
        "keypoint no camera detected is invisible to this score"
    )
    return lines


# ------------------------------------------------------------------------------- internals


def _checked_frames(poses: PoseResults, detections: Detections, config: ScoreConfig) -> int:
    """The frames to score: the poses' (the detections may have more only when the poses are
    partial results of them)."""
    frames = int(np.shape(poses.poses.valid)[0])
    have = int(np.shape(detections.score)[0])
    expected = poses.frames_total if poses.frames_total is not None else frames
    if have != expected:
        what = "partial results of" if poses.frames_total is not None else "results of"
        raise InputError(
            f"{have} frames, but the poses ({config.poses}) are {what} {expected} frames: "
            "not the detections they were made from",
            file=config.detections.path,
            field="frames",
        )
    return frames


def _check_skeletons(poses: PoseResults, detections: Detections, file: str) -> None:
    """Every skeleton a person of the poses holds exists in the detections."""
    members = np.asarray(poses.members)
    exists = np.asarray(poses.poses.valid, bool)[..., None] & (members >= 0)  # (F, G, C)
    count = np.asarray(detections.count)  # (F, C)
    over = exists & (members >= count[:, None, :])
    if over.any():
        f, g, c = np.argwhere(over)[0]
        raise InputError(
            f"person {g} of the poses uses skeleton {members[f, g, c]}, the detections have "
            f"{count[f, c]} skeletons there: not the detections the poses were made from",
            file=file,
            frame=int(f),
            camera=poses.cameras[c],
            field="skeletons",
        )


def _key(radius: float) -> str:
    return f"{radius:g}"


def _pct(v: float) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{100 * v:.1f} %"


def _px(v: float) -> str:
    return _num(v, "px")


def _num(v: float | None, unit: str = "") -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.2f} {unit}".rstrip()
