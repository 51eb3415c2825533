"""Keypoint layouts: names, bones, flips and conversions."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_jax import skeletons
from mvpose_jax.errors import InputError


@pytest.mark.parametrize("name, num", [("coco18", 18), ("coco17", 17), ("body25", 25)])
def test_layouts(name, num):
    lay = skeletons.get_layout(name)
    assert lay.num_keypoints == num and len(set(lay.keypoints)) == num
    flip = np.array(lay.flip)
    np.testing.assert_array_equal(flip[flip], np.arange(num))  # an involution
    for k, f in enumerate(lay.flip):
        a, b = lay.keypoints[k], lay.keypoints[f]
        assert a == b or {a[:2], b[:2]} == {"l_", "r_"} and a[2:] == b[2:]
    for a, b in lay.bones:
        assert 0 <= a < num and 0 <= b < num and a != b
    # Bones connect every keypoint into one skeleton.
    seen, frontier = {0}, [0]
    while frontier:
        k = frontier.pop()
        for a, b in lay.bones:
            for x, y in ((a, b), (b, a)):
                if x == k and y not in seen:
                    seen.add(y)
                    frontier.append(y)
    assert len(seen) == num


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
