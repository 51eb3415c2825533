"""infer's 3D poses written as TRC and C3D marker files (OpenSim, motion capture) or a tidy CSV."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

from mvpose_jax.errors import InputError
from mvpose_jax.jobs.common import RigSource

# An output ending so is a file name (its stem names the files); else a folder.
EXPORT_SUFFIXES = (".trc", ".c3d", ".csv")


@dataclasses.dataclass(frozen=True)
class ExportJob:
    """Attributes:
    poses: infer's poses.npz / poses.json (or their folder).
    formats: "trc", "c3d", "csv", or comma lists of them (`export_formats`).
    out: a folder (poses_track<id>.trc, poses.csv ...) or a file (walk.trc: walk_track<id>.trc ...).
    rig: the calibration infer used (the world's up for the OpenSim axes), or None.
    up: the world's up as "X,Y,Z", instead of the rig's.
    axes: "opensim" (Y up) or "world"; units: "mm" or "m".
    fps: frame rate (None: from the poses' timestamps).
    per_track: one TRC/C3D file per track (else one of every track).
    """

    poses: str
    formats: tuple[str, ...]
    out: str
    rig: RigSource | None = None
    up: str | None = None
    axes: str = "opensim"
    units: str = "mm"
    fps: float | None = None
    per_track: bool = True


class Exported(NamedTuple):
    """The files written, in which folder, and the up direction the OpenSim axes used (None:
    the world axes)."""

    paths: list[Path]
    folder: Path
    up: tuple[float, float, float] | None


def export(job: ExportJob) -> Exported:
    """Reads the poses and writes the files (a progress bar on stderr)."""
    from mvpose_jax.cameras import up_vector
    from mvpose_jax.data.exports import ExportConfig, export_poses
    from mvpose_jax.data.files import check_writable
    from mvpose_jax.data.poses import load_poses

    formats = export_formats(job.formats)
    out = Path(job.out)
    to_file = out.suffix.lower() in EXPORT_SUFFIXES
    check_writable(job.out, folder=not to_file)
    stem = out.with_suffix("") if to_file else out / "poses"
    up = None
    if job.axes == "opensim":
        if job.rig and job.up:
            raise InputError("give the up direction once: --rig or --up, not both", field="--up")
        if job.up:
            up = up_direction(job.up)
        elif job.rig:
            up = tuple(float(v) for v in up_vector(job.rig.load()))
        else:
            raise InputError(
                "the OpenSim axes need the world's up: give --rig (the calibration infer used) "
                "or --up X,Y,Z, or keep the calibration's axes with --axes world",
                field="--rig",
            )
    config = ExportConfig(formats, job.units, job.per_track, job.fps, job.axes, up)
    paths = export_poses(load_poses(job.poses), stem, config, progress=True)
    return Exported(list(paths), stem.parent, up)


def export_formats(values: Sequence[str]) -> tuple[str, ...]:
    """``("trc,c3d", "csv")`` -> ("trc", "c3d", "csv"); an unknown one is an error."""
    from mvpose_jax.data.exports import EXPORT_FORMATS

    formats = []
    for value in values:
        for fmt in value.split(","):
            fmt = fmt.strip().lower()
            if fmt not in EXPORT_FORMATS:
                raise InputError(
                    f"unknown format {fmt!r}; choose from {', '.join(EXPORT_FORMATS)}",
                    field="--format",
                )
            if fmt not in formats:
                formats.append(fmt)
    return tuple(formats)


def up_direction(text: str) -> tuple[float, float, float]:
    """``"X,Y,Z"`` as three numbers."""
    try:
        up = tuple(float(v) for v in text.split(","))
    except ValueError:
        up = ()
    if len(up) != 3:
        raise InputError(f"expected three numbers X,Y,Z, got {text!r}", field="--up")
    return up
