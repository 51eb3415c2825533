"""Synthetic recordings on any rig: the public entry points.

* `generate_recording`: one scene of 1-8 (or more) people, the test data of the method, with the
  3D ground truth, the identity of every detection and the noise-free projections.
* `generate_single_person_recordings`: many recordings of one person each, the training data.
* `detection_variants`: the paper's D-detected, D-projected and D-average versions of a recording.
* `simulate`: the same as the first two, returning the generator's internals as well
  (`SyntheticScene`: per-person occlusion, truncation, misses, swaps), for tests and analysis.

Recordings of a batch are simulated together (vectorised over recordings, frames, people and
cameras); people of different recordings never meet.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mvpose_jax.cameras import Rig
from mvpose_jax.data.recording import Recording
from mvpose_jax.errors import InputError
from mvpose_jax.progress import progress_bar
from mvpose_jax.skeletons import Detections, Poses3D
from mvpose_jax.synthetic import body as bm
from mvpose_jax.synthetic.config import SyntheticConfig
from mvpose_jax.synthetic.detector import (
    DetectorOutput,
    Occluders,
    _fields,
    detect_people,
    extra_skeletons,
    false_positives,
    mix_parts,
    place_occluders,
)
from mvpose_jax.synthetic.motion import Paths, plan_paths, pose_angles
from mvpose_jax.synthetic.scene import SceneGeometry, scene_geometry

# Single-person recordings are simulated in batches of about this many person-frames.
_BATCH_FRAMES = 20_000


@dataclasses.dataclass(frozen=True)
class SyntheticScene:
    """A generated recording and what the generator knows about it (G people of the scene).

    Attributes:
      recording: the `Recording` (detections, ground truth, identities, projections).
      truth: per-person detector internals, arrays (F, C, G, ...): which keypoints are in the
        image, occluded (by anyone / by others), which people are in view, missed, swapped …
      num_false_positives: (F, C) false-positive skeletons in each view (duplicates and
        fragments of people, `truth.duplicated` and `truth.fragmented`, not counted).
      points: (F, G, NUM_POINTS, 3) world points of the body model: the 18 keypoints, then the
        pelvis and head centres (the capsule ends of `body.CAPSULES`), metres.
      bodies: the G bodies.
      paths: the planned movement (floor coordinates) and on-the-spot activities.
      geometry: the rig's floor and capture area.
      occluders: the scene's static boxes (O of them: centre (O, 3), axes (O, 3, 3), half sizes
        (O, 3)); None without.
    """

    recording: Recording
    truth: DetectorOutput
    num_false_positives: np.ndarray
    points: np.ndarray
    bodies: bm.Bodies
    paths: Paths
    geometry: SceneGeometry
    occluders: Occluders | None = None


def generate_recording(
    rig: Rig,
    *,
    num_people: int,
    num_frames: int,
    config: SyntheticConfig = SyntheticConfig(),
    seed: int | np.random.Generator = 0,
    progress: bool = False,
) -> Recording:
    """A multi-person recording (test data): detections, 3D ground truth and identities.

    Args:
      rig: the cameras (a preset via `calibration.load_rig` or a user's calibration).
      num_people: G people in the scene, all present in every frame.
      num_frames: F frames at ``config.motion.fps``.
      config: generator settings.
      seed: an int or a numpy Generator; equal seeds give equal recordings.
      progress: show a progress bar.
    Returns:
      A `Recording`: detections (F, C, P, 18) in the coco18 layout, ground_truth xyz (F, G, 18, 3)
      metres, identity (F, C, P) (the G index, -1 for false positives and padding), projected
      (F, C, P, 18, 2) noise-free projections of each detection's true person (false positives
      keep their own pixels), timestamps (F,) seconds.
    """
    return simulate(
        rig,
        num_people=num_people,
        num_frames=num_frames,
        config=config,
        seed=seed,
        progress=progress,
    )[0].recording


def generate_single_person_recordings(
    rig: Rig,
    *,
    num_recordings: int,
    num_frames: int,
    config: SyntheticConfig = SyntheticConfig(),
    seed: int | np.random.Generator = 0,
    progress: bool = False,
) -> list[Recording]:
    """Recordings of one person each, every one a different body (training data).

    The detector model is the same as in test scenes (false positives included: the method must
    learn that the main skeleton of a view is the one with most keypoints).

    Args:
      rig: the cameras.
      num_recordings: how many recordings.
      num_frames: F frames per recording.
      config, seed, progress: as in `generate_recording`.
    """
    return [
        s.recording
        for s in simulate(
            rig,
            num_people=1,
            num_frames=num_frames,
            num_scenes=num_recordings,
            config=config,
            seed=seed,
            progress=progress,
        )
    ]


def simulate(
    rig: Rig,
    *,
    num_people: int,
    num_frames: int,
    num_scenes: int = 1,
    config: SyntheticConfig = SyntheticConfig(),
    seed: int | np.random.Generator = 0,
    progress: bool = False,
) -> list[SyntheticScene]:
    """Generates ``num_scenes`` independent scenes of ``num_people`` people each.

    Returns:
      One `SyntheticScene` per scene.
    Raises:
      InputError for non-positive sizes or a rig without a capture area.
    """
    if num_people < 1 or num_frames < 1 or num_scenes < 1:
        raise InputError(
            f"num_people, num_frames and num_scenes must be positive, got {num_people}, "
            f"{num_frames}, {num_scenes}",
            field="num_people",
        )
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    geometry = scene_geometry(rig, config.scene)
    per_batch = max(1, _BATCH_FRAMES // (num_frames * num_people))
    # Scenes simulated together share one floor: with a floor jitter, every scene draws its own
    # (whole centimetres, so few distinct geometries are built and cached) and scenes are batched
    # per floor.
    jobs = [(geometry, list(range(num_scenes)))]
    jitter = config.scene.floor_jitter_m
    if not (np.isfinite(jitter) and jitter >= 0):
        raise InputError(f"floor_jitter_m must be >= 0, not {jitter}", field="floor_jitter_m")
    if jitter > 0:
        offsets = np.round(rng.uniform(-jitter, jitter, num_scenes), 2)
        jobs = [
            (
                scene_geometry(
                    rig,
                    dataclasses.replace(
                        config.scene,
                        floor_height=round(geometry.floor_height + float(o), 4),
                        floor_jitter_m=0.0,
                        floor_offset_m=0.0,  # already in geometry.floor_height
                    ),
                ),
                np.nonzero(offsets == o)[0].tolist(),
            )
            for o in np.unique(offsets)
        ]
    bar = None
    if progress:
        bar = progress_bar(
            total=num_scenes * num_frames, unit="frame", desc="generating", leave=False
        )
    out: list[SyntheticScene | None] = [None] * num_scenes
    for geo, scenes in jobs:
        for s in range(0, len(scenes), per_batch):
            batch = scenes[s : s + per_batch]
            made = _simulate_batch(rig, geo, len(batch), num_people, num_frames, config, rng)
            for i, scene in zip(batch, made, strict=True):
                out[i] = scene
            if bar is not None:
                bar.update(len(batch) * num_frames)
    if bar is not None:
        bar.close()
    return out  # type: ignore[return-value]


def detection_variants(recording: Recording) -> dict[str, Recording]:
    """The paper's three versions of a recording's detections.

    * ``"detected"``: the recording itself (D-detected).
    * ``"projected"``: every reported keypoint moved to the noise-free projection of its true 3D
      position (D-projected); scores, missing keypoints and false positives stay as they are.
    * ``"average"``: the mean of the two (D-average).

    Raises:
      InputError when the recording has no ``projected`` array.
    """
    if recording.projected is None:
        raise InputError("the recording has no noise-free projections", field="projected")
    det = recording.detections
    xy = np.asarray(det.xy)
    proj = np.asarray(recording.projected, xy.dtype)
    present = (np.asarray(det.score) > 0)[..., None]

    def with_xy(new: np.ndarray) -> Recording:
        new = np.where(present, new, 0.0).astype(xy.dtype)
        return dataclasses.replace(recording, detections=Detections(new, det.score, det.count))

    return {
        "detected": recording,
        "projected": with_xy(proj),
        "average": with_xy(0.5 * (xy + proj)),
    }


# --------------------------------------------------------------------------- internals


def _simulate_batch(
    rig: Rig,
    geometry: SceneGeometry,
    B: int,
    Gp: int,
    F: int,
    config: SyntheticConfig,
    rng: np.random.Generator,
) -> list[SyntheticScene]:
    G = B * Gp
    cams = geometry.cameras
    C = cams.num_cameras
    bodies = bm.sample_bodies(rng, G, config.body)
    group = np.repeat(np.arange(B), Gp)
    paths = plan_paths(geometry, bodies, group, F, config.motion, rng)
    angles = pose_angles(paths, bodies, config.motion, rng)
    local, frames = bm.forward_kinematics(bodies, angles)  # floor coordinates
    world = geometry.to_world(local)  # (F, G, NP, 3)
    axes = frames @ geometry.basis  # (F, G, 3, 3) heading frames in the world
    dc = config.detector
    # The domain shifts' effects (all off by default, and then they draw no random numbers).
    occluders = place_occluders(geometry, B, dc, rng) if dc.num_occluders > 0 else None
    det = detect_people(
        cams, world, axes, bodies.height, bodies.radii, group, dc, rng, occluders=occluders
    )
    if dc.limb_mix_rate > 0:
        det = mix_parts(det, group, dc, rng)
    extra = None
    if dc.duplicate_rate > 0 or dc.fragment_rate > 0:
        det, *extra = extra_skeletons(det, dc, rng)

    # Body-frame poses to shape false positives from (a few hundred random person-frames).
    n_src = min(F * G, 256)
    fi, gi = rng.integers(0, F, n_src), rng.integers(0, G, n_src)
    rel = local[fi, gi, : bm.NUM_KEYPOINTS] - local[fi, gi, bm.PELVIS][:, None]
    body_frame = np.einsum("nkd,njd->nkj", rel, frames[fi, gi])  # (n, K, 3) forward, left, up
    split = lambda a: a.reshape(a.shape[:2] + (B, Gp) + a.shape[3:])  # noqa: E731
    fp_xy, fp_score, fp_valid = false_positives(
        cams,
        body_frame,
        split(det.reported),
        split(det.xy),
        split(det.height_px),
        config.detector,
        rng,
    )
    num_fp = fp_valid.sum(-1)  # (F, C, B)
    if extra is not None:
        # Duplicates and fragments are extra rows with identity -1, like false positives: the
        # pipeline takes one skeleton per person and view, so the best grouping leaves them out.
        ex_xy, ex_score, ex_valid = (a.reshape((F, C, B, Gp * 2) + a.shape[4:]) for a in extra)
        fp_xy = np.concatenate([fp_xy, ex_xy], axis=3)
        fp_score = np.concatenate([fp_score, ex_score], axis=3)
        fp_valid = np.concatenate([fp_valid, ex_valid], axis=3)
    M = fp_valid.shape[-1]
    K = bm.NUM_KEYPOINTS

    # Rows: real detections and false positives, shuffled per view (a detector's order carries
    # no identity), valid rows first.
    xy = np.concatenate([split(det.xy), fp_xy], axis=3)  # (F, C, B, Gp + M, K, 2)
    score = np.concatenate([split(det.score), fp_score], axis=3)
    valid = np.concatenate([split(det.reported), fp_valid], axis=3)
    ident = np.concatenate(
        [np.broadcast_to(np.arange(Gp), (F, C, B, Gp)), np.full((F, C, B, M), -1)], axis=3
    )  # (F, C, B, Gp + M)
    proj = np.concatenate([split(det.projected).astype(np.float32), fp_xy], axis=3)
    # Destination row of every valid slot: a random permutation of each view's valid slots.
    rank = np.argsort(np.argsort(np.where(valid, rng.random(valid.shape), 2.0), axis=-1), axis=-1)
    count = valid.sum(-1).astype(np.int32)  # (F, C, B)
    P_all = max(1, int(count.max()))
    idx = np.nonzero(valid)
    dest = idx[:3] + (rank[idx],)

    def place(a: np.ndarray, fill) -> np.ndarray:
        out = np.full((F, C, B, P_all) + a.shape[4:], fill, a.dtype)
        out[dest] = a[idx]
        return out

    xy, score, ident, proj = (
        place(xy, 0),
        place(score, 0),
        place(ident.astype(np.int32), -1),
        place(proj, 0),
    )
    timestamps = np.arange(F, dtype=np.float64) / config.motion.fps

    scenes = []
    for b in range(B):
        P = max(1, int(count[:, :, b].max()))
        sl = slice(b * Gp, (b + 1) * Gp)
        xyz = world[:, sl, :K].astype(np.float32)
        gt = Poses3D(xyz, np.ones((F, Gp), bool), np.ones((F, Gp, K), bool))
        rec = Recording(
            detections=Detections(
                np.ascontiguousarray(xy[:, :, b, :P]),
                np.ascontiguousarray(score[:, :, b, :P]),
                np.ascontiguousarray(count[:, :, b]),
            ),
            cameras=tuple(rig.names),
            layout="coco18",
            ground_truth=gt,
            identity=np.ascontiguousarray(ident[:, :, b, :P]),
            timestamps=timestamps,
            projected=np.ascontiguousarray(proj[:, :, b, :P]),
        )
        truth = DetectorOutput(*(a[:, :, sl] for a in _fields(det)))
        path_b = Paths(
            paths.root[:, sl],
            paths.heading[:, sl],
            paths.speed[:, sl],
            *_segments_of(paths, b * Gp, (b + 1) * Gp),
        )
        scenes.append(
            SyntheticScene(
                rec,
                truth,
                num_fp[:, :, b],
                world[:, sl],
                bodies.take(sl),
                path_b,
                geometry,
                None if occluders is None else Occluders(*(a[b] for a in occluders)),
            )
        )
    return scenes


def _segments_of(paths: Paths, lo: int, hi: int):
    keep = (paths.seg_person >= lo) & (paths.seg_person < hi)
    return (
        paths.seg_person[keep] - lo,
        paths.seg_kind[keep],
        paths.seg_start[keep],
        paths.seg_end[keep],
    )
