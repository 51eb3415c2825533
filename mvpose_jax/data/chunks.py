"""An ``infer`` run's finished chunks on disk, so an interrupted run keeps its work and resumes.

Layout of the folder (``OUT/chunks/``)::

    manifest.json        {"format": "mvpose-jax.infer-chunks", "version": 1, "frames_total": N,
                          "chunk_frames": n, "settings": {"source.detections": ..., ...}}
    chunk_000000.npz     results of frames 0 .. n-1 (`data.poses.save_poses_chunk`)
    chunk_000001.npz     frames n .. 2n-1
    ...

``settings`` holds every input and setting that changes the results, flat, keyed by their path
in the job's config (``"pipeline.matching.threshold"``), so a refusal names the setting. Chunk ``i`` starts at frame ``i * n``; each is
written atomically once its frames are done, so the finished chunks are always whole files, and
the results of the first ``k`` chunks are the first ``k * n`` frames of the full results.
`ChunkStore.assemble` writes ``poses.npz`` and ``poses.json`` from them (partial when they do not
cover the recording).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any, NamedTuple

from mvpose_jax.data.files import atomic_write_text, read_json, to_jsonable
from mvpose_jax.data.poses import PoseResults, assemble_poses, load_poses_chunk, save_poses_chunk
from mvpose_jax.errors import InputError, MvposeError

FORMAT = "mvpose-jax.infer-chunks"
MANIFEST = "manifest.json"
SMOOTHED = "smoothed"  # chunk files after a transform (smoothing), made while assembling


class Assembled(NamedTuple):
    """What `ChunkStore.assemble` wrote."""

    npz: Path
    json: Path
    frames: int  # frames covered (the recording's frame count unless partial)
    partial: bool


class ChunkStore:
    """The chunk folder of one run (module docstring).

    Args:
      folder: the folder (created by `begin`).
      settings: every input and setting that changes the results, JSON-able, keyed by its
        path in the job's config.
      frames_total: frames in the recording.
      chunk_frames: frames per chunk.
    """

    def __init__(
        self, folder: str | os.PathLike, *, settings: dict, frames_total: int, chunk_frames: int
    ):
        self.folder = Path(folder)
        self.settings = to_jsonable(settings)
        self.frames_total = int(frames_total)
        self.chunk_frames = int(chunk_frames)
        self.num_chunks = -(-self.frames_total // self.chunk_frames)
        self.discarded = 0  # chunks of an earlier run that `begin` removed

    def begin(self, *, resume: bool) -> int:
        """Starts a run: with ``resume``, continues the unfinished run in the folder if there is
        one (same settings, else an error); otherwise (or when there is none) starts over,
        removing any earlier chunks (`discarded` says how many).

        Returns:
          The first frame still to compute (0 when starting over).
        Raises:
          InputError (resuming) naming the first setting that differs from the unfinished run's.
        """
        manifest = self.folder / MANIFEST
        if resume and manifest.exists():
            self._check_manifest(manifest)
            return len(self.finished()) * self.chunk_frames
        self.discarded = len(self._chunk_files())
        self.remove()
        self.folder.mkdir(parents=True, exist_ok=True)
        doc = {
            "format": FORMAT,
            "version": 1,
            "frames_total": self.frames_total,
            "chunk_frames": self.chunk_frames,
            "settings": self.settings,
        }
        atomic_write_text(manifest, json.dumps(doc, indent=1) + "\n")
        return 0

    def path(self, first_frame: int) -> Path:
        """The file of the chunk starting at ``first_frame``."""
        return self.folder / f"chunk_{first_frame // self.chunk_frames:06d}.npz"

    def save(self, first_frame: int, results: PoseResults) -> None:
        """Writes one finished chunk, atomically."""
        save_poses_chunk(results, self.path(first_frame), first_frame=first_frame)

    def finished(self) -> list[Path]:
        """The finished chunks from the first on, up to the first one missing or unreadable (the
        rest are computed again)."""
        out = []
        for i in range(self.num_chunks):
            path = self.folder / f"chunk_{i:06d}.npz"
            if not path.is_file():
                break
            first = i * self.chunk_frames
            try:
                start, results = load_poses_chunk(path)
            except MvposeError:
                break
            frames = min(self.chunk_frames, self.frames_total - first)
            if start != first or len(results.confidence) != frames:
                break
            out.append(path)
        return out

    def assemble(self, out: str | os.PathLike, *, transform=None) -> Assembled:
        """Writes ``out/poses.npz`` and ``out/poses.json`` from the finished chunks (partial
        results when they do not cover the recording), atomically.

        Args:
          transform: optional ``(chunk files, folder) -> chunk files``, run on the finished
            chunks first, its files written in ``folder`` (``SMOOTHED`` inside this one; e.g.
            `smoothing.smooth_chunk_files`); the raw chunks stay as they are, for ``--resume``.
        """
        chunks = self.finished()
        if transform is not None:
            shutil.rmtree(self.folder / SMOOTHED, ignore_errors=True)
            chunks = transform(chunks, self.folder / SMOOTHED)
        npz, js, frames = assemble_poses(chunks, out, frames_total=self.frames_total)
        shutil.rmtree(self.folder / SMOOTHED, ignore_errors=True)
        return Assembled(npz, js, frames, frames < self.frames_total)

    def next_track_id(self) -> int:
        """One more than the largest track id in the finished chunks (0 without tracks)."""
        ids = [-1]
        for path in self.finished():
            track = load_poses_chunk(path)[1].track
            if track is not None and track.size:
                ids.append(int(track.max()))
        return max(ids) + 1

    def remove(self) -> None:
        """Deletes the chunk files and the manifest (and the folder when nothing else is in it)."""
        for path in self._chunk_files():
            path.unlink()
        (self.folder / MANIFEST).unlink(missing_ok=True)
        shutil.rmtree(self.folder / SMOOTHED, ignore_errors=True)
        if self.folder.is_dir() and not any(self.folder.iterdir()):
            shutil.rmtree(self.folder)

    def _chunk_files(self) -> list[Path]:
        if not self.folder.is_dir():
            return []
        return sorted(self.folder.glob("chunk_*.npz"))

    def _check_manifest(self, path: Path) -> None:
        doc = read_json(path)
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise InputError(
                f"not a chunk manifest (format is not {FORMAT!r})", file=path, field="format"
            )
        hint = "; run with the same settings, or without --resume to start over"
        saved: dict[str, Any] = dict(doc.get("settings") or {})
        saved.setdefault("chunk_frames", doc.get("chunk_frames"))
        current = {**self.settings, "chunk_frames": self.chunk_frames}
        for key in sorted(set(saved) | set(current)):
            if saved.get(key) != current.get(key):
                raise InputError(
                    f"the unfinished run in {self.folder} used {key} {_shown(saved.get(key))}, "
                    f"this command {_shown(current.get(key))}{hint}",
                    field=key,
                )
        if doc.get("frames_total") != self.frames_total:
            raise InputError(
                f"the detections have {self.frames_total} frames, the unfinished run's had "
                f"{doc.get('frames_total')}{hint}",
                field="source.detections",
            )


def _shown(value: Any) -> str:
    if value is None:
        return "(not given)"
    if isinstance(value, list):
        return " ".join(str(v) for v in value)
    return str(value)
