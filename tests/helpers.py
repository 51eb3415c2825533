"""Builders shared by the tests: rigs, points, calibration documents, random graph frames.

Plain functions (fixtures live in `conftest.py`); every builder is seeded and deterministic.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, make_rig, rig_centre_and_radius
from mvpose_jax.matcher_training import matcher_loss_fn
from mvpose_jax.models import GATConfig, MatchingGAT, MLPConfig, PoseMLP
from mvpose_jax.train import init_train_state, make_optimizer, make_train_step
from mvpose_jax.trained import Estimator, EstimatorConfig, MatcherConfig


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


def untrained_estimator(rig: Rig, num_keypoints: int = 18, seed: int = 0) -> Estimator:
    """An estimator on every camera of ``rig`` whose network returns its initial 3D estimate
    exactly: a "residual" PoseMLP starts with a zero output layer (a closed form for inference
    tests, no training)."""
    mlp = MLPConfig(widths=(8,), output="residual")
    model = PoseMLP(rig.num_cameras, num_keypoints, mlp, rngs=nnx.Rngs(seed))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    config = EstimatorConfig(train_cameras=tuple(rig.names), mlp=mlp)
    return Estimator(graphdef, rest, params, rig, config, rig_centre_and_radius(rig))


def read_trc(path) -> dict:
    """A TRC file read by the format's description alone (not by mvpose-jax's writer): line 1
    ``PathFileType``; lines 2-3 header keys and values; line 4 ``Frame#``, ``Time`` and each
    marker's name over its three columns; line 5 ``X1 Y1 Z1 ...``; then, after any blank lines,
    one tab-separated row per frame, an empty field where a marker is missing.

    Returns:
      dict: header (key -> text), names (M,), frame (N,) int, time (N,), xyz (N, M, 3) NaN missing.
    """
    lines = Path(path).read_text(encoding="utf-8").split("\n")
    assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"], lines[0]
    header = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
    columns = lines[3].split("\t")
    assert columns[:2] == ["Frame#", "Time"], columns[:2]
    M = int(header["NumMarkers"])
    names = [columns[2 + 3 * m] for m in range(M)]
    assert all(c == "" for m in range(M) for c in columns[3 + 3 * m : 5 + 3 * m])
    axes = lines[4].split("\t")
    assert axes[2 : 2 + 3 * M] == [f"{a}{m}" for m in range(1, M + 1) for a in "XYZ"]
    rows = [line.split("\t") for line in lines[5:] if line.strip()]
    assert len(rows) == int(header["NumFrames"])
    xyz = np.full((len(rows), M, 3), np.nan)
    for n, row in enumerate(rows):
        values = row[2 : 2 + 3 * M]
        assert len(values) == 3 * M and all(v == "" for v in row[2 + 3 * M :]), row
        for m in range(M):
            triple = values[3 * m : 3 * m + 3]
            assert all(v == "" for v in triple) or all(v != "" for v in triple), triple
            if triple[0]:
                xyz[n, m] = [float(v) for v in triple]
    return dict(
        header=header,
        names=names,
        frame=np.array([int(r[0]) for r in rows]),
        time=np.array([float(r[1]) for r in rows]),
        xyz=xyz,
    )


def read_c3d(path) -> dict:
    """A C3D file read by the C3D manual alone (Intel byte order, float points, no analog): the
    512-byte header, the parameter section (groups and parameters, arrays column-major), and
    the 3D data (x, y, z and a fourth word: negative = invalid, else residual byte low, camera
    mask high).

    Returns:
      dict: parameters {GROUP: {PARAM: value}} (strings as lists of stripped str, numbers as
      arrays indexed as the manual's dimensions), first_frame, rate, xyz (N, M, 3) NaN invalid,
      residual (N, M) int (-1 invalid), labels (M,) (LABELS, LABELS2 ...).
    """
    data = Path(path).read_bytes()
    header = np.frombuffer(data[:512], "<i2")
    assert data[1] == 0x50, "not a C3D file"
    num_points, first_frame, last_frame = int(header[1]), int(header[3]), int(header[4])
    data_start = int(header[8])
    rate = float(np.frombuffer(data[20:24], "<f4")[0])
    start = (data[0] - 1) * 512
    assert data[start + 3] == 84, "expected Intel processor type"
    groups, params, pos = {}, [], start + 4
    while True:
        name_len, ident = (int(v) for v in np.frombuffer(data[pos : pos + 2], "i1"))
        if name_len == 0:
            break
        name_len = abs(name_len)
        name = data[pos + 2 : pos + 2 + name_len].decode()
        body = pos + 2 + name_len
        offset = int(np.frombuffer(data[body : body + 2], "<i2")[0])
        if ident < 0:
            groups[-ident] = name
        else:
            kind, ndim = (int(v) for v in np.frombuffer(data[body + 2 : body + 4], "i1"))
            dims = list(data[body + 4 : body + 4 + ndim])
            raw = data[body + 4 + ndim : body + 4 + ndim + abs(kind) * int(np.prod(dims))]
            if kind == -1:
                if len(dims) <= 1:
                    value = [raw.decode().strip()]
                else:
                    width = dims[0]
                    value = [raw[i : i + width].decode().strip() for i in range(0, len(raw), width)]
            else:
                dtype = {1: "i1", 2: "<i2", 4: "<f4"}[kind]
                # column-major: the first dimension varies fastest
                value = (
                    np.frombuffer(raw, dtype).reshape(dims[::-1]).T
                    if dims
                    else (np.frombuffer(raw, dtype)[0])
                )
            params.append((ident, name, value))
        if offset == 0:
            break
        pos = body + offset
    parameters = {g: {} for g in groups.values()}
    for ident, name, value in params:
        parameters[groups[ident]][name] = value
    point = parameters["POINT"]
    assert int(point["USED"]) == num_points
    assert float(point["SCALE"]) < 0, "expected float points"
    num_frames = last_frame - first_frame + 1
    words = np.frombuffer(
        data[(data_start - 1) * 512 :][: num_frames * num_points * 16], "<f4"
    ).reshape(num_frames, num_points, 4)
    invalid = words[..., 3] < 0
    xyz = np.where(invalid[..., None], np.nan, words[..., :3].astype(np.float64))
    residual = np.where(invalid, -1, words[..., 3].astype(np.int64) & 0xFF)
    labels = []
    for i in range(1, 100):
        key = "LABELS" if i == 1 else f"LABELS{i}"
        if key not in point:
            break
        labels += point[key]
    return dict(
        parameters=parameters,
        first_frame=first_frame,
        rate=rate,
        xyz=xyz,
        residual=residual,
        labels=labels[:num_points],
    )


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
