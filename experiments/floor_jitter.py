"""A coarse look at what a wrong floor costs the 3D estimator: ``python -m experiments.floor_jitter``.

Trains the quick residual estimator (the experiments' recipe, shortened) on single-person
recordings generated with the floor where it is (the validation scenes' floor), ``--offset``
metres off, and off with a floor jitter, then scores each on the validation scenes
(``[seed, 3, n]``, true floor) on their true person groups (the 3D stage alone): PCP and MPJPE.
This measures the estimator only; the matcher (which also learns where people are) is not
covered, because training it takes hours here.
"""

from __future__ import annotations

import argparse

import numpy as np

from experiments.config import estimator_config, seed_stream
from mvpose_jax.cameras import up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.estimator_training import train_estimator
from mvpose_jax.features import single_person_samples
from mvpose_jax.lifting import members_from_identity, poses_of_members
from mvpose_jax.metrics import pose_metrics
from mvpose_jax.models import MLPConfig
from mvpose_jax.synthetic import (
    SceneConfig,
    SyntheticConfig,
    generate_recording,
    generate_single_person_recordings,
    scene_geometry,
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rig", default="panoptic5")
    p.add_argument("--offset", type=float, default=0.3, help="training floor error, metres")
    p.add_argument("--jitter", type=float, default=0.3, help="floor jitter of the third model")
    p.add_argument("--recordings", type=int, default=150)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--people", type=int, nargs="+", default=[2, 4, 6])
    p.add_argument("--scene-frames", type=int, default=40)
    args = p.parse_args(argv)

    rig = load_rig(args.rig)
    floor = scene_geometry(rig).floor_height
    scenes = [
        generate_recording(
            rig, num_people=n, num_frames=args.scene_frames, seed=seed_stream("validation", 0, n)
        )
        for n in args.people
    ]
    config = estimator_config(MLPConfig.quick(), steps=args.steps)
    variants = {
        "floor right": (0.0, 0.0),
        f"floor {args.offset:+g} m": (args.offset, 0.0),
        f"floor {args.offset:+g} m, jitter {args.jitter:g}": (args.offset, args.jitter),
        f"floor right, jitter {args.jitter:g}": (0.0, args.jitter),
    }
    for name, (offset, jitter) in variants.items():
        scene = SceneConfig(floor_height=floor + offset, floor_jitter_m=jitter)
        cfg = SyntheticConfig(scene=scene)
        train = generate_single_person_recordings(
            rig,
            num_recordings=args.recordings,
            num_frames=args.frames,
            config=cfg,
            seed=seed_stream("train", 0),
        )
        dev = generate_single_person_recordings(
            rig, num_recordings=5, num_frames=40, config=cfg, seed=seed_stream("dev", 0)
        )
        xy, score = single_person_samples(train)
        dxy, dscore = single_person_samples(dev)
        estimator, _ = train_estimator(rig, xy, score, dxy, dscore, config, progress=False)
        pcp, mpjpe = [], []
        for rec in scenes:
            G = rec.ground_truth.valid.shape[1]
            members = members_from_identity(np.asarray(rec.identity), G)
            poses, _ = poses_of_members(rig, rec.detections, members, estimator=estimator)
            m = pose_metrics(poses, rec.ground_truth, up=up_vector(rig))
            pcp.append(m["pcp"])
            mpjpe.append(m["mpjpe_mm"])
        print(
            f"| {name} | {np.mean(pcp):.2f} | {np.mean(mpjpe):.2f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
