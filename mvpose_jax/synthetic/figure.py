"""A figure of one frame of a recording: 2D detections per camera and the 3D ground truth.

    python -m mvpose_jax.synthetic.figure --rig panoptic5 --people 4 --out results/synthetic_frame.png
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mvpose_jax.cameras import Rig, camera_centres, up_vector
from mvpose_jax.data.recording import Recording
from mvpose_jax.skeletons import get_layout


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
        fps = np.sum((recording.identity[frame, c, :n] < 0)) if recording.identity is not None else 0
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
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, format="png")
        # mkstemp creates the file private (0600); give it the usual permissions.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    finally:
        plt.close(fig)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Draw one frame of a synthetic recording.")
    parser.add_argument("--rig", default="panoptic5", help="preset name or calibration file")
    parser.add_argument("--people", type=int, default=4)
    parser.add_argument("--frames", type=int, default=150, help="frames to simulate")
    parser.add_argument("--frame", type=int, default=-1, help="frame to draw (default: the last)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results/synthetic_frame.png")
    args = parser.parse_args(argv)

    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.synthetic.generate import generate_recording

    rig = load_rig(args.rig)
    rec = generate_recording(rig, num_people=args.people, num_frames=args.frames, seed=args.seed)
    frame = args.frame % rec.num_frames
    out = render_frame_figure(
        rec, rig, frame, args.out,
        title=f"synthetic {args.rig}: {args.people} people, frame {frame}, seed {args.seed}",
    )  # fmt: skip
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
