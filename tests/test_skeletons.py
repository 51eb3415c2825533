"""Keypoint layouts: names, bones, flips and conversions."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_jax import skeletons
from mvpose_jax.errors import InputError


# Face points (the 68-point face's contours, the pupils, BlazePose's mouth corners) are drawn as
# their own outlines; every other keypoint is joined to the body.
def _face_part(name: str) -> bool:
    return name.startswith("face_") or name.endswith(("_pupil", "_mouth"))


@pytest.mark.parametrize(
    "name, num",
    [
        ("coco18", 18),
        ("coco17", 17),
        ("body25", 25),
        ("openpose_coco18", 18),
        ("halpe26", 26),
        ("body25b", 25),
        ("body135", 135),
        ("halpe68", 68),
        ("halpe136", 136),
        ("coco133", 133),
        ("mpii", 16),
        ("blazepose", 33),
    ],
)
def test_layouts(name, num):
    lay = skeletons.get_layout(name)
    assert lay.num_keypoints == num and len(set(lay.keypoints)) == num
    flip = np.array(lay.flip)
    np.testing.assert_array_equal(flip[flip], np.arange(num))  # an involution
    for k, f in enumerate(lay.flip):
        a, b = lay.keypoints[k], lay.keypoints[f]
        assert (
            a == b
            or {a[:2], b[:2]} == {"l_", "r_"}
            and a[2:] == b[2:]
            or a.startswith("face_")
            and b.startswith("face_")
        )
    for a, b in lay.bones:
        assert 0 <= a < num and 0 <= b < num and a != b
    assert {k for bone in lay.bones for k in bone} == set(range(num))  # every keypoint is drawn
    # Bones connect every keypoint but the face's into one skeleton.
    start = lay.index("l_shoulder")
    seen, frontier = {start}, [start]
    while frontier:
        k = frontier.pop()
        for a, b in lay.bones:
            for x, y in ((a, b), (b, a)):
                if x == k and y not in seen:
                    seen.add(y)
                    frontier.append(y)
    assert {k for k in range(num) if not _face_part(lay.keypoints[k])} <= seen


# Keypoint indices as the formats' own documentation numbers them (0-based).
DOCUMENTED_INDICES = {
    # OpenPose experimental_models README (BODY_25B): COCO's 17, 17 UpperNeck, 18 HeadTop,
    # 19 LBigToe, 20 LSmallToe, 21 LHeel, 22 RBigToe, 23 RSmallToe, 24 RHeel.
    "body25b": {
        0: "nose",
        5: "l_shoulder",
        16: "r_ankle",
        17: "upper_neck",
        18: "head",
        19: "l_big_toe",
        21: "l_heel",
        24: "r_heel",
    },
    # OpenPose BODY_135: BODY_25B, 25-44 left hand (25 LThumb1CMC ... 44 LPinky4FingerTip),
    # 45-64 right hand, 65-134 face (65 FaceContour0, 133 RPupil, 134 LPupil).
    "body135": {
        18: "head",
        25: "l_thumb_1",
        29: "l_index_1",
        44: "l_pinky_4",
        45: "r_thumb_1",
        64: "r_pinky_4",
        65: "face_0",
        132: "face_67",
        133: "r_pupil",
        134: "l_pupil",
    },
    # AlphaPose's HALPE_68 (Halpe-FullBody without the face): HALPE_26, then 21 + 21 hand points
    # (hand point 0 the wrist, 1-4 thumb, 5-8 index, ..., 17-20 pinky).
    "halpe68": {
        17: "head",
        18: "neck",
        19: "mid_hip",
        25: "r_heel",
        26: "l_hand_root",
        28: "l_thumb_2",
        47: "r_hand_root",
        64: "r_pinky_1",
        67: "r_pinky_4",
    },
    # HALPE dataset README (136): 0-25 body, 26-93 face, 94-114 left hand, 115-135 right hand.
    "halpe136": {
        18: "neck",
        26: "face_0",
        93: "face_67",
        94: "l_hand_root",
        99: "l_index_1",
        115: "r_hand_root",
        135: "r_pinky_4",
    },
    # COCO-WholeBody README: 0-16 body, 17-22 feet (17 left big toe, 18 left small toe, 19 left
    # heel, 20-22 right), 23-90 face, 91-111 left hand, 112-132 right hand.
    "coco133": {
        16: "r_ankle",
        17: "l_big_toe",
        18: "l_small_toe",
        19: "l_heel",
        20: "r_big_toe",
        22: "r_heel",
        23: "face_0",
        90: "face_67",
        91: "l_hand_root",
        112: "r_hand_root",
        132: "r_pinky_4",
    },
    # MPII Human Pose joint ids: 0 r ankle, 1 r knee, 2 r hip, 3 l hip, 4 l knee, 5 l ankle,
    # 6 pelvis, 7 thorax, 8 upper neck, 9 head top, 10 r wrist, 11 r elbow, 12 r shoulder,
    # 13 l shoulder, 14 l elbow, 15 l wrist.
    "mpii": {
        0: "r_ankle",
        2: "r_hip",
        3: "l_hip",
        6: "pelvis",
        7: "thorax",
        8: "upper_neck",
        9: "head",
        10: "r_wrist",
        12: "r_shoulder",
        15: "l_wrist",
    },
    # MediaPipe Pose landmarks: 0 nose, 2 left eye, 5 right eye, 7 left ear, 8 right ear, 9 mouth
    # (left), 11 left shoulder, 12 right shoulder, 15 left wrist, 17 left pinky, 23 left hip,
    # 28 right ankle, 29 left heel, 31 left foot index, 32 right foot index.
    "blazepose": {
        0: "nose",
        2: "l_eye",
        5: "r_eye",
        7: "l_ear",
        8: "r_ear",
        9: "l_mouth",
        11: "l_shoulder",
        12: "r_shoulder",
        15: "l_wrist",
        17: "l_pinky",
        23: "l_hip",
        28: "r_ankle",
        29: "l_heel",
        31: "l_foot_index",
        32: "r_foot_index",
    },
}


@pytest.mark.parametrize("name", sorted(DOCUMENTED_INDICES))
def test_layout_orders_follow_the_documentation(name):
    lay = skeletons.get_layout(name)
    for k, keypoint in DOCUMENTED_INDICES[name].items():
        assert lay.keypoints[k] == keypoint, (k, lay.keypoints[k])


def test_face_flips_mirror_the_68_point_face():
    lay = skeletons.get_layout("coco133")
    face0 = 23  # COCO-WholeBody's face starts at 23
    # iBUG 300-W (0-based): jaw 0 <-> 16, chin 8 on the midline, brow ends 17 <-> 26, eye
    # corners 36 <-> 45, mouth corners 48 <-> 54, nose tip 30 on the midline.
    for a, b in ((0, 16), (8, 8), (17, 26), (36, 45), (39, 42), (48, 54), (30, 30), (62, 62)):
        assert lay.flip[face0 + a] == face0 + b and lay.flip[face0 + b] == face0 + a
    assert lay.flip[91] == 112  # left hand root <-> right hand root


# coco18 keypoints each layout cannot give: MPII has no face but the upper neck and head top.
MISSING_IN_COCO18 = {"mpii": {"nose", "l_eye", "r_eye", "l_ear", "r_ear"}}


@pytest.mark.parametrize("name", sorted(set(skeletons.LAYOUTS) - {"coco18"}))
def test_coco18_survives_a_trip_through_each_layout(name):
    """coco18 points placed in a layout by name (the inverse mapping), with the layout's other
    points random, come back unchanged; the neck, where the layout has none, is the shoulders'
    midpoint, as the ground truth is built."""
    rng = np.random.default_rng(3)
    coco18 = skeletons.get_layout("coco18")
    lay = skeletons.get_layout(name)
    n = 5
    truth = rng.uniform(0, 1000, size=(n, 18, 2)).astype(np.float32)
    score = rng.uniform(0.1, 1.0, size=(n, 18)).astype(np.float32)
    score[rng.uniform(size=score.shape) < 0.2] = 0.0
    ls, rs, neck = coco18.index("l_shoulder"), coco18.index("r_shoulder"), coco18.index("neck")
    both = (score[:, ls] > 0) & (score[:, rs] > 0)
    truth[:, neck] = (truth[:, ls] + truth[:, rs]) / 2
    score[:, neck] = np.where(both, np.minimum(score[:, ls], score[:, rs]), 0.0)
    truth[score == 0] = 0.0
    # Built in the layout: every other point random (extras carried, then dropped).
    xy = rng.uniform(0, 1000, size=(n, lay.num_keypoints, 2)).astype(np.float32)
    sc = rng.uniform(0.1, 1.0, size=(n, lay.num_keypoints)).astype(np.float32)
    for k, keypoint in enumerate(coco18.keypoints):
        if keypoint in lay.keypoints:
            xy[:, lay.index(keypoint)], sc[:, lay.index(keypoint)] = truth[:, k], score[:, k]
    back, back_score = skeletons.convert_keypoints(xy, sc, name, "coco18")
    missing = MISSING_IN_COCO18.get(name, set())
    for k, keypoint in enumerate(coco18.keypoints):
        if keypoint in missing:
            assert not back_score[:, k].any() and not back[:, k].any()
        else:
            np.testing.assert_array_equal(back_score[:, k], score[:, k], err_msg=keypoint)
            np.testing.assert_allclose(back[:, k], truth[:, k], rtol=1e-6, err_msg=keypoint)


def test_coco18_matches_the_design():
    lay = skeletons.get_layout("coco18")
    assert (
        lay.keypoints[0] == "nose"
        and lay.keypoints[17] == "neck"
        and lay.keypoints[10] == "r_wrist"
    )
    assert len(skeletons.evaluation_keypoints("coco18")) == 14  # all but eyes and ears


def test_coco17_to_coco18_builds_the_neck():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 100, size=(3, 17, 2)).astype(np.float32)
    score = rng.uniform(0.1, 1.0, size=(3, 17)).astype(np.float32)
    score[1, 6] = 0.0  # person 1 misses the right shoulder
    out_xy, out_score = skeletons.convert_keypoints(xy, score, "coco17", "coco18")
    assert out_xy.shape == (3, 18, 2)
    np.testing.assert_allclose(out_xy[:, :17][score > 0], xy[score > 0])
    np.testing.assert_allclose(out_xy[0, 17], (xy[0, 5] + xy[0, 6]) / 2, rtol=1e-6)
    assert out_score[0, 17] == min(score[0, 5], score[0, 6])
    assert out_score[1, 17] == 0.0  # a derived keypoint needs all of its sources


def test_body25_round_trip_keeps_shared_keypoints():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 100, size=(4, 25, 2))
    vis = rng.uniform(size=(4, 25)) > 0.2
    c18, v18 = skeletons.convert_keypoints(xy, vis, "body25", "coco18")
    back, vback = skeletons.convert_keypoints(c18, v18, "coco18", "body25")
    b25 = skeletons.get_layout("body25")
    for k, name in enumerate(b25.keypoints):
        if name in skeletons.get_layout("coco18").keypoints:
            np.testing.assert_array_equal(vback[:, k], vis[:, k])
            np.testing.assert_allclose(back[:, k][vis[:, k]], xy[:, k][vis[:, k]])
        elif name == "mid_hip":
            both = vis[:, b25.index("l_hip")] & vis[:, b25.index("r_hip")]
            np.testing.assert_array_equal(vback[:, k], both)
        else:  # feet: coco18 has none
            assert not vback[:, k].any()


def test_flip_keypoints_swaps_sides():
    lay = skeletons.get_layout("coco18")
    values = np.arange(18)[:, None] * np.ones((1, 3))
    flipped = skeletons.flip_keypoints(values, "coco18")
    assert flipped[lay.index("l_wrist"), 0] == lay.index("r_wrist")
    assert flipped[lay.index("neck"), 0] == lay.index("neck")


def test_unknown_layout():
    with pytest.raises(InputError, match="unknown keypoint layout"):
        skeletons.get_layout("coco19")


@pytest.mark.parametrize("shape", [(2, 3, 4), (2, 5, 4), (3, 5, 7)])
def test_zero_padded_is_np_pad_at_the_ends(shape):
    a = np.arange(24, dtype=np.float32).reshape(2, 3, 4) + 1
    expected = np.pad(a, [(0, n - m) for m, n in zip(a.shape, shape, strict=True)])
    out = skeletons.zero_padded(a, shape)
    np.testing.assert_array_equal(out, expected)
    assert out.dtype == a.dtype
    assert (out is a) == (shape == a.shape)  # no copy where nothing is padded


def test_skeleton_slots_are_multiples_of_four():
    slots = [skeletons.skeleton_slots(p) for p in (0, 1, 3, 4, 5, 8, 9, 13)]
    assert slots == [4, 4, 4, 4, 8, 8, 12, 16]
