"""``mvpose-jax score``: the label-free score of any result (`jobs.score`)."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import (
    add_detection_options,
    add_rig_argument,
    check_writable,
    detections_source,
    rig_source,
)
from mvpose_jax.cli.registry import command


def _score_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("poses", help="poses.npz / poses.json (or their folder), as infer writes them")
    add_rig_argument(p, default=None)
    p.add_argument("--detections", required=True, help="the detections the poses were made from")
    add_detection_options(p, what="--detections")
    p.add_argument(
        "--json",
        required=True,
        metavar="OUT",
        help="the report: OUT.json (its figure beside it as OUT.png), or a folder "
        "(label_free.json and label_free.png in it)",
    )


@command(
    "score",
    "Score 3D poses without labels: each camera's skeletons against the poses' projections "
    "(a keypoint not produced is a miss), leave-one-camera-out re-triangulation, bone-length "
    "spread, jitter, people counts and track fragments; a JSON report and a figure.",
    _score_arguments,
)
def _score(args: argparse.Namespace) -> int:
    from mvpose_jax.jobs.score import ScoreConfig, run_score, summary_lines

    check_writable(args.json, folder=not args.json.endswith(".json"))
    config = ScoreConfig(args.poses, rig_source(args), detections_source(args), args.json)
    report, paths = run_score(config)
    for line in summary_lines(report):
        print(line)
    print("wrote " + " and ".join(str(p) for p in paths))
    return 0
