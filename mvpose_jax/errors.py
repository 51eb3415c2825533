"""The project's own exceptions: bad input always says where it is bad."""

from __future__ import annotations


class MvposeError(Exception):
    """Base class of every error this package raises on purpose."""


class InputError(MvposeError, ValueError):
    """Bad input data: names the file, frame, camera and field where known.

    Attributes:
      file: path of the offending file, or None for in-memory input.
      frame: frame index (0-based), or None.
      camera: camera name or index, or None.
      field: name of the offending field (e.g. ``"K"``, ``"keypoints[3]"``), or None.
      reason: what is wrong, in words.
    """

    def __init__(
        self,
        reason: str,
        *,
        file: object = None,
        frame: int | None = None,
        camera: object = None,
        field: str | None = None,
    ):
        self.reason = reason
        self.file = None if file is None else str(file)
        self.frame = frame
        self.camera = camera
        self.field = field
        where = []
        if self.file is not None:
            where.append(f"file {self.file!r}")
        if frame is not None:
            where.append(f"frame {frame}")
        if camera is not None:
            where.append(f"camera {camera!r}")
        if field is not None:
            where.append(f"field {field!r}")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {reason}" if prefix else reason)

    def at(self, **where) -> InputError:
        """Returns a copy with missing location parts filled in (existing ones win)."""
        merged = dict(file=self.file, frame=self.frame, camera=self.camera, field=self.field)
        for k, v in where.items():
            if merged.get(k) is None:
                merged[k] = v
        return InputError(self.reason, **merged)


class MvposeWarning(UserWarning):
    """Base class of the warnings this package gives about input it accepted but changed or
    doubts (the command line prints them as one line each)."""
