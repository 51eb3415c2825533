"""Pictures of results: 2D overlays per camera (OpenCV) and 3D skeleton figures (matplotlib).

Everything here is an output edge: pure drawing on numpy arrays, plus writers that go through a
temporary file and a rename (a figure or video is never left half-written).

* `draw_view`: one camera image (or a blank canvas) with the detected skeletons (thin) and the
  3D people reprojected into it (thick), coloured by person.
* `write_image`, `VideoWriter`: atomic PNG/JPEG and mp4.
* `skeleton_figure`: 3D skeletons of one frame in side-by-side panels (e.g. ground truth, ours,
  triangulation), the rig's up pointing up.
* `curves_figure`: training curves (loss against step) of several runs.
* `render_frame_figure`: one frame of a recording, the detections in every camera and the 3D
  ground truth, written as PNG (``mvpose-jax synthetic-figure`` draws a simulated one).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from mvpose_jax.cameras import Rig, camera_centres, project_points, up_vector
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import get_layout

if TYPE_CHECKING:
    from mvpose_jax.data.recording import Recording

# Distinct BGR colours (Okabe-Ito without black) for people 0, 1, ...; grey for unassigned.
PALETTE_BGR = (
    (0, 159, 230),
    (233, 180, 86),
    (115, 158, 0),
    (66, 228, 240),
    (178, 114, 0),
    (0, 94, 213),
    (167, 121, 204),
)
UNASSIGNED_BGR = (150, 150, 150)


def person_colour(i: int) -> tuple[int, int, int]:
    """The BGR colour of person ``i`` (grey for -1)."""
    return UNASSIGNED_BGR if i < 0 else PALETTE_BGR[i % len(PALETTE_BGR)]


def _rgb(i: int) -> tuple[float, float, float]:
    b, g, r = person_colour(i)
    return (r / 255, g / 255, b / 255)


def draw_view(
    rig: Rig,
    camera: int,
    layout: str,
    *,
    image: np.ndarray | None = None,
    detections: tuple[np.ndarray, np.ndarray] | None = None,
    identity: np.ndarray | None = None,
    xyz: np.ndarray | None = None,
    keypoint_valid: np.ndarray | None = None,
    colours: np.ndarray | None = None,
    scale: float = 1.0,
) -> np.ndarray:
    """One camera's picture: detections and reprojected 3D people.

    Args:
      rig: the cameras; ``camera`` indexes it.
      layout: keypoint layout name (for the bones).
      image: (H, W, 3) uint8 BGR background (default: a white canvas of the camera's size).
      detections: (xy (P, K, 2) pixels, score (P, K)) of this camera (thin lines, 0 = missing).
      identity: (P,) the person of each detection (its colour), -1 unassigned (grey).
      xyz: (G, K, 3) metres, people to reproject (thick lines, person g in colour g).
      keypoint_valid: (G, K) which keypoints of xyz exist (default all).
      colours: (G,) the colour index of each person (its track id, so a person keeps a colour
        over time; -1 grey); default: the person's index g. Detections take their person's.
      scale: resize factor of the output (and everything drawn).
    Returns:
      (H·scale, W·scale, 3) uint8 BGR.
    """
    lay = get_layout(layout)
    w, h = (int(v) for v in np.asarray(rig.size)[camera])
    canvas = (
        np.full((h, w, 3), 255, np.uint8)
        if image is None
        else np.ascontiguousarray(image[..., :3], np.uint8)
    )
    if scale != 1.0:
        canvas = cv2.resize(
            canvas, (max(1, round(canvas.shape[1] * scale)), max(1, round(canvas.shape[0] * scale)))
        )
    sx = canvas.shape[1] / w
    sy = canvas.shape[0] / h
    thin = max(1, round(2 * scale))

    def draw(pts, seen, colour, width, radius):
        pts = np.asarray(pts, np.float64) * [sx, sy]
        # Points far outside the image (or not finite) would overflow OpenCV's int coordinates.
        seen = seen & (np.abs(pts) < 1 << 20).all(-1)
        pts = np.round(np.where(seen[:, None], pts, 0.0)).astype(np.int64)
        for a, b in lay.bones:
            if seen[a] and seen[b]:
                cv2.line(
                    canvas,
                    tuple(map(int, pts[a])),
                    tuple(map(int, pts[b])),
                    colour,
                    width,
                    cv2.LINE_AA,
                )
        for k in np.nonzero(seen)[0]:
            cv2.circle(canvas, tuple(map(int, pts[k])), radius, colour, -1, cv2.LINE_AA)

    def colour_of(g: int) -> int:
        if colours is None or g < 0 or g >= len(colours):
            return g if colours is None else -1
        return int(colours[g])

    if detections is not None:
        xy, score = (np.asarray(a) for a in detections)
        for p in range(len(xy)):
            ident = -1 if identity is None else int(identity[p])
            draw(xy[p], score[p] > 0, person_colour(colour_of(ident)), thin, thin + 1)
    if xyz is not None and len(xyz):
        xyz = np.asarray(xyz, np.float32)
        kv = np.ones(xyz.shape[:2], bool) if keypoint_valid is None else np.asarray(keypoint_valid)
        px = np.asarray(project_points(rig.select([rig.names[camera]]), xyz))[0]  # (G, K, 2)
        depth = (np.asarray(rig.R)[camera] @ xyz[..., None])[..., 2, 0] + np.asarray(rig.t)[
            camera, 2
        ]
        for g in range(len(xyz)):
            if kv[g].any():
                draw(
                    px[g],
                    kv[g] & (depth[g] > 0) & np.isfinite(px[g]).all(-1),
                    person_colour(colour_of(g)),
                    3 * thin,
                    2 * thin + 1,
                )
    cv2.putText(
        canvas,
        rig.names[camera],
        (8, 8 + round(20 * scale)),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.7 * scale,
        (40, 40, 40),
        max(1, round(1.5 * scale)),
        cv2.LINE_AA,
    )
    return canvas


def tile(images: Sequence[np.ndarray], columns: int = 3) -> np.ndarray:
    """Images side by side on a grid (each resized to the first one's height), white padded."""
    h = images[0].shape[0]
    resized = [cv2.resize(im, (max(1, round(im.shape[1] * h / im.shape[0])), h)) for im in images]
    w = max(im.shape[1] for im in resized)
    rows = []
    for i in range(0, len(resized), columns):
        row = [
            np.pad(im, [(0, 0), (0, w - im.shape[1]), (0, 0)], constant_values=255)
            for im in resized[i : i + columns]
        ]
        row += (
            [np.full((h, w, 3), 255, np.uint8)] * (columns - len(row))
            if len(resized) > columns
            else []
        )
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)


def _temporary_beside(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    return Path(tmp)


def _publish(tmp: Path, path: Path) -> None:
    os.chmod(tmp, 0o666 & ~_umask())
    os.replace(tmp, path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Writes a BGR image (format from the suffix, e.g. .png, .jpg) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_beside(path)
    try:
        if not cv2.imwrite(str(tmp), image):
            raise InputError("OpenCV could not write this image format", file=path)
        _publish(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


class VideoWriter:
    """An mp4 written frame by frame to a temporary file and renamed when closed without error.

    Usage: ``with VideoWriter(path, fps) as video: video.write(bgr_frame)``.
    """

    def __init__(self, path: str | os.PathLike, fps: float = 25.0):
        self.path = Path(path)
        self.fps = fps
        self._tmp: Path | None = None
        self._writer = None
        self.frames = 0

    def __enter__(self) -> VideoWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = _temporary_beside(self.path)
        return self

    def write(self, frame: np.ndarray) -> None:
        if self._writer is None:
            h, w = frame.shape[:2]
            self._writer = cv2.VideoWriter(
                str(self._tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h)
            )
            if not self._writer.isOpened():
                raise InputError("OpenCV cannot write mp4 here (no mp4v encoder)", file=self.path)
        self._writer.write(frame)
        self.frames += 1

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._writer is not None:
            self._writer.release()
        try:
            if exc_type is None:
                if not self.frames:
                    raise InputError("no frames to write", file=self.path)
                _publish(self._tmp, self.path)
        finally:
            self._tmp.unlink(missing_ok=True)


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Saves a matplotlib figure atomically and closes it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_beside(path)
    try:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
        _publish(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
        plt.close(fig)
    return path


def skeleton_figure(
    panels: Mapping[str, tuple[np.ndarray, np.ndarray]],
    layout: str,
    *,
    rig: Rig | None = None,
    title: str | None = None,
):
    """3D skeletons of one frame, one panel per method, on shared axes.

    Args:
      panels: {panel title: (xyz (G, K, 3) metres, keypoint_valid (G, K))}; person g has colour g
        in every panel, so panels with the same person order compare at a glance.
      layout: keypoint layout name.
      rig: draws the cameras' centres and orients the view by the rig's up vector.
    Returns:
      A matplotlib Figure (save it with `save_figure`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lay = get_layout(layout)
    up = np.asarray(up_vector(rig)) if rig is not None else np.array([0.0, 0.0, 1.0])
    # A right-handed frame with z along up, so matplotlib's vertical axis is the world's up.
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    basis = np.stack([a, np.cross(up, a), up])
    pts_all = [np.asarray(x)[np.asarray(v)] for x, v in panels.values() if np.asarray(v).any()]
    pts_all = np.concatenate(pts_all) @ basis.T if pts_all else np.zeros((1, 3))
    lo, hi = pts_all.min(0), pts_all.max(0)
    centre, half = (lo + hi) / 2, max(0.5, float((hi - lo).max()) / 2 * 1.1)
    fig = plt.figure(figsize=(4.2 * len(panels), 4.4), dpi=110)
    for i, (name, (xyz, kv)) in enumerate(panels.items()):
        ax = fig.add_subplot(1, len(panels), i + 1, projection="3d")
        xyz = np.asarray(xyz) @ basis.T
        kv = np.asarray(kv)
        for g in range(len(xyz)):
            for a_, b_ in lay.bones:
                if kv[g, a_] and kv[g, b_]:
                    ax.plot(*xyz[g, [a_, b_]].T, color=_rgb(g), lw=1.6)
            ax.scatter(*xyz[g, kv[g]].T, color=_rgb(g), s=6)
        if rig is not None:
            cams = np.asarray(camera_centres(rig)) @ basis.T
            ax.scatter(*cams.T, marker="^", color="k", s=14)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.set_title(f"{name} ({int(kv.any(-1).sum())} people)", fontsize=10)
        ax.tick_params(labelsize=6)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def curves_figure(
    histories: Mapping[str, Sequence[Mapping[str, float]]],
    keys: Sequence[str] = ("train_loss", "val_loss"),
):
    """Training curves: one panel per run, ``keys`` of its history against the step (log scale).

    Args:
      histories: {run name: FitResult.history}, each record with "step" and the keys.
    Returns:
      A matplotlib Figure.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = max(1, len(histories))
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.2 * rows), dpi=110, squeeze=False)
    for ax, (name, hist) in zip(axes.flat, histories.items(), strict=False):
        steps = [h["step"] for h in hist]
        for key in keys:
            values = [h.get(key, np.nan) for h in hist]
            if np.isfinite(values).any():
                ax.plot(steps, values, marker=".", label=key.replace("_", " "))
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_title(name, fontsize=10)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(histories) :]:
        ax.axis("off")
    fig.tight_layout()
    return fig


def render_frame_figure(
    recording: Recording, rig: Rig, frame: int, path: str | os.PathLike, *, title: str | None = None
) -> Path:
    """Draws one frame and writes it as PNG atomically (temporary file, then rename).

    Each camera panel shows the image frame and the detected skeletons, coloured by true identity
    (false positives grey, dashed), with the noise-free projections of the ground truth as faint
    dots. A 3D panel shows the ground-truth skeletons and the cameras, the rig's up pointing up.

    Args:
      recording: any recording (identity and ground truth are used when present).
      rig: its cameras (for image sizes and the 3D view).
      frame: frame index.
      path: output .png file.
    Returns:
      The path written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    layout = get_layout(recording.layout)
    det = recording.detections
    xy, score, count = (np.asarray(a) for a in (det.xy, det.score, det.count))
    C = len(recording.cameras)
    sizes = np.asarray(rig.size)
    cam_idx = [rig.camera_index(name) for name in recording.cameras]
    # tab10 without its grey, which marks false positives.
    tab = plt.get_cmap("tab10").colors
    colours = [col for i, col in enumerate(tab) if i != 7]
    palette = lambda i: colours[i % len(colours)]  # noqa: E731
    ncol = min(3, C + 1)
    nrow = int(np.ceil((C + 1) / ncol))
    fig = plt.figure(figsize=(5.2 * ncol, 3.6 * nrow), dpi=110)
    grid = fig.add_gridspec(nrow, ncol)
    for c in range(C):
        ax = fig.add_subplot(grid[c // ncol, c % ncol])
        w, h = sizes[cam_idx[c]]
        ax.add_patch(plt.Rectangle((0, 0), w, h, fill=False, color="k", lw=1))
        ax.set_xlim(-0.05 * w, 1.05 * w)
        ax.set_ylim(1.05 * h, -0.05 * h)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        n = int(count[frame, c])
        for p in range(n):
            ident = -1 if recording.identity is None else int(recording.identity[frame, c, p])
            colour = "0.55" if ident < 0 else palette(ident)
            style = "--" if ident < 0 else "-"
            s = score[frame, c, p]
            pts = xy[frame, c, p]
            for a, b in layout.bones:
                if s[a] > 0 and s[b] > 0:
                    ax.plot(pts[[a, b], 0], pts[[a, b], 1], style, color=colour, lw=1.4)
            ok = s > 0
            ax.scatter(pts[ok, 0], pts[ok, 1], s=6 + 10 * s[ok], color=colour, zorder=3)
            if recording.projected is not None and ident >= 0:
                pr = np.asarray(recording.projected)[frame, c, p]
                ax.scatter(pr[ok, 0], pr[ok, 1], s=3, color="k", alpha=0.35, zorder=4)
        fps = np.sum(recording.identity[frame, c, :n] < 0) if recording.identity is not None else 0
        ax.set_title(f"{recording.cameras[c]}: {n} detections ({fps} false)", fontsize=9)

    # The 3D panel takes the rest of the last row.
    ax3 = fig.add_subplot(grid[nrow - 1, C % ncol :], projection="3d")
    up = up_vector(rig)
    axis = np.eye(3)[np.argmin(np.abs(up))]
    e1 = axis - (axis @ up) * up
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    basis = np.stack([e1, e2, up], -1)  # world -> (e1, e2, up) coordinates
    centres = np.asarray(camera_centres(rig))[cam_idx] @ basis
    ax3.scatter(centres[:, 0], centres[:, 1], centres[:, 2], marker="^", color="k", s=20)
    for c in range(C):
        ax3.text(*centres[c], recording.cameras[c], fontsize=6)
    if recording.ground_truth is not None:
        gt = np.asarray(recording.ground_truth.xyz)[frame] @ basis  # (G, K, 3)
        valid = np.asarray(recording.ground_truth.valid)[frame]
        for g in np.flatnonzero(valid):
            for a, b in layout.bones:
                ax3.plot(*gt[g, [a, b]].T, color=palette(g), lw=1.5)
        allp = np.concatenate([gt[valid].reshape(-1, 3), centres])
        floor = gt[valid][..., 2].min() if valid.any() else centres[:, 2].min() - 1.5
        lo, hi = allp.min(0), allp.max(0)
        xx, yy = np.meshgrid(np.linspace(lo[0], hi[0], 2), np.linspace(lo[1], hi[1], 2))
        ax3.plot_surface(xx, yy, np.full_like(xx, floor - 0.07), alpha=0.12, color="0.5")
        span = (hi - lo).max() / 2
        mid = (hi + lo) / 2
        ax3.set_xlim(mid[0] - span, mid[0] + span)
        ax3.set_ylim(mid[1] - span, mid[1] + span)
        ax3.set_zlim(mid[2] - span, mid[2] + span)
    ax3.set_box_aspect((1, 1, 1))
    ax3.set_title("3D ground truth (m, up = z)", fontsize=9)
    ax3.tick_params(labelsize=6)
    fig.suptitle(title or f"frame {frame}", fontsize=11)
    fig.tight_layout()

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_beside(path)
    try:
        # Always PNG, at the figure's own size (no tight bounding box, unlike `save_figure`).
        fig.savefig(tmp, format="png")
        _publish(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
        plt.close(fig)
    return path
