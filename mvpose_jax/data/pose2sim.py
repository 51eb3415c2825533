"""Pose2Sim projects read as they are: sessions, participants and trials, with Pose2Sim's rules.

A Pose2Sim project is a folder tree::

    session/                     Config.toml (the project's settings)
      Calibration/               any folder whose name contains "calib" (case-insensitive)
        Calib_qualisys.toml      the calibration: the first *.toml there (sorted)
      participant/               Config.toml (optional): overrides the session's
        trial/                   Config.toml (optional): overrides the participant's
          pose/                  detections: the first of pose-associated/, pose-sync/, pose/
            cam01_json/          one OpenPose folder per camera: subfolders whose name has "json"
              cam01.0000.json    one file per frame

A trial may also be given alone, or a participant, or a session whose trials sit directly in it;
`find_trials` finds every trial (a folder holding one of `POSE_FOLDERS`) at most two levels below
the folder given, in sorted order, and reads, as Pose2Sim does:

  * settings: the ``Config.toml`` of every level from the session root down to the trial, the
    deeper one overriding key by key (nested tables merged). The session root is the highest
    folder with a ``Config.toml`` among the folder given and as many of its parents as make three
    levels (a trial's parent and grandparent, a participant's parent).
  * the calibration: the first ``*.toml`` (sorted by name) in the first folder (sorted by name)
    whose name contains "calib", looked for in the session root, then in each level below it down
    to the trial.
  * cameras: the detection folder's subfolders whose name contains "json", in natural order
    (digit runs compared as numbers: ``cam2_json`` before ``cam10_json``), paired with the
    calibration's cameras (in the file's order) BY POSITION, not by name, as Pose2Sim pairs them
    (``cam01_json`` -> ``cam_01``); a different count is an error naming both lists. Frame files
    are then aligned by `mvpose_jax.data.openpose` (names without ``_keypoints.json`` by their
    sorted position, as Pose2Sim does).
  * ``[project] frame_rate`` (frames per second; ``'auto'`` means the videos' rate, which the JSON
    files do not hold: `Pose2SimTrial.fps` is then None and a note says so),
    ``[project] frame_range`` (``[]`` or ``'all'``: every frame; ``[first, stop]``: frames first to
    stop - 1, Pose2Sim's convention), ``[project] exclude_from_batch`` (trials, as
    ``participant/trial`` paths from the session root or trial names, skipped when a session or a
    participant is read; a trial given alone is read) and ``[pose] pose_model`` (the detector's
    keypoint layout, `POSE_MODELS`).

Pose2Sim names its 3D results ``pose-3d/<trial>_<first>-<stop>.trc`` (``_P<n>`` after the trial
for person n of a multi-person trial): `trc_name`. `open_trial` opens a trial's detections.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mvpose_jax.data.calibration import load_rig, rig_from_toml
from mvpose_jax.data.files import read_toml
from mvpose_jax.data.openpose import OpenPoseStream
from mvpose_jax.errors import InputError

CONFIG_NAME = "Config.toml"
# Where a trial's detections are, in the order Pose2Sim looks (its association's output first).
POSE_FOLDERS = ("pose-associated", "pose-sync", "pose")
# Pose2Sim's [pose] pose_model names (upper case) -> our keypoint layouts. "COCO" is OpenPose's
# 18-keypoint COCO model, in OpenPose's order; the RTMLib names (Body_with_feet, Whole_body, Body)
# are the models Pose2Sim's own pose estimation runs.
POSE_MODELS = {
    "BODY_25B": "body25b",
    "BODY_25": "body25",
    "BODY_135": "body135",
    "COCO": "openpose_coco18",
    "COCO_17": "coco17",
    "BODY": "coco17",
    "HALPE_26": "halpe26",
    "BODY_WITH_FEET": "halpe26",
    "HALPE_68": "halpe68",
    "HALPE_136": "halpe136",
    "COCO_133": "coco133",
    "COCO_133_WRIST": "coco133",
    "WHOLE_BODY": "coco133",
    "WHOLE_BODY_WRIST": "coco133",
    "BLAZEPOSE": "blazepose",
    "MPII": "mpii",
}
# Trials sit at most this many levels below a session (session / participant / trial).
_MAX_DEPTH = 2


@dataclasses.dataclass(frozen=True)
class Pose2SimTrial:
    """One trial of a Pose2Sim project, with everything needed to read it.

    Attributes:
      name: the trial folder's name (Pose2Sim's output files start with it).
      folder: the trial folder.
      config: its settings, every level's ``Config.toml`` merged (deeper ones override).
      config_files: the ``Config.toml`` files merged, session first.
      calibration: the calibration file (Pose2Sim TOML; `mvpose_jax.data.calibration.load_rig`).
      detections: the OpenPose folder used (``pose-associated``, ``pose-sync`` or ``pose``).
      camera_map: detection folder -> calibration camera name, paired by sorted position.
      fps: frames per second from ``[project] frame_rate``; None for ``'auto'`` or when absent
        (the JSON files hold no time: the caller falls back to its default and says so).
      frame_range: (first, stop) frames to read, stop excluded; None for every frame.
      source_layout: our keypoint layout of ``[pose] pose_model``; None when the config names
        none (the reader then detects it from the keypoint count).
      pose_model: ``[pose] pose_model`` as written, or None.
      notes: things the caller should tell the user (an 'auto' frame rate, a suspicious pairing).
    """

    name: str
    folder: Path
    config: Mapping[str, Any]
    config_files: tuple[Path, ...]
    calibration: Path
    detections: Path
    camera_map: Mapping[str, str]
    fps: float | None
    frame_range: tuple[int, int] | None
    source_layout: str | None
    pose_model: str | None
    notes: tuple[str, ...] = ()

    @property
    def cameras(self) -> tuple[str, ...]:
        """The calibration cameras of the detection folders, in the pairing's order (pass as
        ``cameras=`` so that other subfolders of the detection folder are not read)."""
        return tuple(self.camera_map.values())

    def pairing_lines(self) -> list[str]:
        """The camera pairing in words, one line per camera: ``cam01_json -> cam_01``."""
        return [f"{folder} -> {camera}" for folder, camera in self.camera_map.items()]

    def describe(self) -> str:
        """The trial, its calibration and its camera pairing in a few lines, for the CLI."""
        fps = "auto" if self.fps is None else f"{self.fps:g}"
        frames = (
            "all" if self.frame_range is None else f"{self.frame_range[0]}-{self.frame_range[1]}"
        )
        lines = [
            f"trial {self.name}: detections {self.detections}, calibration {self.calibration}",
            f"  pose model {self.pose_model} ({self.source_layout}), {fps} fps, frames {frames}",
            *(f"  {line}" for line in self.pairing_lines()),
            *(f"  note: {note}" for note in self.notes),
        ]
        return "\n".join(lines)

    def frame_span(self, num_frames: int) -> tuple[int, int]:
        """(first, stop) of the frames to read from a recording of ``num_frames`` frames: the
        config's ``frame_range`` cut to the recording, or every frame.

        Raises:
          InputError naming the Config.toml and field when the range holds none of its frames.
        """
        if self.frame_range is None:
            return 0, int(num_frames)
        first, stop = self.frame_range[0], min(self.frame_range[1], int(num_frames))
        if first >= stop:
            raise InputError(
                f"frame_range {list(self.frame_range)} holds none of the recording's "
                f"{num_frames} frames ({self.detections})",
                file=_source_of(self.config_files, ("project", "frame_range")),
                field="[project] frame_range",
            )
        return first, stop


@dataclasses.dataclass(frozen=True)
class Pose2SimSession:
    """The trials of a Pose2Sim project (`find_trials`).

    Attributes:
      root: the session root (the highest folder whose Config.toml was read).
      trials: the trials to read, in sorted order.
      excluded: trial folders skipped because ``exclude_from_batch`` names them.
    """

    root: Path
    trials: tuple[Pose2SimTrial, ...]
    excluded: tuple[Path, ...] = ()


def open_trial(
    trial: Pose2SimTrial,
    *,
    layout: str = "coco18",
    rig: Any = None,
    missing_frames: str = "empty",
) -> OpenPoseStream:
    """Opens a trial's detections to be read a range of frames at a time, as Pose2Sim reads them:
    the paired camera folders only (named by their calibration cameras, in the calibration's
    order), the config's keypoint layout converted to ``layout``, a frame a camera has no file
    for read as nobody seen (``missing_frames="empty"``, counted in the stream's `report`, as are
    entries without keypoints).

    Args:
      trial: from `find_trials`.
      layout: keypoint layout of the ranges read.
      rig: the trial's rig if already loaded (default: its calibration is loaded).
      missing_frames: ``"empty"`` (default) or ``"error"`` (`mvpose_jax.data.openpose`).
    Returns:
      An `OpenPoseStream` (close it, or use it in a ``with`` block).
    """
    return OpenPoseStream(
        trial.detections,
        layout=layout,
        source_layout=trial.source_layout,
        cameras=trial.cameras,
        rig=load_rig(trial.calibration) if rig is None else rig,
        missing_frames=missing_frames,
        camera_map=trial.camera_map,
    )


def trc_name(trial: str, first: int, stop: int, person: int | None = None) -> str:
    """Pose2Sim's name for a trial's TRC file: ``<trial>_<first>-<stop>.trc``, or
    ``<trial>_P<person>_<first>-<stop>.trc`` for person ``person`` (from 1) of a multi-person trial.
    ``stop`` is one past the last frame (a 100-frame trial is ``_0-100``)."""
    who = "" if person is None else f"_P{int(person)}"
    return f"{trial}{who}_{int(first)}-{int(stop)}.trc"


def is_pose2sim_project(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a Pose2Sim session, participant or trial folder: a trial (a folder
    holding one of `POSE_FOLDERS`) at most two levels down, and a ``Config.toml`` in the folder
    or in a parent within the session's three levels."""
    root = Path(path)
    if not root.is_dir():
        return False
    try:
        trials = _trial_folders(root)
    except OSError:
        return False
    if not trials:
        return False
    return bool(_config_chain(root, _depth(root, trials)))


def find_trials(
    path: str | os.PathLike, *, pose_folders: Sequence[str] = POSE_FOLDERS
) -> Pose2SimSession:
    """Finds and describes every trial of a Pose2Sim session, participant or trial folder.

    Args:
      path: the session, a participant or a trial folder.
      pose_folders: the detection folders to look for, first found first; default Pose2Sim's
        order (``("pose",)`` reads the raw detections rather than Pose2Sim's association).
    Returns:
      A `Pose2SimSession` (trials sorted by their path; excluded ones listed apart).
    Raises:
      InputError naming the file and field: no trial, no Config.toml, no calibration, a detection
      folder whose camera count differs from the calibration's (both lists named), an unknown
      pose model, an unreadable frame rate or frame range.
    """
    given = Path(path)
    if not given.is_dir():
        raise InputError("not a folder (a Pose2Sim session, participant or trial)", file=given)
    pose_folders = tuple(pose_folders)
    try:
        trials = _trial_folders(given, pose_folders)
    except OSError as e:
        raise InputError(f"cannot list ({e.strerror})", file=given) from None
    if not trials:
        raise InputError(
            f"no trial here: no folder holding one of {list(pose_folders)} in this folder or up "
            f"to {_MAX_DEPTH} levels below it",
            file=given,
        )
    chain = _config_chain(given, _depth(given, trials))
    if not chain:
        raise InputError(
            f"no {CONFIG_NAME} in this folder or its parents of the same session: not a Pose2Sim "
            "project",
            file=given,
        )
    root = chain[0]
    found, excluded = [], []
    for folder in trials:
        levels = _levels(root, folder)
        files = tuple(level / CONFIG_NAME for level in levels if (level / CONFIG_NAME).is_file())
        config = _merged(files)
        if folder != given and _is_excluded(config, files, root, folder):
            excluded.append(folder)
            continue
        found.append(_trial(folder, levels, files, config, pose_folders))
    return Pose2SimSession(root=root, trials=tuple(found), excluded=tuple(excluded))


def merge_configs(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``override``'s keys replacing its own, nested tables merged key by key (as
    Pose2Sim merges a session's, a participant's and a trial's Config.toml). Neither is changed."""
    out = copy.deepcopy(dict(base))
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge_configs(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


# --------------------------------------------------------------------------- helpers


def natural_key(name: str) -> tuple:
    """Sort key comparing digit runs as numbers (``cam2`` before ``cam10``)."""
    # re.split with a group alternates text and digit runs, so equal positions hold equal types.
    return tuple(int(s) if i % 2 else s for i, s in enumerate(re.split(r"(\d+)", name)))


def _subfolders(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))


def _pose_folder(folder: Path, pose_folders: Sequence[str]) -> Path | None:
    for name in pose_folders:
        if (folder / name).is_dir():
            return folder / name
    return None


def _trial_folders(root: Path, pose_folders: Sequence[str] = POSE_FOLDERS) -> list[Path]:
    """Trial folders at ``root`` or up to `_MAX_DEPTH` levels below it, sorted by path."""
    if _pose_folder(root, pose_folders) is not None:
        return [root]
    found, level = [], [root]
    for _ in range(_MAX_DEPTH):
        below = []
        for folder in level:
            for sub in _subfolders(folder):
                if "calib" in sub.name.lower():
                    continue
                (found if _pose_folder(sub, pose_folders) is not None else below).append(sub)
        level = below
    return sorted(found, key=lambda p: p.relative_to(root).parts)


def _depth(root: Path, trials: list[Path]) -> int:
    return max(len(t.relative_to(root).parts) for t in trials)


def _config_chain(given: Path, depth: int) -> list[Path]:
    """The folders holding a Config.toml from the session root down to ``given``: ``given`` and
    its parents within the session's three levels (a trial's two, a participant's one)."""
    chain = [given] if (given / CONFIG_NAME).is_file() else []
    folder = given.resolve()
    for _ in range(max(0, _MAX_DEPTH - depth)):
        folder = folder.parent
        if (folder / CONFIG_NAME).is_file():
            chain.insert(0, folder)
    return chain


def _levels(root: Path, trial: Path) -> list[Path]:
    """The folders from ``root`` down to ``trial`` (both included)."""
    root_r, trial_r = root.resolve(), trial.resolve()
    if trial_r == root_r:
        return [trial]
    parts = trial_r.relative_to(root_r).parts
    return [root] + [root.joinpath(*parts[: i + 1]) for i in range(len(parts))]


def _merged(files: Sequence[Path]) -> dict[str, Any]:
    config: dict[str, Any] = {}
    for file in files:
        config = merge_configs(config, read_toml(file))
    return config


def _source_of(files: Sequence[Path], keys: tuple[str, ...]) -> Path | None:
    """The deepest Config.toml that sets ``keys`` (a path of nested tables), for error messages."""
    for file in reversed(files):
        table: Any = read_toml(file)
        for key in keys:
            table = table.get(key) if isinstance(table, dict) else None
        if table is not None:
            return file
    return files[-1] if files else None


def _setting(config: Mapping[str, Any], section: str, key: str) -> Any:
    table = config.get(section)
    return table.get(key) if isinstance(table, Mapping) else None


def _is_excluded(config: Mapping[str, Any], files, root: Path, trial: Path) -> bool:
    listed = _setting(config, "project", "exclude_from_batch")
    if listed is None:
        return False
    if not isinstance(listed, list) or not all(isinstance(s, str) for s in listed):
        raise InputError(
            f"expected a list of trial paths, got {listed!r}"[:200],
            file=_source_of(files, ("project", "exclude_from_batch")),
            field="[project] exclude_from_batch",
        )
    relative = trial.resolve().relative_to(root.resolve()).as_posix()
    wanted = {s.replace("\\", "/").strip("/") for s in listed}
    wanted |= {w.removeprefix("./") for w in wanted}
    return relative in wanted or trial.name in wanted


def _calibration(levels: Sequence[Path]) -> Path:
    for level in levels:
        folders = [p for p in _subfolders(level) if "calib" in p.name.lower()]
        if not folders:
            continue
        tomls = sorted(p for p in folders[0].glob("*.toml") if p.is_file())
        if not tomls:
            raise InputError(
                "the calibration folder holds no .toml file (Pose2Sim's calibration); convert or "
                "calculate the calibration with Pose2Sim first",
                file=folders[0],
                field="calibration",
            )
        return tomls[0]
    raise InputError(
        "no calibration: no folder whose name contains 'calib' in the session root or any level "
        f"down to the trial ({[str(p) for p in levels]})",
        file=levels[0],
        field="calibration",
    )


def _camera_map(detections: Path, calibration: Path) -> tuple[dict[str, str], list[str]]:
    """detection folder -> calibration camera by position, and notes on suspicious pairs."""
    folders = sorted(
        (p.name for p in _subfolders(detections) if "json" in p.name.lower()), key=natural_key
    )
    cameras = [str(n) for n in rig_from_toml(read_toml(calibration), file=calibration).names]
    if len(folders) != len(cameras):
        raise InputError(
            f"{len(folders)} camera folder(s) (names containing 'json') {folders} but "
            f"{len(cameras)} camera(s) in the calibration {calibration}: {cameras}; Pose2Sim pairs "
            "them by sorted position, so the counts must agree (remove the extra folders or "
            "cameras, or read the OpenPose folder with a camera map)",
            file=detections,
            field="cameras",
        )
    pairs = dict(zip(folders, cameras, strict=True))
    notes = []
    for folder, camera in pairs.items():
        other = next((c for c in cameras if c != camera and _names_alike(folder, c)), None)
        if other is not None:
            notes.append(
                f"folder {folder} is paired with camera {camera} by position (Pose2Sim's rule), "
                f"though camera {other} has its name"
            )
    return pairs, notes


def _names_alike(folder: str, camera: str) -> bool:
    stem = folder.lower().removesuffix("_json").removesuffix("-json").removesuffix("json")
    return stem == camera.lower()


def _trial(folder: Path, levels, files, config, pose_folders) -> Pose2SimTrial:
    detections = _pose_folder(folder, pose_folders)
    assert detections is not None  # _trial_folders found it
    calibration = _calibration(levels)
    camera_map, notes = _camera_map(detections, calibration)
    fps = _fps(config, files, notes)
    frame_range = _frame_range(config, files, notes)
    pose_model = _setting(config, "pose", "pose_model")
    if pose_model is None:
        source_layout = None
        notes.append("no [pose] pose_model in Config.toml: the layout follows the keypoint count")
    else:
        source_layout = _layout_of(pose_model, files)
    return Pose2SimTrial(
        name=folder.name,
        folder=folder,
        config=config,
        config_files=tuple(files),
        calibration=calibration,
        detections=detections,
        camera_map=camera_map,
        fps=fps,
        frame_range=frame_range,
        source_layout=source_layout,
        pose_model=pose_model,
        notes=tuple(notes),
    )


def _layout_of(pose_model: Any, files) -> str:
    key = pose_model.upper() if isinstance(pose_model, str) else None
    if key not in POSE_MODELS:
        raise InputError(
            f"unknown pose model {pose_model!r}"[:200]
            + f"; known: {sorted(POSE_MODELS)} (CUSTOM models are not read)",
            file=_source_of(files, ("pose", "pose_model")),
            field="[pose] pose_model",
        )
    return POSE_MODELS[key]


def _fps(config, files, notes: list[str]) -> float | None:
    value = _setting(config, "project", "frame_rate")
    if value is None or (isinstance(value, str) and value.lower() == "auto"):
        said = "no [project] frame_rate" if value is None else "frame_rate = 'auto'"
        notes.append(
            f"{said}: the frame rate is the videos', which the JSON files do not hold; the "
            "recording's timestamps or the default rate are used"
        )
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
        raise InputError(
            f"expected a positive number of frames per second or 'auto', got {value!r}"[:200],
            file=_source_of(files, ("project", "frame_rate")),
            field="[project] frame_rate",
        )
    if value == float("inf"):
        raise InputError(
            "the frame rate is not finite",
            file=_source_of(files, ("project", "frame_rate")),
            field="[project] frame_rate",
        )
    return float(value)


def _frame_range(config, files, notes: list[str]) -> tuple[int, int] | None:
    value = _setting(config, "project", "frame_range")
    if value is None or value == [] or (isinstance(value, str) and value.lower() == "all"):
        return None
    if isinstance(value, str) and value.lower() == "auto":
        notes.append("frame_range = 'auto' (Pose2Sim's choice of the moving frames): all read")
        return None
    ok = (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
        and 0 <= value[0] < value[1]
    )
    if not ok:
        raise InputError(
            f"expected [] or [first, stop] with 0 <= first < stop, got {value!r}"[:200],
            file=_source_of(files, ("project", "frame_range")),
            field="[project] frame_range",
        )
    return int(value[0]), int(value[1])
