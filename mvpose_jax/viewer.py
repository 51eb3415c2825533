"""Pose results as a rerun recording (``.rrd``): cameras, detections and skeletons in 3D over time.

`write_rerun` writes one file that rerun's viewer opens (``rerun FILE.rrd``; the web viewer too).
Its entities (``<cam>`` is the camera's name, ``<who>`` is ``track_<id>`` for tracked results and
``person_<g>`` otherwise, ``<p>`` a detected skeleton's index in its view):

* ``/``: static, an ``AnnotationContext``: one class per track (or person slot), whose keypoints
  are the layout's names and whose connections are its bones; the viewer draws the skeletons from
  it. Class ids are the track ids (person slots when untracked); detections that no person
  used get class `UNMATCHED_CLASS_ID`, people of tracked results that no track took (entity
  ``untracked_<g>``) `UNTRACKED_CLASS_ID` (both grey).
* ``world``: static ``ViewCoordinates`` when the rig's up is near a world axis (15 degrees).
* ``world/floor``: static ``LineStrips3D``, a 1 m grid on the floor (``x . up = floor_height``).
* ``world/cameras/<cam>``: static ``Transform3D``, world from camera (x_world = R^T x_cam + c);
  ``world/cameras/<cam>/image``: static ``Pinhole`` (K, the image size, OpenCV's RDF axes).
* ``world/cameras/<cam>/image/detections/<p>``: ``Points2D`` of the detected keypoints (with
  ``detections``), class of the track the skeleton went to.
* ``world/cameras/<cam>/image/reprojections/<who>``: ``Points2D`` of each 3D person projected
  into every camera, lens distortion included (so they lie on the detections, not on the frustum's
  ideal pinhole).
* ``world/people/<who>``: ``Points3D`` of each person's reconstructed keypoints.

Per frame the entities carry ``Points*`` with ``class_ids`` and ``keypoint_ids`` (only existing
keypoints are logged); a person or skeleton that leaves is cleared. Timelines: ``frame``
(sequence) always, ``time`` (seconds) when the results or detections have timestamps or ``fps``
is given. rerun is an optional dependency (``pip install "mvpose-jax[viewer]"``), imported here
only when called.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from mvpose_jax.cameras import Rig, camera_centres, point_depths, project_points, up_vector
from mvpose_jax.data.recording import Recording, convert_layout
from mvpose_jax.errors import InputError
from mvpose_jax.progress import progress_bar
from mvpose_jax.skeletons import get_layout

if TYPE_CHECKING:
    from mvpose_jax.data.poses import PoseResults

# rerun's class ids are 16-bit; the largest two mark detections that no person used, and people
# of tracked results that no track took (track -1).
UNMATCHED_CLASS_ID = 65535
UNTRACKED_CLASS_ID = 65534
# Colours of classes (by id, cycling): a qualitative palette (Tableau 10), readable on rerun's
# dark background.
PALETTE = (
    (78, 121, 167),
    (242, 142, 43),
    (225, 87, 89),
    (118, 183, 178),
    (89, 161, 79),
    (237, 201, 72),
    (176, 122, 161),
    (255, 157, 167),
    (156, 117, 95),
    (186, 176, 172),
)
UNMATCHED_COLOUR = (128, 128, 128)
# Keypoint sizes: 3D in scene units (metres), 2D in screen points (zoom-independent).
POINT_RADIUS_M = 0.025
DETECTION_RADIUS_UI = 2.0
REPROJECTION_RADIUS_UI = 3.5
# Floor grid spacing, metres.
FLOOR_SPACING_M = 1.0
# Frames projected per jit call (padded to it, so one compile serves any length).
_PROJECT_BATCH = 256


def write_rerun(
    path: str | os.PathLike,
    poses: PoseResults,
    rig: Rig,
    *,
    detections: Recording | None = None,
    floor_height: float | None = None,
    fps: float | None = None,
    recording_name: str | None = None,
    spawn: bool = False,
    progress: bool = False,
) -> Path:
    """Writes pose results (and optionally their detections) as a rerun recording, atomically.

    Args:
      path: the ``.rrd`` file to write (its folder is made).
      poses: the results: xyz (F, G, K, 3) metres; every camera of ``poses.cameras`` must be in
        the rig.
      rig: the calibration; every camera is drawn and every person reprojected into it.
      detections: optional 2D detections of at least F frames, cameras of the rig (converted to
        the results' layout when it differs): those the results were made from, as
        ``poses.identity`` names each skeleton's person by its index in them.
      floor_height: the floor along the rig's up (`cameras.up_vector`), metres; None: the median
        over people and frames of the lowest keypoint's height (no floor without people, nor
        when the rig's up cannot be inferred).
      fps: frame rate for the ``time`` timeline when neither poses nor detections have timestamps.
      recording_name: the name shown by the viewer (default: the file's stem).
      spawn: then open the file in rerun's viewer (needs a display).
      progress: report the frames written (`progress.progress_bar`).
    Returns:
      the path written.
    Raises:
      InputError naming the field: cameras unknown to the rig, too few detection frames, track
        ids beyond 16 bits. ImportError naming the extra to install when rerun is missing.
    """
    rr = _import_rerun()
    path = Path(path)
    layout = get_layout(poses.layout)
    num_frames = int(np.shape(poses.poses.valid)[0])
    for name in poses.cameras:
        if name not in rig.names:
            raise InputError(
                f"not a camera of the rig {list(rig.names)}", camera=name, field="cameras"
            )
    if detections is not None:
        detections = _checked_detections(detections, rig, num_frames, poses.layout)
    who, class_ids = _people_keys(poses)
    times = _frame_times(poses, detections, fps, num_frames)
    try:
        up = up_vector(rig)
    except InputError:  # cameras that disagree on up: no floor and no world axes, still a file
        up, floor_height = None, None
    else:
        if floor_height is None:
            floor_height = floor_from_people(poses, up)
    views = _layout_of_views(
        rig,
        up=up,
        target=_people_centre(poses, rig),
        timeline="frame" if times is None else "time",
        floor=floor_height is not None,
    )

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    # mkstemp makes the file private (0600); give it the permissions open() would have.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        rec = rr.RecordingStream("mvpose-jax")
        rec.save(tmp, default_blueprint=views)
        # Only the data's own timelines: the wall clock of writing means nothing to a viewer.
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        rec.send_recording_name(recording_name or path.stem)
        _log_static(rr, rec, rig, class_ids, layout, up, floor_height)
        with progress_bar(
            total=num_frames, desc="viewer", unit="frame", disable=not progress
        ) as bar:
            _log_frames(rr, rec, poses, rig, detections, who, times, bar)
        rec.flush()
        rec.disconnect()
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    if spawn:
        subprocess.Popen([sys.executable, "-m", "rerun", str(path)])
    return path


def floor_from_people(poses: PoseResults, up: np.ndarray) -> float | None:
    """The median over people and frames of the lowest keypoint's height along ``up`` (metres).

    A rough floor for display (the feet's keypoints sit a few cm above the real floor); None when
    no person has a keypoint. `floor.estimate_floor_from_detections` measures the floor properly from detections.
    """
    xyz = np.asarray(poses.poses.xyz, np.float64)
    ok = (
        np.asarray(poses.poses.keypoint_valid, bool)
        & np.asarray(poses.poses.valid, bool)[..., None]
    )
    heights = np.where(ok, xyz @ up, np.inf).min(axis=-1)  # (F, G)
    heights = heights[np.isfinite(heights)]
    return float(np.median(heights)) if heights.size else None


# --------------------------------------------------------------------------- what is logged


def _log_static(rr, rec, rig: Rig, class_ids, layout, up, floor_height) -> None:
    classes = [
        rr.ClassDescription(
            info=rr.AnnotationInfo(id=int(i), label=label, color=_colour(i)),
            keypoint_annotations=[
                rr.AnnotationInfo(id=k, label=name) for k, name in enumerate(layout.keypoints)
            ],
            keypoint_connections=[(int(a), int(b)) for a, b in layout.bones],
        )
        for i, label in class_ids.items()
    ]
    rec.log("/", rr.AnnotationContext(classes), static=True)

    axes = None if up is None else _axis_aligned_view(rr, up)
    if axes is not None:
        rec.log("world", axes, static=True)
    if floor_height is not None:
        rec.log(
            "world/floor",
            rr.LineStrips3D(_floor_grid(rig, up, floor_height), colors=[(90, 90, 90)]),
            static=True,
        )

    R, K = np.asarray(rig.R, np.float64), np.asarray(rig.K, np.float64)
    centres, size = np.asarray(camera_centres(rig), np.float64), np.asarray(rig.size)
    # The frusta's depth: a tenth of the rig's spread, so they are seen but do not cross the room.
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=-1).max())
    plane = max(0.1 * spread, 0.05)
    for c, name in enumerate(rig.names):
        cam = _camera_path(name)
        # world_from_cam: x_world = R^T x_cam + centre (the inverse of x_cam = R x_world + t).
        rec.log(
            cam,
            rr.Transform3D(
                translation=centres[c],
                mat3x3=R[c].T,
                relation=rr.TransformRelation.ParentFromChild,
            ),
            static=True,
        )
        rec.log(
            f"{cam}/image",
            rr.Pinhole(
                image_from_camera=K[c],
                resolution=size[c],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=plane,
            ),
            static=True,
        )
        # The image's border, so that the 2D view shows where the picture ends.
        rec.log(
            f"{cam}/image/border",
            rr.Boxes2D(mins=[0.0, 0.0], sizes=size[c], colors=[(90, 90, 90)]),
            static=True,
        )


def _log_frames(rr, rec, poses, rig: Rig, detections, who, times, bar) -> None:
    xyz = np.asarray(poses.poses.xyz, np.float32)
    valid = np.asarray(poses.poses.valid, bool)
    kp_valid = np.asarray(poses.poses.keypoint_valid, bool) & valid[..., None]
    cams = [_camera_path(n) for n in rig.names]
    res_cam = {n: c for c, n in enumerate(poses.cameras)}
    identity = np.asarray(poses.identity)
    present: set[str] = set()
    for first, px, in_front in _projections(rig, xyz):
        for i in range(len(px[0])):
            f = first + i
            rec.set_time("frame", sequence=f)
            if times is not None:
                rec.set_time("time", duration=float(times[f]))
            now: dict[str, Any] = {}
            for g in np.nonzero(valid[f])[0]:
                k = np.nonzero(kp_valid[f, g])[0]
                if not k.size:
                    continue
                cls, key = who[f][g]
                now[f"world/people/{key}"] = rr.Points3D(
                    xyz[f, g, k],
                    class_ids=cls,
                    keypoint_ids=k,
                    radii=POINT_RADIUS_M,
                    show_labels=False,
                )
                for c, cam in enumerate(cams):
                    kc = k[in_front[c, i, g, k]]
                    if kc.size:
                        now[f"{cam}/image/reprojections/{key}"] = rr.Points2D(
                            px[c, i, g, kc],
                            class_ids=cls,
                            keypoint_ids=kc,
                            radii=rr.Radius.ui_points(REPROJECTION_RADIUS_UI),
                            show_labels=False,
                        )
            if detections is not None:
                det = detections.detections
                for c, name in enumerate(detections.cameras):
                    cam = _camera_path(name)
                    rc = res_cam.get(name)
                    for p in range(int(det.count[f, c])):
                        k = np.nonzero(np.asarray(det.score[f, c, p]) > 0)[0]
                        if not k.size:
                            continue
                        g = -1
                        if rc is not None and p < identity.shape[2]:
                            g = int(identity[f, rc, p])
                        cls = who[f][g][0] if g >= 0 and g in who[f] else UNMATCHED_CLASS_ID
                        now[f"{cam}/image/detections/{p}"] = rr.Points2D(
                            np.asarray(det.xy[f, c, p])[k],
                            class_ids=cls,
                            keypoint_ids=k,
                            radii=rr.Radius.ui_points(DETECTION_RADIUS_UI),
                            show_labels=False,
                        )
            # Whoever left since the last frame is cleared, or the viewer would keep showing them.
            for gone in sorted(present - now.keys()):
                rec.log(gone, rr.Clear(recursive=False))
            for entity, archetype in now.items():
                rec.log(entity, archetype)
            present = set(now)
            bar.update(1)


# --------------------------------------------------------------------------- helpers


def _layout_of_views(
    rig: Rig, *, up: np.ndarray | None, target: np.ndarray, timeline: str, floor: bool
):
    """The viewer's opening layout: the 3D scene beside a grid of the cameras' images.

    The 3D eye looks down at ``target`` from beyond the first two cameras; with a floor of ours,
    rerun's own grid (at the world's origin, not on the floor) is hidden.
    """
    import rerun.blueprint as rrb

    centres = np.asarray(camera_centres(rig), np.float64)
    spread = max(float(np.linalg.norm(centres - target, axis=-1).max()), 1.0)
    # Between the first two cameras (around the people on a ring of cameras), not behind one.
    away = centres[: min(2, len(centres))].mean(axis=0) - target
    if up is not None:
        away -= (away @ up) * up
    away /= max(float(np.linalg.norm(away)), 1e-9)
    lift = np.zeros(3) if up is None else up
    eye = rrb.EyeControls3D(
        position=target + spread * (1.2 * away + 1.0 * lift), look_target=target, eye_up=up
    )
    cameras = [rrb.Spatial2DView(origin=f"{_camera_path(n)}/image", name=n) for n in rig.names]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(
                origin="world",
                name="3D",
                eye_controls=eye,
                line_grid=rrb.LineGrid3D(visible=not floor),
            ),
            rrb.Grid(*cameras),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=timeline),
        collapse_panels=True,
    )


def _import_rerun():
    try:
        import rerun as rr
    except ImportError as e:
        raise ImportError(
            'the viewer needs rerun: pip install "mvpose-jax[viewer]" (or pip install rerun-sdk)'
        ) from e
    return rr


def _checked_detections(rec: Recording, rig: Rig, num_frames: int, layout: str) -> Recording:
    for name in rec.cameras:
        if name not in rig.names:
            raise InputError(
                f"detections of a camera not in the rig {list(rig.names)}",
                camera=name,
                field="detections",
            )
    if rec.num_frames < num_frames:
        raise InputError(
            f"detections have {rec.num_frames} frames, the results {num_frames}",
            field="detections",
        )
    return convert_layout(rec, layout) if rec.layout != layout else rec


def _people_keys(poses: PoseResults) -> tuple[list[dict[int, tuple[int, str]]], dict[int, str]]:
    """Per frame, each valid person's (class id, entity name); and every class id's label."""
    valid = np.asarray(poses.poses.valid, bool)
    track = None if poses.track is None else np.asarray(poses.track)
    who: list[dict[int, tuple[int, str]]] = []
    labels: dict[int, str] = {}
    for f in range(valid.shape[0]):
        keys = {}
        for g in np.nonzero(valid[f])[0]:
            if track is not None and track[f, g] < 0:
                keys[int(g)] = (UNTRACKED_CLASS_ID, f"untracked_{int(g)}")
                labels[UNTRACKED_CLASS_ID] = "untracked"
            elif track is not None:
                t = int(track[f, g])
                if t >= UNTRACKED_CLASS_ID:
                    raise InputError(
                        f"track id {t} is beyond rerun's 16-bit class ids", frame=f, field="track"
                    )
                keys[int(g)] = (t, f"track_{t}")
                labels[t] = f"track {t}"
            else:  # untracked results: the slot
                keys[int(g)] = (int(g), f"person_{int(g)}")
                labels.setdefault(int(g), f"person {int(g)}")
        who.append(keys)
    labels[UNMATCHED_CLASS_ID] = "unmatched"
    return who, labels


def _frame_times(poses, detections, fps, num_frames) -> np.ndarray | None:
    if poses.timestamps is not None:
        return np.asarray(poses.timestamps, np.float64)
    if detections is not None and detections.timestamps is not None:
        return np.asarray(detections.timestamps, np.float64)[:num_frames]
    if fps is not None:
        return np.arange(num_frames) / float(fps)
    return None


@jax.jit
def _project_batch(rig: Rig, xyz: jax.Array) -> tuple[jax.Array, jax.Array]:
    # (C, B, G, K, 2) distorted pixels; (C, B, G, K) in front of the camera.
    return project_points(rig, xyz), point_depths(rig, xyz) > 0.0


def _projections(rig: Rig, xyz: np.ndarray) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """Per batch of frames: (first frame, pixels (C, B, G, K, 2), in front (C, B, G, K))."""
    num_frames = xyz.shape[0]
    for first in range(0, num_frames, _PROJECT_BATCH):
        batch = xyz[first : first + _PROJECT_BATCH]
        padded = np.zeros((_PROJECT_BATCH,) + batch.shape[1:], np.float32)
        padded[: len(batch)] = batch
        px, in_front = _project_batch(rig, padded)
        yield first, np.asarray(px)[:, : len(batch)], np.asarray(in_front)[:, : len(batch)]


def _people_centre(poses: PoseResults, rig: Rig) -> np.ndarray:
    """The median of every reconstructed keypoint (the cameras' mean centre without any): (3,)."""
    ok = (
        np.asarray(poses.poses.keypoint_valid, bool)
        & np.asarray(poses.poses.valid, bool)[..., None]
    )
    if not ok.any():
        return np.asarray(camera_centres(rig), np.float64).mean(axis=0)
    return np.median(np.asarray(poses.poses.xyz, np.float64)[ok], axis=0)


def _camera_path(name: str) -> str:
    import rerun as rr

    return f"world/cameras/{rr.escape_entity_path_part(name)}"


def _colour(class_id: int) -> tuple[int, int, int]:
    if class_id in (UNMATCHED_CLASS_ID, UNTRACKED_CLASS_ID):
        return UNMATCHED_COLOUR
    return PALETTE[class_id % len(PALETTE)]


def _axis_aligned_view(rr, up: np.ndarray):
    """rerun's world axes when ``up`` is within 15 degrees of a world axis, else None.

    Only the viewer's opening camera turns with them (not the data): an up inferred from the
    cameras (`cameras.up_vector`) is often some degrees off the axis the calibration meant.
    """
    axis = int(np.argmax(np.abs(up)))
    if abs(up[axis]) < np.cos(np.deg2rad(15.0)):
        return None
    name = f"RIGHT_HAND_{'XYZ'[axis]}_{'UP' if up[axis] > 0 else 'DOWN'}"
    return getattr(rr.ViewCoordinates, name)


def _floor_grid(rig: Rig, up: np.ndarray, height: float) -> list[np.ndarray]:
    """Lines of a square grid on the floor under the cameras: a list of (2, 3) segments."""
    centres = np.asarray(camera_centres(rig), np.float64)
    # Two floor directions: perpendicular to up, starting from the world axis least along it.
    e1 = np.cross(up, np.eye(3)[int(np.argmin(np.abs(up)))])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    middle = centres.mean(axis=0)
    middle = middle - (middle @ up - height) * up  # onto the floor
    flat = (centres - middle) @ np.stack([e1, e2], axis=1)  # (C, 2) floor coordinates
    half = max(np.ceil(np.abs(flat).max() / FLOOR_SPACING_M), 2.0) * FLOOR_SPACING_M
    ticks = np.arange(-half, half + 1e-9, FLOOR_SPACING_M)
    lines = []
    for a, b in ((e1, e2), (e2, e1)):
        for s in ticks:
            lines.append(np.stack([middle + s * a - half * b, middle + s * a + half * b]))
    return lines
