"""Builders shared by the tests: rigs, points, calibration documents, random graph frames.

Plain functions (fixtures live in `conftest.py`); every builder is seeded and deterministic.
"""

from __future__ import annotations

import dataclasses
import json
import math

import cv2
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, make_rig
from mvpose_jax.models import GATConfig, MatchingGAT
from mvpose_jax.train import init_train_state, make_optimizer, make_train_step, matcher_loss_fn
from mvpose_jax.trained import MatcherConfig


def random_rig(seed: int = 0, num_cameras: int = 4):
    """Cameras on a ring looking at the origin, with strong radial AND tangential distortion.

    The distortion stays invertible over the image (as any real calibration's does there).
    """
    rng = np.random.default_rng(seed)
    K, dist, R, t = [], [], [], []
    for c in range(num_cameras):
        angle = 2 * np.pi * c / num_cameras + rng.uniform(-0.2, 0.2)
        centre = np.array([4 * np.cos(angle), -1.5 + rng.uniform(-0.3, 0.3), 4 * np.sin(angle)])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross(forward, [0.0, -1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rot = np.stack([right, down, forward])  # cam_from_world rows: x right, y down, z forward
        R.append(rot)
        t.append(-rot @ centre)
        f = rng.uniform(1200, 1600)
        K.append(
            [[f, 0, 960 + rng.uniform(-20, 20)], [0, f * rng.uniform(0.99, 1.01), 540], [0, 0, 1]]
        )
        dist.append(
            [
                rng.uniform(-0.28, -0.1),
                rng.uniform(0.0, 0.15),
                rng.uniform(-2e-3, 2e-3),
                rng.uniform(-2e-3, 2e-3),
                rng.uniform(-0.03, 0.02),
            ]
        )
    return make_rig(
        K, dist, R, t, [[1920, 1080]] * num_cameras, [f"cam{c}" for c in range(num_cameras)]
    )


def scene_points(rig, seed, shape):
    """Points in front of every camera of the rig, near where the cameras look: shape + (3,)."""
    from mvpose_jax.cameras import camera_centres

    centres = np.asarray(camera_centres(rig))
    looks = centres + 3.0 * np.asarray(rig.R)[:, 2]  # 3 m along each optical axis
    rng = np.random.default_rng(seed)
    return (rng.normal(size=tuple(shape) + (3,)) * 0.4 + looks.mean(axis=0)).astype(np.float32)


def panoptic_dict(rig: Rig, *, source: str = "hostile", vga_decoy: bool = False) -> dict:
    """A CMU Panoptic calibration (t in cm as a column, 'distCoef', 'resolution'); with
    ``vga_decoy``, plus a VGA camera that a selection by name must skip."""
    cams = [
        {
            "name": f"00_{c:02d}",
            "type": "hd",
            "resolution": np.asarray(rig.size[c]).astype(int).tolist(),
            "K": np.asarray(rig.K[c], np.float64).tolist(),
            "distCoef": np.asarray(rig.dist[c], np.float64).tolist(),
            "R": np.asarray(rig.R[c], np.float64).tolist(),
            "t": (np.asarray(rig.t[c], np.float64) * 100).reshape(3, 1).tolist(),
        }
        for c in range(rig.num_cameras)
    ]
    if vga_decoy:
        cams.append({**cams[0], "name": "01_01", "type": "vga", "resolution": [640, 480]})
    return {"calibDataSource": source, "cameras": cams}


def toml_doc(rig: Rig, scale: float = 1.0) -> dict:
    """An anipose / Pose2Sim calibration as a TOML document (translations divided by ``scale``)."""
    doc = {}
    for c, name in enumerate(rig.names):
        doc[f"cam_{c + 1}"] = {
            "name": name,
            "size": np.asarray(rig.size[c], np.float64).tolist(),
            "matrix": np.asarray(rig.K[c], np.float64).tolist(),
            "distortions": np.asarray(rig.dist[c], np.float64)[:4].tolist(),
            "rotation": cv2.Rodrigues(np.asarray(rig.R[c], np.float64))[0].ravel().tolist(),
            "translation": (np.asarray(rig.t[c], np.float64) / scale).tolist(),
            "fisheye": False,
        }
    doc["metadata"] = {"adjusted": False, "error": 0.0}
    return doc


def toml_text(rig: Rig, scale: float = 1.0) -> str:
    """`toml_doc` written as TOML text."""
    return dump_toml(toml_doc(rig, scale))


class Raw:
    """JSON (or TOML) text put verbatim where a value goes: what `json.dumps` cannot write."""

    def __init__(self, text: str):
        self.text = text

    def __repr__(self):
        return f"Raw({self.text[:40]!r}{'…' if len(self.text) > 40 else ''})"


def _toml_value(v) -> str:
    if v is None:  # TOML has no null; a string stands in for it
        return '"null"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, Raw):
        return v.text
    raise TypeError(type(v))


def dump_toml(doc) -> str:
    """A small TOML writer for the anipose structure (tables of values, inline tables below)."""
    if not isinstance(doc, dict):  # the root replaced: write it as a value
        return f"value = {_toml_value(doc)}\n"
    values = [(k, v) for k, v in doc.items() if not isinstance(v, dict)]
    lines = [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in values]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines.append(f"[{json.dumps(k)}]")
            lines += [f"{json.dumps(kk)} = {_toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


def json_paths(node, prefix=()):
    """Every place in a JSON document, as key paths."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from json_paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from json_paths(v, prefix + (i,))


def random_frames(
    rng: np.random.Generator, F: int, C: int = 3, P: int = 3, K: int = 4, p_valid: float = 0.6
):
    """Random detection features (F, C, P, K*10), validity (F, C, P) and identities (F, C, P)
    (-1 for a fifth of the skeletons), for graph building."""
    feats = rng.normal(size=(F, C, P, K * 10)).astype(np.float32)
    valid = rng.random((F, C, P)) < p_valid
    identity = np.where(rng.random((F, C, P)) < 0.8, rng.integers(0, 3, (F, C, P)), -1)
    return feats, valid, identity


# A tiny matching GAT on C cameras and K keypoints (the shapes `random_frames` makes by default).
C, K = 3, 4
TINY_GAT = GATConfig(widths=(8, 8, 1), heads=(2, 2, 1))


def tiny_matcher_train_state(config: GATConfig = TINY_GAT, lr: float = 3e-3, seed: int = 0):
    """(graphdef, rest, TrainState, jitted train step) of a GAT on C cameras, K keypoints."""
    m = MatchingGAT(C, K, config, rngs=nnx.Rngs(seed))
    tx = make_optimizer(dataclasses.replace(MatcherConfig().train, learning_rate=lr))
    graphdef, rest, state = init_train_state(m, tx)
    return graphdef, rest, state, make_train_step(graphdef, rest, tx, matcher_loss_fn)


def read_in_chunks(path, chunk_frames: int, **kwargs):
    """A recording read through `data.open_recording` ``chunk_frames`` frames at a time, its
    ranges joined again (people padded to the largest range's): what `load_recording` returns,
    for comparing the two. Returns (Recording, the ranges' person counts P)."""
    from mvpose_jax.data import Recording, open_recording
    from mvpose_jax.skeletons import Detections, Poses3D

    with open_recording(path, **kwargs) as stream:
        parts = [rec for _, rec in stream.chunks(chunk_frames)] or [stream.read_frames(0, 0)]
        cameras, layout = stream.cameras, stream.layout
    sizes = [np.shape(r.detections.score)[2] for r in parts]
    P = max(sizes, default=1)

    def join(get, fill=0, axis=2):
        arrays = [get(r) for r in parts]
        if not arrays or arrays[0] is None:
            return None
        pad = lambda a: np.pad(  # noqa: E731
            a,
            [(0, P - a.shape[axis]) if i == axis else (0, 0) for i in range(a.ndim)],
            constant_values=fill,
        )
        return np.concatenate([pad(np.asarray(a)) if axis is not None else a for a in arrays])

    gt = None
    if parts and parts[0].ground_truth is not None:
        gt = Poses3D(
            *(
                join(lambda r, i=i: r.ground_truth[i], axis=None)
                for i in range(len(parts[0].ground_truth))
            )
        )
    rec = Recording(
        detections=Detections(
            join(lambda r: r.detections.xy),
            join(lambda r: r.detections.score),
            join(lambda r: r.detections.count, axis=None),
        ),
        cameras=cameras,
        layout=layout,
        ground_truth=gt,
        identity=join(lambda r: r.identity, fill=-1),
        timestamps=join(lambda r: r.timestamps, axis=None),
        image_names=join(lambda r: r.image_names, axis=None),
        projected=join(lambda r: r.projected),
    )
    return rec, sizes
