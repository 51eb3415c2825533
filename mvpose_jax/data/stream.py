"""Recordings read a range of frames at a time: memory bounded by the range, not the recording.

`RecordingStream` is what `mvpose_jax.data.formats.open_recording` returns: the recording's
cameras, layout and frame count up front, then `read_frames(start, stop)` (any range) or
`chunks(chunk_frames)` (consecutive ranges) as `Recording` objects whose fields hold only those
frames. Values are checked range by range with the same checks and errors as the whole-file
readers; errors name frames by their place in the whole recording (their number, for OpenPose
folders), never by their place in the range. Scores clipped to 1 are reported in ONE warning per
file, after the last range read (`close`, or the end of `chunks`).

Which formats stream (each reader documents how):
  * ``npz``: every per-frame member is read from the zip a range of rows at a time, stored or
    deflated (`mvpose_jax.data.npz.NpzStream`).
  * OpenPose folders: only the frame files of the range are parsed; the file names of every
    camera folder are listed once (`mvpose_jax.data.openpose.OpenPoseStream`).
  * native and original JSON: one JSON document each, which the standard library parses only
    whole: they are loaded whole and then handed out in ranges (`InMemoryStream`), so memory
    grows with their length. Convert a long recording to ``.npz`` once
    (``mvpose-jax convert``) to read it in bounded memory.
"""

from __future__ import annotations

import abc
import dataclasses
import os
from collections.abc import Iterator, Mapping

from mvpose_jax.data.checks import ClippedScores, warn_clipped
from mvpose_jax.data.recording import Recording, slice_frames


@dataclasses.dataclass(frozen=True)
class ReadReport:
    """What a reader took as it was, for the caller's summary (nothing is dropped unsaid).

    Attributes:
      empty_entries: camera -> person entries without keypoints that were skipped (OpenPose
        files: an empty ``pose_keypoints_2d`` list or an empty object), in the frames read so far.
      missing_frames: camera -> frames of the recording with no file for that camera, read as
        frames where that camera saw nobody (OpenPose folders read with
        ``missing_frames="empty"``).
    """

    empty_entries: Mapping[str, int] = dataclasses.field(default_factory=dict)
    missing_frames: Mapping[str, int] = dataclasses.field(default_factory=dict)

    @property
    def total_empty(self) -> int:
        return sum(self.empty_entries.values())

    @property
    def total_missing(self) -> int:
        return sum(self.missing_frames.values())

    def lines(self) -> list[str]:
        """The counts in words, one line each, for a summary; none when there is nothing to say."""
        out = []
        if self.total_empty:
            per = ", ".join(f"{c} {n}" for c, n in self.empty_entries.items() if n)
            out.append(f"{self.total_empty} skeleton entries without keypoints skipped ({per})")
        if self.total_missing:
            per = ", ".join(f"{c} {n}" for c, n in self.missing_frames.items() if n)
            out.append(f"frames without a file, read as nobody seen: {per}")
        return out


class RecordingStream(abc.ABC):
    """A recording on disk, read a range of frames at a time (see the module docstring).

    Attributes:
      path: the file or folder.
      cameras: C camera names (the camera axis of every range).
      layout: keypoint layout of every range.
      num_frames: F, frames in the recording.
      streamed: True when ranges are read from disk as asked (memory bounded by the range);
        False when the whole recording was loaded (single-document JSON formats).
    A range's person axis P is the file's (npz without camera selection) or the most people in a
    view of that range; the whole recording's P is the largest over its ranges.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        cameras: tuple[str, ...],
        layout: str,
        num_frames: int,
        streamed: bool,
    ):
        self.path = path
        self.cameras = tuple(cameras)
        self.layout = layout
        self.num_frames = int(num_frames)
        self.streamed = streamed
        # Scores clipped to 1 over every range read: one warning per file, when reading ends.
        self.clipped = ClippedScores()

    @abc.abstractmethod
    def read_frames(self, start: int, stop: int) -> Recording:
        """Frames ``start`` to ``stop`` (exclusive), checked.

        Raises:
          InputError naming the file, frame (in the whole recording), camera and field.
        """

    def report(self) -> ReadReport:
        """Counts of what was taken as it was (`ReadReport`); formats that skip nothing report
        none."""
        return ReadReport()

    def chunks(self, chunk_frames: int, *, start: int = 0) -> Iterator[tuple[int, Recording]]:
        """Consecutive ranges of ``chunk_frames`` frames from frame ``start``: yields (first frame,
        `Recording` of the range); the last range may be shorter."""
        if chunk_frames < 1:
            raise ValueError(f"chunk_frames must be at least 1, got {chunk_frames}")
        for first in range(start, self.num_frames, chunk_frames):
            yield first, self.read_frames(first, min(self.num_frames, first + chunk_frames))
        self.finish()

    def finish(self) -> None:
        """Gives the file's one warning about clipped scores, if any were met since the last."""
        warn_clipped(self._source(), self.clipped, stacklevel=3)
        self.clipped = ClippedScores()

    def close(self) -> None:
        """Releases open files (and gives the pending clipping warning)."""
        self.finish()

    def __enter__(self) -> RecordingStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _source(self) -> object:
        """What the clipping warning names."""
        return self.path


class InMemoryStream(RecordingStream):
    """A recording already loaded whole, handed out in ranges (the JSON formats)."""

    def __init__(self, recording: Recording, path: str | os.PathLike):
        super().__init__(
            path,
            cameras=recording.cameras,
            layout=recording.layout,
            num_frames=recording.num_frames,
            streamed=False,
        )
        self.recording = recording

    def read_frames(self, start: int, stop: int) -> Recording:
        return slice_frames(self.recording, start, stop)


class FrameRangeStream(RecordingStream):
    """Frames ``first`` to ``stop`` (exclusive) of another stream, as a recording of their own:
    its frame 0 is the other's frame ``first`` (errors still name the frame in the whole file).
    Closing it closes the other."""

    def __init__(self, inner: RecordingStream, first: int, stop: int):
        if not 0 <= first < stop <= inner.num_frames:
            raise ValueError(f"frames {first}-{stop} are not within 0-{inner.num_frames}")
        super().__init__(
            inner.path,
            cameras=inner.cameras,
            layout=inner.layout,
            num_frames=stop - first,
            streamed=inner.streamed,
        )
        self.inner, self.first = inner, int(first)

    def read_frames(self, start: int, stop: int) -> Recording:
        return self.inner.read_frames(self.first + start, self.first + stop)

    def report(self) -> ReadReport:
        return self.inner.report()

    def close(self) -> None:
        self.inner.close()
