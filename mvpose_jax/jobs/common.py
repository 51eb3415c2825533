"""What several jobs share: where the cameras and the detections come from, how they are read,
how people are grouped, frame rates and the model folder's dev-quality file."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mvpose_jax.errors import InputError

if TYPE_CHECKING:
    from mvpose_jax.cameras import Rig
    from mvpose_jax.data.poses import PoseResults
    from mvpose_jax.data.recording import Recording
    from mvpose_jax.detector_fit import DetectorFit
    from mvpose_jax.floor import FloorEstimate
    from mvpose_jax.proposals import CombinedConfig
    from mvpose_jax.trained import Matcher


@dataclasses.dataclass(frozen=True)
class RigSource:
    """A rig: a preset name or a calibration file, and how the file is read.

    Attributes:
      rig: preset name (panoptic5, arplab6) or calibration file (.json, .toml).
      translation_scale: TOML calibrations only: metres per translation unit.
      orthonormalise: replace each camera's R by the nearest rotation.
    """

    rig: str
    translation_scale: float = 1.0
    orthonormalise: bool = False

    def load(self) -> Rig:
        """`data.calibration.load_rig` of this source."""
        from mvpose_jax.data.calibration import load_rig

        return load_rig(
            self.rig, translation_scale=self.translation_scale, orthonormalise=self.orthonormalise
        )


@dataclasses.dataclass(frozen=True)
class DetectionsSource:
    """A recording of 2D detections in any readable format, and how to read it.

    Attributes:
      path: native JSON, original JSON, .npz file or OpenPose folder.
      layout: keypoint layout to work in (None: the file's).
      missing_frames: OpenPose folders: "error" or "empty" (None: the reader's default).
      camera_map: OpenPose folders: camera folder -> calibration camera name.
      source_layout: OpenPose folders: the files' keypoint layout (None: from the count).
      cameras: read only these cameras, in this order (None: all).
    """

    path: str
    layout: str | None = None
    missing_frames: str | None = None
    camera_map: Mapping[str, str] | None = None
    source_layout: str | None = None
    cameras: tuple[str, ...] | None = None

    def reading_options(self) -> dict[str, Any]:
        """The options given, as `data.load_recording` / `open_recording` keyword arguments."""
        kwargs: dict[str, Any] = {}
        if self.missing_frames:
            kwargs["missing_frames"] = self.missing_frames
        if self.camera_map:
            kwargs["camera_map"] = self.camera_map
        if self.source_layout:
            kwargs["source_layout"] = self.source_layout
        # Cameras are chosen while loading: an OpenPose folder's other folders (a stray or
        # uncalibrated camera) are never read.
        kwargs["cameras"] = list(self.cameras) if self.cameras else None
        return kwargs


@dataclasses.dataclass(frozen=True)
class ProposalOptions:
    """How detections are grouped into people (infer and adapt).

    Attributes:
      proposals: "combined", "gat" or "epipolar"; None: combined with a matcher, else epipolar.
      threshold: the GAT's or the epipolar matcher's least match score (None: the matcher
        folder's chosen one, else 0.5).
      min_views: least views of a person.
      half_score_px: the epipolar matcher's distance (px) that scores 0.5.
    """

    proposals: str | None = None
    threshold: float | None = None
    min_views: int = 2
    half_score_px: float = 30.0


def load_detections(source: DetectionsSource, rig: Rig) -> tuple[Recording, Rig]:
    """The recording of ``source`` on the rig's cameras: (recording, the rig of its cameras)."""
    from mvpose_jax.data import load_recording

    rec = load_recording(source.path, layout=source.layout, rig=rig, **source.reading_options())
    return rec, rig.select(list(rec.cameras))


def measure_floor(rig: Rig, source: DetectionsSource) -> FloorEstimate:
    """`floor.estimate_floor_from_detections` on the recording of ``source`` (its OpenPose
    options only: every camera of the rig it holds, in its own layout)."""
    from mvpose_jax.floor import estimate_floor_from_detections

    rec = _own_recording(rig, source)
    return estimate_floor_from_detections(
        rig.select(list(rec.cameras)), rec.detections, layout=rec.layout
    )


def fit_detector_to(rig: Rig, source: DetectionsSource) -> DetectorFit:
    """`detector_fit.fit_detector` on the recording of ``source`` (its OpenPose options only:
    every camera of the rig it holds, in its own layout)."""
    from mvpose_jax.detector_fit import fit_detector

    rec = _own_recording(rig, source)
    return fit_detector(rig.select(list(rec.cameras)), rec.detections, layout=rec.layout)


def _own_recording(rig: Rig, source: DetectionsSource) -> Recording:
    """The user's recording of ``source`` on ``rig``, read with its OpenPose options."""
    from mvpose_jax.data import load_recording

    kwargs = {
        k: v
        for k, v in (
            ("missing_frames", source.missing_frames),
            ("camera_map", source.camera_map),
            ("source_layout", source.source_layout),
        )
        if v
    }
    return load_recording(source.path, rig=rig, **kwargs)


def recordings_in(path: str, layout: str | None, source_layout: str | None = None) -> list:
    """Every recording in a file or (recursively) a folder, in any readable format: .npz and
    .json files, and OpenPose folders (one subfolder per camera), each one recording."""
    from mvpose_jax.data import load_recording
    from mvpose_jax.data.openpose import is_openpose_folder

    root = Path(path)
    if not root.exists():
        raise InputError("no such file or folder", file=root)

    def found(folder: Path):
        if is_openpose_folder(folder):
            yield folder
            return
        for p in sorted(folder.iterdir()):
            if p.is_dir():
                yield from found(p)
            elif p.suffix.lower() in (".npz", ".json"):
                yield p

    sources = list(found(root)) if root.is_dir() else [root]
    if not sources:
        raise InputError("no recordings (.npz, .json or OpenPose folders) here", file=root)

    def load(source: Path):
        if source_layout and source.is_dir():
            return load_recording(source, layout=layout, source_layout=source_layout)
        return load_recording(source, layout=layout)

    return [load(s) for s in sources]


def proposal_mode(proposals: str | None, threshold: float | None, has_matcher: bool) -> str:
    """The proposals to run (`stages.PROPOSALS`; default "combined" with a matcher, else
    "epipolar"), checked: one that needs a matcher without one, or a threshold given to the
    combined matcher (whose settings are the matcher folder's, so it would be silently ignored),
    is refused."""
    from mvpose_jax import stages

    mode = proposals or ("combined" if has_matcher else "epipolar")
    try:
        stage = stages.lookup("proposals", mode, what="--proposals")
    except ValueError as e:
        raise InputError(str(e), field="--proposals") from None
    if stage.needs_matcher and not has_matcher:
        raise InputError(f"--proposals {mode} needs --matcher", field="--proposals")
    if threshold is not None and mode == "combined":
        raise InputError(
            "sets the GAT's or the epipolar matcher's proposals, not the combined matcher's (its "
            "settings are the --matcher folder's proposal_threshold.json); add --proposals gat "
            "to group by the GAT alone at this threshold",
            field="--threshold",
        )
    return mode


def proposal_settings(
    options: ProposalOptions, matcher_folder: str | None, matcher: Matcher | None
) -> tuple[str, float, CombinedConfig | None]:
    """(proposals, threshold, combined config or None) of ``options``.

    The threshold is the GAT's and the epipolar matcher's setting; the combined matcher's come
    from the matcher folder, so a given one would be silently ignored: it is refused instead.
    """
    from mvpose_jax.trained import read_combined_config, read_proposal_threshold

    proposals = proposal_mode(options.proposals, options.threshold, matcher is not None)
    threshold = read_proposal_threshold(matcher_folder, options.threshold)
    combined = read_combined_config(matcher_folder) if proposals == "combined" else None
    return proposals, threshold, combined


def poses_on_rig(poses_path: str, rig: RigSource) -> tuple[PoseResults, Rig]:
    """Poses written by infer and the whole calibration; poses whose cameras are not all in it
    are an error naming the poses file."""
    from mvpose_jax.data.poses import load_poses

    poses = load_poses(poses_path)
    rig_all = rig.load()
    missing = [c for c in poses.cameras if c not in rig_all.names]
    if missing:
        raise InputError(
            f"the poses' cameras {missing} are not in the calibration's {list(rig_all.names)}",
            file=poses_path,
            field="cameras",
        )
    return poses, rig_all


def detections_of(poses: PoseResults, rig_all: Rig, source: DetectionsSource) -> Recording:
    """The detections ``poses`` were made from, read on the poses' cameras in their layout."""
    from mvpose_jax.data import load_recording

    options = {**source.reading_options(), "cameras": list(poses.cameras)}
    return load_recording(source.path, layout=poses.layout, rig=rig_all, **options)


def poses_and_detections(
    rig: RigSource, detections: DetectionsSource, poses_path: str
) -> tuple[PoseResults, Recording, Rig]:
    """Poses written by infer and the detections they were made from, on the poses' cameras:
    (PoseResults, Recording, Rig). Poses that cannot come from these detections (another
    layout, frame count or more skeletons per view) are an error."""
    import numpy as np

    from mvpose_jax.data.poses import load_poses

    rig_all = rig.load()
    poses = load_poses(poses_path)
    source = dataclasses.replace(detections, cameras=tuple(poses.cameras))
    rec, rig_used = load_detections(source, rig_all)
    if rec.layout != poses.layout:
        raise InputError(
            f"poses are in layout {poses.layout!r}, the detections in {rec.layout!r}; pass --layout",
            file=poses_path,
            field="layout",
        )
    F, P = rec.num_frames, np.shape(rec.detections.score)[2]
    if len(poses.confidence) != F or poses.identity.shape[2] > P:
        partial = (
            f" (partial results of an interrupted infer, {poses.frames_total} frames in all: "
            "finish them with infer --resume)"
            if poses.partial
            else ""
        )
        raise InputError(
            f"poses have {len(poses.confidence)} frames and {poses.identity.shape[2]} skeletons per "
            f"view; the detections {F} and {P}{partial}",
            file=poses_path,
            field="frames",
        )
    return poses, rec, rig_used


def read_dev_quality(folder: str) -> dict | None:
    """A model folder's comparison of the estimator with triangulation on the dev people
    (`train.compare_with_triangulation`'s file), or None when it has none."""
    from mvpose_jax.trained import ModelFolder

    return ModelFolder(folder).read_dev_quality()
