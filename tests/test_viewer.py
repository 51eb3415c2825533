"""The rerun viewer file: written, then read back with rerun's own reader."""

from __future__ import annotations

import collections
import os
import sys

import numpy as np
import pytest

pa = pytest.importorskip("pyarrow")
rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from mvpose_jax.cameras import make_rig, project_points, up_vector  # noqa: E402
from mvpose_jax.data.poses import PoseResults  # noqa: E402
from mvpose_jax.data.recording import Recording  # noqa: E402
from mvpose_jax.errors import InputError  # noqa: E402
from mvpose_jax.skeletons import Detections, Poses3D, get_layout  # noqa: E402
from mvpose_jax.viewer import UNMATCHED_CLASS_ID, UNTRACKED_CLASS_ID, write_rerun  # noqa: E402
from tests.helpers import random_rig, scene_points  # noqa: E402

F, G, C = 4, 2, 3
TRACKS = (3, 7)
FPS = 25.0


def read_rrd(path) -> dict:
    """Every logged row: {entity: [(frame or None, time in ns or None, {component: batch})]},
    each entity's rows by frame.

    A component's value is its batch (a list, one element for one-value components).
    """
    rows = collections.defaultdict(list)
    for chunk in RrdReader(path).stream():
        record = chunk.to_record_batch()
        batch = record.to_pydict()
        if "time" in batch:  # a duration column; as integer nanoseconds
            batch["time"] = record.column("time").cast(pa.int64()).to_pylist()
        for r in range(chunk.num_rows):
            values = {k: v[r] for k, v in batch.items() if ":" in k and v[r] is not None}
            frame = batch["frame"][r] if "frame" in batch else None
            time = batch["time"][r] if "time" in batch else None
            rows[chunk.entity_path].append((frame, time, values))
    # Chunks come in no promised order: rows in time order, static ones first.
    for entity_rows in rows.values():
        entity_rows.sort(key=lambda row: -1 if row[0] is None else row[0])
    return rows


@pytest.fixture(scope="module")
def result():
    """Two tracked people over four frames seen by three cameras; the second one leaves at frame
    2, a keypoint of the first is missing at frame 1; detections are their projections, plus one
    false positive in camera 0."""
    rig = random_rig(seed=3, num_cameras=C)
    layout = get_layout("coco18")
    K = layout.num_keypoints
    xyz = scene_points(rig, 0, (F, G, K)) * np.float32(0.5)
    xyz = xyz + np.asarray([[0.0, 0.0, 0.0], [0.8, 0.0, 0.0]], np.float32)[None, :, None]
    valid = np.ones((F, G), bool)
    valid[2, 1] = False
    kp_valid = np.repeat(valid[..., None], K, axis=-1)
    kp_valid[1, 0, 5] = False
    poses = Poses3D(np.where(kp_valid[..., None], xyz, 0.0), valid, kp_valid)
    px = np.asarray(project_points(rig, xyz))  # (C, F, G, K, 2)
    P = G + 1
    det_xy = np.zeros((F, C, P, K, 2), np.float32)
    score = np.zeros((F, C, P, K), np.float32)
    count = np.zeros((F, C), np.int32)
    identity = np.full((F, C, P), -1, np.int32)
    members = np.full((F, G, C), -1, np.int32)
    for f in range(F):
        for c in range(C):
            p = 0
            for g in range(G):
                if valid[f, g]:
                    det_xy[f, c, p], score[f, c, p] = px[c, f, g], 0.9
                    identity[f, c, p], members[f, g, c] = g, p
                    p += 1
            if c == 0:  # a false positive no person used
                det_xy[f, c, p], score[f, c, p, :4] = 100.0, 0.5
                p += 1
            count[f, c] = p
    track = np.where(valid, np.asarray(TRACKS)[None], -1).astype(np.int32)
    timestamps = np.arange(F) / FPS
    results = PoseResults(
        poses,
        np.where(valid, 0.9, 0.0).astype(np.float32),
        members,
        identity,
        rig.names,
        "coco18",
        timestamps,
        track,
    )
    recording = Recording(Detections(det_xy, score, count), rig.names, "coco18")
    return rig, results, recording


@pytest.fixture(scope="module")
def written(result, tmp_path_factory):
    rig, results, recording = result
    path = tmp_path_factory.mktemp("viewer") / "out" / "scene.rrd"
    assert write_rerun(path, results, rig, detections=recording) == path
    assert not [p for p in path.parent.iterdir() if p.name != "scene.rrd"]  # no temp file left
    assert len(RrdReader(path).blueprints()) == 1  # the opening layout of the views
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # as open() makes files, not private
    return read_rrd(path)


def test_the_file_holds_cameras_people_floor_and_detections(result, written):
    rig, results, _ = result
    cams = [f"/world/cameras/{n}" for n in rig.names]
    expected = {"/", "/world", "/world/floor"} | set(cams) | {f"{c}/image" for c in cams}
    expected |= {f"{c}/image/border" for c in cams}
    expected |= {f"/world/people/track_{t}" for t in TRACKS}
    expected |= {f"{c}/image/reprojections/track_{t}" for c in cams for t in TRACKS}
    expected |= {f"{c}/image/detections/{p}" for c in cams for p in range(G)}
    expected |= {f"{cams[0]}/image/detections/{G}"}  # camera 0's false positive
    assert expected <= set(written)
    assert not {e for e in written if "person_" in e}  # tracked: entities are tracks

    # Cameras: static transform and pinhole with each image's size.
    for c, cam in enumerate(cams):
        ((frame, _, pinhole),) = written[f"{cam}/image"]
        assert frame is None
        assert pinhole["Pinhole:resolution"][0] == pytest.approx(np.asarray(rig.size[c]))
        ((_, _, border),) = written[f"{cam}/image/border"]
        assert border["Boxes2D:half_sizes"][0] == pytest.approx(np.asarray(rig.size[c]) / 2)
    # The floor is a grid perpendicular to up, at the feet.
    ((_, _, floor),) = written["/world/floor"]
    strips = np.asarray(floor["LineStrips3D:strips"], np.float64)  # (lines, 2, 3)
    up = up_vector(rig)
    assert np.ptp(strips @ up) < 1e-4
    heights = np.asarray(results.poses.xyz, np.float64) @ up  # (F, G, K)
    valid = np.asarray(results.poses.valid)
    lowest = np.where(np.asarray(results.poses.keypoint_valid), heights, np.inf).min(-1)[valid]
    assert float(strips[0, 0] @ up) == pytest.approx(np.median(lowest), abs=1e-4)


def test_the_timeline_has_every_frame_in_seconds(written):
    frames = {f for f, _, _ in written["/world/people/track_3"]}
    assert frames == set(range(F))
    times = sorted({t for _, t, _ in written["/world/people/track_3"]})
    # rerun stores durations in nanoseconds.
    np.testing.assert_allclose(np.asarray(times, np.float64) * 1e-9, np.arange(F) / FPS, atol=1e-9)


def test_people_have_their_track_class_and_their_existing_keypoints(result, written):
    _, results, _ = result
    K = get_layout("coco18").num_keypoints
    for frame, _, v in written["/world/people/track_3"]:
        want = [k for k in range(K) if not (frame == 1 and k == 5)]
        assert v["Points3D:keypoint_ids"] == want
        assert set(v["Points3D:class_ids"]) == {3}
        np.testing.assert_allclose(
            v["Points3D:positions"], np.asarray(results.poses.xyz)[frame, 0, want], atol=1e-6
        )
    # The second person leaves at frame 2: its entity is cleared then and comes back at 3.
    by_frame = {f: v for f, _, v in written["/world/people/track_7"]}
    assert set(by_frame) == set(range(F))
    assert "Points3D:positions" not in by_frame[2] and "Clear:is_recursive" in by_frame[2]
    assert len(by_frame[3]["Points3D:positions"]) == K


def test_the_annotation_context_names_keypoints_and_bones_once(written):
    layout = get_layout("coco18")
    ((frame, _, v),) = written["/"]
    assert frame is None  # static
    classes = {c["class_id"]: c for c in v["AnnotationContext:context"][0]}
    assert set(classes) == {*TRACKS, UNMATCHED_CLASS_ID}
    desc = classes[3]["class_description"]
    assert desc["info"]["label"] == "track 3"
    assert [a["label"] for a in desc["keypoint_annotations"]] == list(layout.keypoints)
    pairs = [(p["keypoint0"], p["keypoint1"]) for p in desc["keypoint_connections"]]
    assert pairs == [tuple(b) for b in layout.bones]


def test_detections_and_reprojections_lie_on_each_other(result, written):
    rig, results, recording = result
    det = recording.detections
    for c, name in enumerate(rig.names):
        cam = f"/world/cameras/{name}/image"
        for frame, _, v in written[f"{cam}/reprojections/track_3"]:
            k = v["Points2D:keypoint_ids"]
            # The detections are the projections here: the reprojection lies on them.
            np.testing.assert_allclose(v["Points2D:positions"], det.xy[frame, c, 0, k], atol=1e-3)
        for _, _, v in written[f"{cam}/detections/0"]:
            assert set(v["Points2D:class_ids"]) == {3}
    fp = written[f"/world/cameras/{rig.names[0]}/image/detections/2"]
    # The false positive is slot 2 while both people are there, slot 1 at frame 2.
    assert {f for f, _, v in fp if "Points2D:class_ids" in v} == {0, 1, 3}
    assert all(
        set(v["Points2D:class_ids"]) == {UNMATCHED_CLASS_ID}
        for _, _, v in fp
        if v.get("Points2D:class_ids")
    )
    assert all(
        v["Points2D:keypoint_ids"] == [0, 1, 2, 3]
        for _, _, v in fp
        if v.get("Points2D:keypoint_ids")
    )


def test_a_person_no_track_took_is_grey_and_named_by_slot(result, tmp_path):
    rig, results, _ = result
    track = np.asarray(results.track).copy()
    track[0, 1] = -1  # the second person, frame 0: valid but untracked
    rows = read_rrd(
        write_rerun(tmp_path / "u.rrd", PoseResults(**{**results.__dict__, "track": track}), rig)
    )
    ((frame, _, v), (cleared, _, clear)) = rows["/world/people/untracked_1"]
    assert frame == 0 and set(v["Points3D:class_ids"]) == {UNTRACKED_CLASS_ID}
    assert cleared == 1 and "Clear:is_recursive" in clear  # frame 1: tracked again
    assert {f for f, _, _ in rows["/world/people/track_7"]} == {1, 2, 3}  # from 1, cleared at 2
    ((_, _, context),) = rows["/"]
    labels = {
        c["class_id"]: c["class_description"]["info"]["label"]
        for c in context["AnnotationContext:context"][0]
    }
    assert labels[UNTRACKED_CLASS_ID] == "untracked"


def test_camera_transform_and_pinhole_project_as_the_rig_does(tmp_path):
    """What rerun's Transform3D (parent from child: x_world = M x_cam + T, the matrix stored
    column-major) and Pinhole (pixel ~ image_from_camera x_cam) imply, against `project_points`."""
    ring = random_rig(seed=5, num_cameras=C)
    rig = make_rig(ring.K, np.zeros((C, 5)), ring.R, ring.t, ring.size, ring.names)  # ideal lens
    layout = get_layout("coco18")
    K = layout.num_keypoints
    xyz = scene_points(rig, 1, (1, 1, K))
    results = PoseResults(
        Poses3D(xyz, np.ones((1, 1), bool), np.ones((1, 1, K), bool)),
        np.ones((1, 1), np.float32),
        np.zeros((1, 1, C), np.int32),
        np.zeros((1, C, 1), np.int32),
        rig.names,
        "coco18",
    )
    path = write_rerun(tmp_path / "one.rrd", results, rig, floor_height=0.0)
    rows = read_rrd(path)
    want = np.asarray(project_points(rig, xyz[0, 0]))  # (C, K, 2)
    for c, name in enumerate(rig.names):
        ((_, _, tf),) = rows[f"/world/cameras/{name}"]
        ((_, _, pin),) = rows[f"/world/cameras/{name}/image"]
        world_from_cam = np.asarray(tf["Transform3D:mat3x3"][0], np.float64).reshape(
            3, 3, order="F"
        )
        translation = np.asarray(tf["Transform3D:translation"][0], np.float64)
        image_from_cam = np.asarray(pin["Pinhole:image_from_camera"][0], np.float64).reshape(
            3, 3, order="F"
        )
        x_cam = (xyz[0, 0].astype(np.float64) - translation) @ world_from_cam  # M^T (x - T)
        assert (x_cam[:, 2] > 0).all()
        h = x_cam @ image_from_cam.T
        np.testing.assert_allclose(h[:, :2] / h[:, 2:], want[c], atol=1e-2)
    # No timestamps and no fps: only the frame timeline.
    assert all(t is None for _, t, _ in rows["/world/people/person_0"])


def test_bad_inputs_name_the_field(result, tmp_path):
    rig, results, recording = result
    with pytest.raises(InputError, match="cameras"):
        write_rerun(tmp_path / "x.rrd", results, rig.select([0, 1]))
    short = Recording(
        Detections(*(np.asarray(a)[:2] for a in recording.detections)), rig.names, "coco18"
    )
    with pytest.raises(InputError, match="detections have 2 frames"):
        write_rerun(tmp_path / "x.rrd", results, rig, detections=short)
    assert not list(tmp_path.iterdir())


def test_without_rerun_the_error_says_what_to_install(result, tmp_path, monkeypatch):
    rig, results, _ = result
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` now raises ImportError
    with pytest.raises(ImportError, match=r'pip install "mvpose-jax\[viewer\]"'):
        write_rerun(tmp_path / "x.rrd", results, rig)
