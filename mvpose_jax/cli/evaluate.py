"""``mvpose-jax evaluate``: infer's 3D poses scored."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import detection_arguments, detections_source, rig_source
from mvpose_jax.cli.registry import command
from mvpose_jax.jobs.evaluate import EvaluateConfig, evaluate


def _evaluate_arguments(p: argparse.ArgumentParser) -> None:
    detection_arguments(p)
    p.add_argument(
        "--poses", required=True, help="poses.npz / poses.json (or their folder) written by infer"
    )
    p.add_argument("--out", help="also write the metrics to this JSON file")


@command(
    "evaluate",
    "Score 3D poses: MPJPE, AP, recall, PCP and matching against ground truth when the recording has "
    "it; reprojection error per camera always.",
    _evaluate_arguments,
)
def _evaluate(args: argparse.Namespace) -> int:
    config = EvaluateConfig(rig_source(args), detections_source(args), args.poses, args.out)
    out = evaluate(config)
    lines = [f"{out['frames']} frames, {out['people']} people"]
    if "pose" in out:
        m = out["pose"]
        lines.append(
            f"3D vs ground truth: MPJPE {m['mpjpe_mm']:.2f} mm, mAP {m['map']:.2f}, mean recall "
            f"{m['mean_recall']:.2f}, PCP {m['pcp']:.2f}, completeness {m['completeness']:.2f} %"
        )
    if "matching" in out:
        m = out["matching"]
        lines.append(
            f"matching vs true identities: ARI {m['ari']:.4f}, H {m['homogeneity']:.4f}, "
            f"C {m['completeness']:.4f}, Vm {m['v_measure']:.4f}"
        )
    lines.append("reprojection error (px, mean / median / keypoints):")
    for cam, e in out["reprojection_px"].items():
        lines.append(f"  {cam:>12s}  {e['mean']:8.2f} / {e['median']:8.2f} / {int(e['count'])}")
    print("\n".join(lines))
    return 0
