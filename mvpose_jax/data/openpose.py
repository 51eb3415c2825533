"""OpenPose-style per-frame JSON folders: what OpenPose, Pose2Sim and many 2D detectors write.

Layout on disk::

    root/
      cam0/                                  one subfolder per camera, named like the camera
        run_000000000000_keypoints.json      one JSON file per frame
        run_000000000001_keypoints.json
        ...
      cam1/
        ...

Each file is ``{"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, y1, c1, ...], ...}, ...]}``
(pixels; ``c`` is the confidence, in [0, 1]). Only ``pose_keypoints_2d`` is read: OpenPose's other
entries (``person_id``, face, hands, 3D) are not part of a `Recording`. OpenPose writes ``c = 0``
and ``x = y = 0`` for a keypoint it did not find; such keypoints are missing (score 0).
Coordinates outside the image (negative ones included: a skeleton partly out of view) are taken
as they are. A person entry without keypoints (``"pose_keypoints_2d": []``, which real detectors
write, or an empty object ``{}``, which Pose2Sim's person association writes for a person one
camera does not see) is no person: it is skipped and counted (`OpenPoseStream.report`). An entry
that has other fields but no ``pose_keypoints_2d``, or a list of the wrong length, is an error.

Frames. A file's frame number is the last run of digits in its name before ``_keypoints.json``
(``run_000000000123_keypoints.json`` is frame 123). When no file has such a name, the frame number
is the file's position in its camera folder in natural order (digit runs compared as numbers, so
``2.json`` comes before ``10.json``); a mix of the two kinds of names is an error, since the two
numberings need not agree. Frames are aligned across cameras by frame number: the recording's
frame ``f`` is the ``f``-th smallest frame number of any camera (numbers no camera has are not
frames). A frame number that some cameras have and another lacks is an error naming that camera
and frame, unless ``missing_frames="empty"``: that camera then saw nobody in that frame (counted
per camera in `OpenPoseStream.report`). Errors
name frames by their number (as in the file names), not by their position in the recording.

Keypoint layout. The number of keypoints in the files says which layout they hold
(`LAYOUT_OF_COUNT`): 25 is ``body25`` (BODY_25), 18 is ``openpose_coco18`` (OpenPose's COCO model,
whose order differs from the project's ``coco18``: OpenPose's index 1, the neck, is coco18's 17, its
2, the right shoulder, coco18's 6, ...), 17 is ``coco17`` (COCO's own order, as other detectors
write it), 26 ``halpe26``, 68 ``halpe68``, 136 ``halpe136``, 133 ``coco133`` (COCO-WholeBody), 135
``body135``, 33 ``blazepose`` and 16 ``mpii``. A count two layouts share is read as the first
(`SHARED_COUNTS`): 25-keypoint files of OpenPose's experimental BODY_25B need
``source_layout="body25b"``, and 18-keypoint files already in the project's order ``"coco18"``.
``source_layout=`` overrides the detection. Keypoints are then converted to ``layout`` (default
``coco18``) with `mvpose_jax.skeletons.convert_keypoints`: a target layout with fewer points drops
the others (face, hands, feet for ``coco18``); reading in the files' own layout keeps them all.

Cameras. Subfolder names are camera names (hidden ones, starting with ``.``, are skipped). With a
``rig``, every camera read must be one of its cameras (else an error lists both) and cameras
follow the rig's order; without one, they follow ``cameras=`` or else sorted folder names.

`save_openpose` writes the same layout (frame ``f`` as ``{f:012d}_keypoints.json``), each file
atomically; only detections travel, in OpenPose's own keypoint order by default.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mvpose_jax.data.checks import (
    check_keypoints,
    check_recording,
    float_lists,
    is_number,
    load_json,
    pack_detections,
    to_float,
)
from mvpose_jax.data.files import atomic_open
from mvpose_jax.data.recording import Recording, convert_layout
from mvpose_jax.data.stream import ReadReport, RecordingStream
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import get_layout

SUFFIX = "_keypoints.json"
MISSING_FRAMES = ("error", "empty")
# Layout of files holding this many keypoints (module docstring).
LAYOUT_OF_COUNT = {
    25: "body25",
    18: "openpose_coco18",
    17: "coco17",
    26: "halpe26",
    68: "halpe68",
    136: "halpe136",
    133: "coco133",
    135: "body135",
    33: "blazepose",
    16: "mpii",
}
# Counts that another layout shares with the default above: its files need source_layout=.
SHARED_COUNTS = {25: ("body25b",), 18: ("coco18",)}
# What `save_openpose` writes for a recording in the project's coco18: OpenPose's own order.
_WRITE_LAYOUT = {"coco18": "openpose_coco18"}
# The keys OpenPose (1.3 and later) writes for each person, all but the pose left empty.
_OTHER_KEYS = (
    "face_keypoints_2d",
    "hand_left_keypoints_2d",
    "hand_right_keypoints_2d",
    "pose_keypoints_3d",
    "face_keypoints_3d",
    "hand_left_keypoints_3d",
    "hand_right_keypoints_3d",
)


def is_openpose_folder(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder of camera subfolders holding ``*_keypoints.json`` files."""
    root = Path(path)
    if not root.is_dir():
        return False
    return any(sub.is_dir() and any(sub.glob("*" + SUFFIX)) for sub in root.iterdir())


def read_openpose(
    folder: str | os.PathLike,
    *,
    layout: str = "coco18",
    source_layout: str | None = None,
    cameras: Sequence[str] | None = None,
    rig: Any = None,
    missing_frames: str = "error",
    camera_map: Mapping[str, str] | None = None,
) -> Recording:
    """Reads a folder of per-camera, per-frame OpenPose JSON files (see the module docstring).

    Args:
      folder: the root folder, holding one subfolder per camera.
      layout: keypoint layout of the returned recording (converted from the files').
      source_layout: the files' layout; default: detected from the keypoint count.
      cameras: camera names to read, in this order (only their folders are read); default: every
        subfolder.
      rig: optional `Rig`; every camera read must be one of its cameras, and without
        ``cameras=`` the camera axis follows the rig's order. With a rig, a folder named after a
        camera plus a suffix tools add (`CAMERA_FOLDER_SUFFIXES`: ``cam01_json`` is ``cam01``)
        belongs to that camera.
      camera_map: folder name -> camera name, for folders named otherwise.
      missing_frames: ``"error"`` (default): a frame number present in some cameras and missing in
        another is an error; ``"empty"``: that camera has no detections in that frame.
    Returns:
      A `Recording` with detections only (no identities, ground truth or timestamps). Entries
      without keypoints are skipped; `OpenPoseStream` counts them (`OpenPoseStream.report`).
    Raises:
      InputError naming the file, frame (its number), camera and field of the first problem.
    """
    with OpenPoseStream(
        folder,
        layout=layout,
        source_layout=source_layout,
        cameras=cameras,
        rig=rig,
        missing_frames=missing_frames,
        camera_map=camera_map,
    ) as stream:
        return stream.read_frames(0, stream.num_frames)


class OpenPoseStream(RecordingStream):
    """An OpenPose folder read a range of frames at a time (`mvpose_jax.data.stream`).

    Opening lists the camera folders and their file names, numbers the frames and checks that
    every camera has every frame (all as `read_openpose`, which reads through here); `read_frames`
    then parses only the files of the range. The files' keypoint count (their layout) is taken
    from the first person met, in the order the ranges are read, and every later person must have
    it. Arguments as `read_openpose`. `report` counts what was taken as it was: entries without
    keypoints skipped (in the frames read so far) and frames missing per camera.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        *,
        layout: str = "coco18",
        source_layout: str | None = None,
        cameras: Sequence[str] | None = None,
        rig: Any = None,
        missing_frames: str = "error",
        camera_map: Mapping[str, str] | None = None,
    ):
        root = Path(folder)
        get_layout(layout)  # an unknown target layout fails before any file is read
        if missing_frames not in MISSING_FRAMES:
            raise InputError(
                f"missing_frames must be one of {list(MISSING_FRAMES)}, got {missing_frames!r}",
                field="missing_frames",
            )
        if source_layout is not None:
            get_layout(source_layout)
        names, camera_names = _camera_folders(root, cameras, rig, camera_map)
        files = {name: _frame_files(root / name, name) for name in names}
        frame_of = _frame_numbers(root, files)  # camera -> {frame number: file}
        numbers = sorted(set().union(*(set(per_cam) for per_cam in frame_of.values())))
        if not numbers:
            raise InputError(
                f"no frame files (*.json) in any camera folder {names}", file=root, field="frames"
            )
        if missing_frames == "error":
            for name in names:
                lacking = [n for n in numbers if n not in frame_of[name]]
                if lacking:
                    other = next(c for c in names if lacking[0] in frame_of[c])
                    raise InputError(
                        f"no file for this frame, which camera {other!r} has "
                        f"({frame_of[other][lacking[0]].name}); {len(lacking)} frame(s) missing "
                        "here in all. Pass missing_frames='empty' to read them as frames without "
                        "people",
                        file=root / name,
                        frame=lacking[0],
                        camera=name,
                        field="frames",
                    )
        super().__init__(
            root, cameras=tuple(camera_names), layout=layout, num_frames=len(numbers), streamed=True
        )
        self._folders = names
        self._frame_of = frame_of
        self._numbers = numbers
        self._source_layout = source_layout
        # The files' keypoint count, and the file, frame and person where it was first seen.
        self._K = None if source_layout is None else get_layout(source_layout).num_keypoints
        self._first: tuple[Path, int, int] | None = None
        # (frame number, camera index) -> entries without keypoints skipped in that file; keyed
        # so that reading a range again does not count it twice.
        self._empty: dict[tuple[int, int], int] = {}
        self._missing = {
            camera: len(numbers) - len(frame_of[name])
            for camera, name in zip(camera_names, names, strict=True)
        }

    def report(self) -> ReadReport:
        """Entries without keypoints skipped in the frames read so far and frames missing per
        camera (read as frames without people), by camera name."""
        empty = dict.fromkeys(self.cameras, 0)
        for (_, c), n in self._empty.items():
            empty[self.cameras[c]] += n
        return ReadReport(empty_entries=empty, missing_frames=dict(self._missing))

    def read_frames(self, start: int, stop: int) -> Recording:
        root, names, layout = Path(self.path), self._folders, self.layout
        numbers = self._numbers[max(0, start) : stop]
        source_layout = self._source_layout
        # Every skeleton, in file order, with where it goes (frame position, camera, person).
        rows: list[np.ndarray] = []  # (3K,) float64 each
        where: list[tuple[int, int, int]] = []
        # Its file, frame number and entry index in the file, for error messages.
        origin: list[tuple[Path, int, int]] = []
        for fi, number in enumerate(numbers):
            for c, name in enumerate(names):
                path = self._frame_of[name].get(number)
                if path is None:
                    continue
                entries = _people(path, number, name)
                self._empty[(number, c)] = sum(flat is None for flat in entries)
                slot = 0  # the person's row in this view: empty entries take none
                for p, flat in enumerate(entries):
                    if flat is None:
                        continue
                    if self._K is None:
                        self._first = (path, number, p)
                        self._K = _detect_count(flat.size, path, number, name, p)
                    K = self._K
                    if flat.size != 3 * K:
                        first = self._first
                        hint = _count_hint(flat.size // 3)
                        why = (
                            f"layout {source_layout!r} has {K} keypoints{hint}"
                            if first is None
                            else f"{first[0]} (frame {first[1]}, person {first[2]}) has {K}"
                        )
                        raise InputError(
                            f"{flat.size // 3} keypoints ({flat.size} numbers), but {why}",
                            file=path,
                            frame=number,
                            camera=name,
                            field=f"people[{p}].pose_keypoints_2d",
                        )
                    rows.append(flat)
                    where.append((fi, c, slot))
                    origin.append((path, number, p))
                    slot += 1

        # Before any person is met, the files' layout is unknown: an empty range is built in
        # the target layout (converting empty detections gives the same).
        src = source_layout or (layout if self._K is None else LAYOUT_OF_COUNT[self._K])
        K = get_layout(src).num_keypoints
        values = np.stack(rows).reshape(-1, K, 3) if rows else np.zeros((0, K, 3))
        failed: list[int] = []

        def locate(i: int):  # called by the check only for the first bad row
            failed.append(i)
            return origin[i][1], names[where[i][1]], origin[i][2]  # the entry's index in the file

        try:
            xy, score = check_keypoints(
                values[..., :2],
                values[..., 2],
                num_keypoints=K,
                locate=locate,
                field="people[{p}].pose_keypoints_2d[keypoint {k}]",
                score_field="people[{p}].pose_keypoints_2d[keypoint {k}].c",
                count_field="people[{p}].pose_keypoints_2d",
                reading=True,
                source=root,
                clipped=self.clipped,
            )
        except InputError as e:
            raise e.at(file=origin[failed[-1]][0]) from None
        index = tuple(np.array(where, np.int64).reshape(-1, 3).T)
        det = pack_detections(
            xy, score, index, num_frames=len(numbers), num_cameras=len(names), file=root
        )
        rec = Recording(detections=det, cameras=self.cameras, layout=src)
        return rec if src == layout else convert_layout(rec, layout)


def save_openpose(
    recording: Recording, folder: str | os.PathLike, *, layout: str | None = None
) -> None:
    """Writes a recording's detections as OpenPose JSON folders, one file per camera and frame.

    Frame ``f`` of camera ``cam`` goes to ``folder/cam/{f:012d}_keypoints.json``, each file written
    atomically; the recording is validated first, so invalid values write nothing. Missing
    keypoints are written ``0, 0, 0`` and padding rows not at all. Identities, ground truth,
    projections, timestamps and image names have no place in the format and are not written.

    Args:
      recording: the recording.
      folder: the root folder (created if needed).
      layout: keypoint layout to write; default the recording's, except that ``coco18`` is written
        in OpenPose's order (``openpose_coco18``), which `read_openpose` detects and maps back.
    Raises:
      InputError: invalid values; a camera name that cannot be a folder name; a camera folder that
        already holds other ``.json`` files (they would be read back as extra frames).
    """
    root = Path(folder)
    check_recording(recording, file=root)
    out_layout = layout or _WRITE_LAYOUT.get(recording.layout, recording.layout)
    get_layout(out_layout)
    for name in recording.cameras:
        if name in ("", ".", "..") or name.startswith(".") or any(ch in name for ch in "/\\\0"):
            raise InputError(
                "camera name cannot be a folder name (empty, hidden, or with a path separator)",
                file=root,
                camera=name,
                field="cameras",
            )
    F = recording.num_frames
    targets = [f"{f:012d}{SUFFIX}" for f in range(F)]
    wanted = set(targets)
    for name in recording.cameras:
        cam_dir = root / name
        if cam_dir.is_dir():
            stale = sorted(p.name for p in cam_dir.glob("*.json") if p.name not in wanted)
            if stale:
                raise InputError(
                    f"the camera folder already holds {len(stale)} other frame file(s) (e.g. "
                    f"{stale[0]}) that would be read back as frames; use an empty folder",
                    file=cam_dir,
                    camera=name,
                )
    if out_layout != recording.layout:
        recording = convert_layout(recording, out_layout)
    det = recording.detections
    score = np.asarray(det.score, np.float32)
    count = np.asarray(det.count)
    # (F, C, P, K, 3) rows [x, y, c], missing keypoints written [0, 0, 0] as OpenPose does.
    kp = np.concatenate([np.asarray(det.xy, np.float32), score[..., None]], axis=-1)
    kp[score == 0] = 0.0
    kp_lists = float_lists(kp.reshape(kp.shape[:3] + (-1,)))
    compact: dict[str, Any] = {"separators": (",", ":"), "allow_nan": False}
    for c, name in enumerate(recording.cameras):
        for f in range(F):
            people = [
                {"person_id": [-1], "pose_keypoints_2d": kp_lists[f][c][p]}
                | {key: [] for key in _OTHER_KEYS}
                for p in range(int(count[f, c]))
            ]
            with atomic_open(root / name / targets[f], "w") as out:
                out.write(json.dumps({"version": 1.3, "people": people}, **compact))


def parse_camera_map(values: Sequence[str] | Sequence[Sequence[str]]) -> dict[str, str]:
    """A camera map (folder name -> camera name) from ``FOLDER=CAMERA`` pairs as a command line
    gives them: pairs separated by commas or spaces, in one string or several, and, for a
    repeated option (argparse's ``action="append", nargs="+"``), lists of such strings; every pair
    counts.

    Raises:
      InputError (field ``--camera-map``): a pair without ``=`` or with an empty side; a folder
      given twice with different cameras (the same pair twice is kept once).
    """
    out: dict[str, str] = {}
    for item in _flatten(values):
        for pair in re.split(r"[,\s]+", item.strip()):
            if not pair:
                continue
            folder, sep, camera = pair.partition("=")
            folder, camera = folder.strip(), camera.strip()
            if not sep or not folder or not camera or "=" in camera:
                raise InputError(
                    f"expected FOLDER=CAMERA pairs separated by commas or spaces, got {pair!r}",
                    field="--camera-map",
                )
            if out.get(folder, camera) != camera:
                raise InputError(
                    f"folder {folder!r} is given two cameras: {out[folder]!r} and {camera!r}",
                    field="--camera-map",
                )
            out[folder] = camera
    return out


def _flatten(values: Any) -> list[str]:
    if isinstance(values, str):
        return [values]
    if values is None:
        return []
    return [s for value in values for s in _flatten(value)]


# --------------------------------------------------------------------------- reading helpers


# Suffixes that tools add to camera folder names (Pose2Sim's cam01_json, image folders' _img):
# with a rig, a folder that is not a camera's name but is one once such a suffix is stripped
# belongs to that camera.
CAMERA_FOLDER_SUFFIXES = ("_json", "_img", "_images", "_keypoints", "-json")


def _camera_folders(
    root: Path, cameras: Sequence[str] | None, rig: Any, camera_map: Mapping[str, str] | None = None
) -> tuple[list[str], list[str]]:
    """The camera folders to read and their camera names, in camera-axis order; checks them
    against the folders and the rig. Only these folders are read (selection before loading)."""
    try:
        entries = sorted(root.iterdir())
    except FileNotFoundError:
        raise InputError("no such folder", file=root) from None
    except NotADirectoryError:
        raise InputError("not a folder (OpenPose recordings are folders)", file=root) from None
    except OSError as e:
        raise InputError(f"cannot list ({e.strerror})", file=root) from None
    folders = [p.name for p in entries if p.is_dir() and not p.name.startswith(".")]
    if not folders:
        stray = [p.name for p in entries if p.suffix.lower() == ".json"]
        hint = (
            f" It holds JSON files (e.g. {stray[0]}): give the folder ABOVE the camera folders."
            if stray
            else ""
        )
        raise InputError(
            "no camera subfolders: expected one subfolder per camera, each holding that "
            f"camera's per-frame JSON files.{hint}",
            file=root,
            field="cameras",
        )
    rig_names = None if rig is None else [str(n) for n in rig.names]
    camera_map = dict(camera_map or {})
    for folder in camera_map:
        if folder not in folders:
            raise InputError(
                f"the camera map names folder {folder!r}, which is not here; folders: {folders}",
                file=root,
                field="camera_map",
            )
    name_of = {f: _camera_name(f, camera_map, rig_names) for f in folders}
    if len(set(name_of.values())) != len(name_of):
        raise InputError(f"two folders map to one camera: {name_of}", file=root, field="camera_map")
    folder_of = {n: f for f, n in name_of.items()}
    if cameras is not None:
        names = [str(c) for c in cameras]
        if not names:
            raise InputError("no cameras selected", file=root, field="cameras")
        if len(set(names)) != len(names):
            raise InputError(f"duplicate camera names {names}", file=root, field="cameras")
        for name in names:
            if name not in folder_of:
                raise InputError(
                    f"no camera folder of that name; the folder has {folders}",
                    file=root,
                    camera=name,
                    field="cameras",
                )
    elif rig_names is not None:
        names = sorted(folder_of, key=lambda n: rig_names.index(n) if n in rig_names else -1)
    else:
        names = [name_of[f] for f in folders]
    if rig_names is not None:
        unknown = [n for n in names if n not in rig_names]
        if unknown:
            raise InputError(
                f"camera folders {[folder_of[n] for n in unknown]} are not cameras of the rig. "
                f"Folders: {folders}; rig cameras: {rig_names} (pass cameras= / --cameras to read "
                "some folders only, or camera_map= / --camera-map FOLDER=CAMERA to name them)",
                file=root,
                camera=unknown[0],
                field="cameras",
            )
    return [folder_of[n] for n in names], names


def _camera_name(folder: str, camera_map: dict[str, str], rig_names: list[str] | None) -> str:
    if folder in camera_map:
        return str(camera_map[folder])
    if rig_names is None or folder in rig_names:
        return folder
    for suffix in CAMERA_FOLDER_SUFFIXES:
        if folder.endswith(suffix) and folder[: -len(suffix)] in rig_names:
            return folder[: -len(suffix)]
    return folder


def _frame_files(cam_dir: Path, camera: str) -> list[Path]:
    """The ``.json`` files of one camera folder (subfolders and other files are not frames)."""
    try:
        return [
            p
            for p in cam_dir.iterdir()
            if p.suffix.lower() == ".json" and not p.name.startswith(".") and p.is_file()
        ]
    except OSError as e:
        raise InputError(f"cannot list ({e.strerror})", file=cam_dir, camera=camera) from None


def _natural_key(name: str) -> tuple:
    # re.split with a group alternates text and digit runs, so equal positions hold equal types.
    return tuple(int(s) if i % 2 else s for i, s in enumerate(re.split(r"(\d+)", name)))


def _number_in(name: str) -> int | None:
    """The frame number in an OpenPose file name, or None when it has none."""
    if not name.endswith(SUFFIX):
        return None
    match = re.search(r"(\d+)\D*$", name[: -len(SUFFIX)])
    return None if match is None else int(match.group(1))


def _frame_numbers(root: Path, files: dict[str, list[Path]]) -> dict[str, dict[int, Path]]:
    """camera -> {frame number: file} (module docstring: names, else natural order)."""
    numbered = {p: _number_in(p.name) for paths in files.values() for p in paths}
    with_number = [p for p, n in numbered.items() if n is not None]
    without = [p for p, n in numbered.items() if n is None]
    if with_number and without:
        raise InputError(
            f"frame numbers come from names ending in '<digits>{SUFFIX}' (e.g. "
            f"{with_number[0].parent.name}/{with_number[0].name}), but this file has no such "
            "name; rename it or move it out, so that frames align across cameras",
            file=without[0],
            camera=without[0].parent.name,
        )
    out: dict[str, dict[int, Path]] = {}
    for camera, paths in files.items():
        per_cam: dict[int, Path] = {}
        if with_number:
            for p in sorted(paths):
                n = numbered[p]
                if n in per_cam:
                    raise InputError(
                        f"two files for frame {n}: {per_cam[n].name} and {p.name}",
                        file=p,
                        frame=n,
                        camera=camera,
                    )
                per_cam[n] = p
        else:
            for i, p in enumerate(sorted(paths, key=lambda p: _natural_key(p.name))):
                per_cam[i] = p
        out[camera] = per_cam
    return out


def _people(path: Path, frame: int, camera: str) -> list[np.ndarray | None]:
    """The ``pose_keypoints_2d`` of every person entry in one file, in file order: a flat float64
    array (3K,), or None for an entry with no keypoints (an empty list, or an empty object ``{}``
    as Pose2Sim's person association writes for a person one camera does not see)."""
    data = load_json(path)
    err = lambda reason, field: InputError(  # noqa: E731
        reason, file=path, frame=frame, camera=camera, field=field
    )
    if not isinstance(data, dict):
        raise err(f"expected a JSON object with 'people', got {type(data).__name__}", None)
    if "people" not in data:
        raise err("missing field", "people")
    people = data["people"]
    if not isinstance(people, list):
        raise err(f"expected a list, got {type(people).__name__}", "people")
    out = []
    for p, person in enumerate(people):
        field = f"people[{p}].pose_keypoints_2d"
        if not isinstance(person, dict):
            raise err(f"expected an object, got {type(person).__name__}", f"people[{p}]")
        if not person:
            out.append(None)
            continue
        if "pose_keypoints_2d" not in person:
            raise err("missing field", field)
        flat = person["pose_keypoints_2d"]
        if not isinstance(flat, list):
            raise err(f"expected a list of numbers, got {type(flat).__name__}", field)
        if not flat:
            out.append(None)
            continue
        if len(flat) % 3:
            raise err(f"{len(flat)} numbers: expected x, y, c for each keypoint", field)
        try:
            arr = np.array(flat)
        except (ValueError, TypeError, OverflowError):
            arr = None
        if arr is None or arr.dtype.kind not in "fi" or arr.shape != (len(flat),):
            for i, v in enumerate(flat):
                if not is_number(v):
                    raise err(f"expected a number, got {v!r}"[:200], f"{field}[{i}]")
            arr = np.array([to_float(v) for v in flat])
        out.append(arr.astype(np.float64))
    return out


def _count_hint(K: int) -> str:
    """What files of K keypoints hold, for the error naming a wrong source layout."""
    if K not in LAYOUT_OF_COUNT:
        return ""
    names = (LAYOUT_OF_COUNT[K], *SHARED_COUNTS.get(K, ()))
    return f"; files of {K} keypoints are {' or '.join(names)}"


def _detect_count(size: int, path: Path, frame: int, camera: str, person: int) -> int:
    K = size // 3
    if K not in LAYOUT_OF_COUNT:
        raise InputError(
            f"{K} keypoints per person: no known layout has that many "
            f"({', '.join(f'{k}: {v}' for k, v in LAYOUT_OF_COUNT.items())}); pass source_layout=",
            file=path,
            frame=frame,
            camera=camera,
            field=f"people[{person}].pose_keypoints_2d",
        )
    return K
