"""The data of the experiments: single-person training and dev recordings per training seed, and
the multi-person validation, test and tracking scenes (with or without a domain shift), all from
`experiments.config.seed_stream`; and how a split's scenes are read as one recording."""

from __future__ import annotations

import dataclasses

import numpy as np

from experiments.config import SPLITS, TRACKING_SPLITS, Scale, seed_stream
from mvpose_jax.data import select_cameras
from mvpose_jax.lifting import members_from_identity
from mvpose_jax.skeletons import Detections, Poses3D
from mvpose_jax.synthetic import (
    DetectorConfig,
    SyntheticConfig,
    detection_variants,
    generate_recording,
    generate_single_person_recordings,
)


@dataclasses.dataclass
class Data:
    """One training seed's data: the rig, its single-person training and dev recordings, and the
    multi-person scenes every training seed shares."""

    rig: object
    train: list
    dev: list
    scenes: dict  # split -> multi-person recordings, one per entry of test_people

    def detections(self, split: str, cameras, variant: str = "detected"):
        """All frames of a split's scenes as one recording.

        Returns:
          detections in ``cameras``, true identities (F, C, P), ground truth `Poses3D` and person
          ids (F, G) (unique across scenes). The ground truth holds the people that at least one
          camera (of the full rig) detected in the frame: a person nobody saw cannot be
          annotated, and every person that is held counts, found or not.
        """
        recs = self.scenes[split]
        P = max(np.shape(r.detections.score)[2] for r in recs)
        G = max(r.ground_truth.valid.shape[1] for r in recs)

        def pad(a, n, axis, fill=0):
            a = np.asarray(a)
            width = [(0, 0)] * a.ndim
            width[axis] = (0, n - a.shape[axis])
            return np.pad(a, width, constant_values=fill)

        seen = []
        for r in recs:
            ident = np.asarray(r.identity)
            g = np.arange(r.ground_truth.valid.shape[1])
            seen.append(pad((ident[:, :, :, None] == g).any(axis=(1, 2)), G, 1, False))
        chosen = [select_cameras(detection_variants(r)[variant], list(cameras)) for r in recs]
        det = Detections(
            np.concatenate([pad(r.detections.xy, P, 2) for r in chosen]),
            np.concatenate([pad(r.detections.score, P, 2) for r in chosen]),
            np.concatenate([np.asarray(r.detections.count) for r in chosen]),
        )
        ident = np.concatenate([pad(r.identity, P, 2, -1) for r in chosen])
        gt = Poses3D(
            *(
                np.concatenate([pad(f, G, 1) for f in field])
                for field in zip(*[r.ground_truth for r in recs], strict=True)
            )
        )
        gt = gt._replace(valid=gt.valid & np.concatenate(seen))
        ids = np.concatenate(
            [np.broadcast_to(i * G + np.arange(G), (r.num_frames, G)) for i, r in enumerate(recs)]
        )
        return det, ident, gt, ids


def make_scenes(
    rig,
    sc: Scale,
    scenes_seed: int,
    *,
    tracking: bool = False,
    config: SyntheticConfig | None = None,
) -> dict:
    """Multi-person scenes, one per entry of ``test_people``, of each split's seed stream.

    tracking: the long tracking scenes (``sc.tracking_frames`` each, streams
    ``tracking/<split>``) rather than the validation and test scenes (``sc.test_frames`` each).
    config: the simulator's settings (None: the default, floor guessed from the cameras).
    Returns: split -> list of `Recording`.
    """
    splits = TRACKING_SPLITS if tracking else SPLITS
    return {
        split: [
            generate_recording(
                rig,
                num_people=n,
                num_frames=sc.tracking_frames if tracking else sc.test_frames,
                config=config or SyntheticConfig(),
                seed=seed_stream(f"tracking/{split}" if tracking else split, scenes_seed, n),
            )
            for n in sc.test_people
        ]
        for split in splits
    }


def make_tracking_scenes(rig, sc: Scale, scenes_seed: int) -> dict:
    """Long multi-person scenes (one per entry of ``test_people``) for tracks over time."""
    return make_scenes(rig, sc, scenes_seed, tracking=True)


def make_data(
    rig,
    scenes: dict,
    sc: Scale,
    seed: int,
    progress: bool,
    floor_height: float | None = None,
    up: tuple[float, float, float] | None = None,
    detector: DetectorConfig | None = None,
) -> Data:
    """Training and dev recordings of training seed ``seed``, with the shared ``scenes``
    (``floor_height``, ``up``: the floor along up, metres, and up, as measured on a real rig
    (`floor.estimate_floor_from_detections`); None: the rig's, or guessed from the cameras;
    ``detector``: the simulated detector, such as one fitted to a real recording
    (`detector_fit.fit_detector`); None: the default one)."""
    config = SyntheticConfig()
    if detector is not None:
        config = dataclasses.replace(config, detector=detector)
    if floor_height is not None or up is not None:
        config = config.with_scene(floor_height=floor_height, up=up)
    if sc.train_floor_jitter_m > 0:
        config = config.with_scene(floor_jitter_m=sc.train_floor_jitter_m)
    if sc.train_floor_offset_m:
        config = config.with_scene(floor_offset_m=sc.train_floor_offset_m)
    train = generate_single_person_recordings(
        rig,
        num_recordings=sc.train_recordings,
        num_frames=sc.train_frames,
        config=config,
        seed=seed_stream("train", seed),
        progress=progress,
    )
    dev = generate_single_person_recordings(
        rig,
        num_recordings=sc.dev_recordings,
        num_frames=sc.dev_frames,
        config=config,
        seed=seed_stream("dev", seed),
    )
    return Data(rig, train, dev, scenes)


def make_shifted_scenes(rig, sc: Scale, scenes_seed: int, shift) -> dict:
    """Validation and test scenes (the same seed streams as `make_scenes`) made with a shift.

    The shift ``"none"`` gives exactly `make_scenes`'s recordings. Scores above 1 (another
    detector's calibration) reach the pipeline as the readers hand them over: clipped to 1.
    A calibration error draws each scene's own perturbed rig; the scene is reconstructed with
    the nominal one.
    """
    out = {}
    for split in SPLITS:
        recs = []
        for n in sc.test_people:
            seed = seed_stream(split, scenes_seed, n)
            gen_rig, config = shift.apply(rig, seed=[*seed, 1])
            rec = generate_recording(
                gen_rig, num_people=n, num_frames=sc.test_frames, config=config, seed=seed
            )
            det = rec.detections
            clipped = det._replace(score=np.minimum(np.asarray(det.score), 1.0))
            recs.append(dataclasses.replace(rec, detections=clipped))
        out[split] = recs
    return out


def true_members(identity: np.ndarray, num_people: int, min_views: int) -> np.ndarray:
    """(F, G, C) each true person's skeleton per camera (-1: none), people seen in min_views+ views."""
    members = members_from_identity(identity, num_people)
    members[(members >= 0).sum(-1) < min_views] = -1
    return members


def views_of(rec) -> np.ndarray:
    """(F, G) how many cameras detected each ground-truth person in each frame."""
    ident = np.asarray(rec.identity)  # (F, C, S)
    G = rec.ground_truth.valid.shape[1]
    return (ident[..., None] == np.arange(G)).any(-2).sum(-2)


def seen_truth(rec) -> Poses3D:
    """The ground truth of the people at least one camera detected in each frame."""
    gt = rec.ground_truth
    return gt._replace(valid=np.asarray(gt.valid) & (views_of(rec) > 0))


def stack_frames(parts: list[np.ndarray], fill=0) -> np.ndarray:
    """Arrays (F_i, G_i, ...) of consecutive scenes as one (sum F_i, max G_i, ...)."""
    G = max(a.shape[1] for a in parts)
    pad = lambda a: np.pad(  # noqa: E731
        a, [(0, 0), (0, G - a.shape[1])] + [(0, 0)] * (a.ndim - 2), constant_values=fill
    )
    return np.concatenate([pad(np.asarray(a)) for a in parts])


def tracking_truth(scenes: list) -> tuple[Poses3D, np.ndarray]:
    """The scenes' ground truth (people some camera saw) as one recording: frames stacked,
    people padded, and (F, G) person ids unique across scenes."""
    gts = [seen_truth(r) for r in scenes]
    G = max(g.valid.shape[1] for g in gts)
    ids = stack_frames(
        [
            np.broadcast_to(i * G + np.arange(g.valid.shape[1]), g.valid.shape)
            for i, g in enumerate(gts)
        ]
    )
    return Poses3D(*(stack_frames([g[k] for g in gts]) for k in range(3))), ids


def tracking_views(scenes: list) -> np.ndarray:
    """(F, G) how many cameras detected each ground-truth person, the scenes' frames stacked as
    `tracking_truth` stacks them."""
    return stack_frames([views_of(rec) for rec in scenes])


def pooled_tracks(poses: list[Poses3D], tracks: list[np.ndarray]) -> tuple[Poses3D, np.ndarray]:
    """Each scene's tracked poses as one recording: frames stacked, people padded, and track ids
    offset per scene (each scene is its own stream) so no two scenes share one."""
    stacked = Poses3D(*(stack_frames([p[k] for p in poses]) for k in range(3)))
    track = stack_frames(
        [np.where(t >= 0, t + i * 100_000, -1) for i, t in enumerate(tracks)], fill=-1
    )
    return stacked, track
