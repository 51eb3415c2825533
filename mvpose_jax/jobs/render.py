"""Drawing infer's 3D poses over each camera's view (images or an mp4), and 3D figures."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import NamedTuple

from mvpose_jax.data.recording import recording_fps
from mvpose_jax.errors import InputError
from mvpose_jax.jobs.common import DetectionsSource, RigSource, poses_and_detections


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Attributes:
    rig, detections: the recording infer read; poses: its poses.npz / poses.json (or folder).
    out: a folder (per-frame PNGs, figures) or an .mp4 file.
    frames: frames to draw (None: every ``every``-th frame).
    images: folder of the camera images (the recording's image names, relative to it; None: a
      white canvas).
    scale: size of each camera view; fps: the mp4's frame rate (None: the recording's, else 30).
    figures_3d: also a 3D skeleton figure per frame (folder output).
    """

    rig: RigSource
    detections: DetectionsSource
    poses: str
    out: str
    frames: tuple[int, ...] | None = None
    every: int = 1
    images: str | None = None
    scale: float = 0.5
    fps: float | None = None
    figures_3d: bool = False


class Rendered(NamedTuple):
    """Frames drawn, and where."""

    frames: int
    out: Path


def render(config: RenderConfig) -> Rendered:
    """Draws the frames asked for (a progress bar on stderr)."""
    import cv2
    import numpy as np

    from mvpose_jax.data.files import check_writable
    from mvpose_jax.progress import progress_bar
    from mvpose_jax.render import (
        VideoWriter,
        draw_view,
        save_figure,
        skeleton_figure,
        tile,
        write_image,
    )

    check_writable(config.out, folder=Path(config.out).suffix.lower() != ".mp4")
    poses, rec, rig = poses_and_detections(config.rig, config.detections, config.poses)
    F = rec.num_frames
    if config.every < 1 or config.scale <= 0:
        raise InputError("--every must be >= 1 and --scale > 0", field="--every/--scale")
    frames = list(config.frames) if config.frames else list(range(0, F, config.every))
    bad = [f for f in frames if not 0 <= f < F]
    if bad:
        raise InputError(f"frames {bad} are outside 0..{F - 1}", frame=bad[0], field="--frames")
    out = Path(config.out)
    video = out.suffix.lower() == ".mp4"
    xy, score = np.asarray(rec.detections.xy), np.asarray(rec.detections.score)
    count = np.asarray(rec.detections.count)
    P = poses.identity.shape[2]

    def image_of(f, c):
        if not config.images or rec.image_names is None:
            return None
        path = Path(config.images) / str(rec.image_names[f, c])
        img = cv2.imread(str(path))
        if img is None:
            raise InputError("cannot read this image", file=path, frame=f, camera=rec.cameras[c])
        return img

    def picture(f):
        v = poses.poses.valid[f]
        views = []
        for c in range(len(rec.cameras)):
            n = int(count[f, c])
            ident = poses.identity[f, c, :n] if n <= P else np.full(n, -1)
            xyz = np.where(v[:, None, None], poses.poses.xyz[f], np.nan)
            views.append(
                draw_view(
                    rig,
                    c,
                    rec.layout,
                    image=image_of(f, c),
                    detections=(xy[f, c, :n], score[f, c, :n]),
                    identity=ident,
                    xyz=xyz,
                    keypoint_valid=poses.poses.keypoint_valid[f] & v[:, None],
                    colours=None if poses.track is None else poses.track[f],
                    scale=config.scale,
                )
            )
        img = tile(views)
        cv2.putText(
            img,
            f"frame {f}",
            (8, img.shape[0] - 10),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.6,
            (40, 40, 40),
            1,
            cv2.LINE_AA,
        )
        return img

    written = 0
    if video:
        with VideoWriter(out, config.fps or recording_fps(rec.timestamps)) as writer:
            for f in progress_bar(frames, desc="render", unit="frame"):
                writer.write(picture(f))
                written += 1
        return Rendered(written, out)
    for f in progress_bar(frames, desc="render", unit="frame"):
        write_image(out / f"frame_{f:06d}.png", picture(f))
        if config.figures_3d:
            v = poses.poses.valid[f]
            panels = {"ours": (poses.poses.xyz[f][v], poses.poses.keypoint_valid[f][v])}
            if rec.ground_truth is not None:
                gv = np.asarray(rec.ground_truth.valid[f])
                panels = {
                    "ground truth": (
                        np.asarray(rec.ground_truth.xyz[f])[gv],
                        np.asarray(rec.ground_truth.keypoint_valid[f])[gv],
                    ),
                    **panels,
                }
            save_figure(
                skeleton_figure(panels, rec.layout, rig=rig, title=f"frame {f}"),
                out / f"frame_{f:06d}_3d.png",
            )
        written += 1
    return Rendered(written, out)
