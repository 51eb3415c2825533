"""Calibration loaders (native JSON, CMU Panoptic JSON, anipose/Pose2Sim TOML) and presets."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from mvpose_jax.cameras import camera_centres
from mvpose_jax.data import calibration
from mvpose_jax.errors import InputError
from tests.helpers import panoptic_dict, toml_text


def _assert_same_rig(a, b, atol=1e-6):
    assert a.names == b.names
    for field in ("K", "dist", "R", "t", "size"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), atol=atol, err_msg=field)


def test_presets_are_the_papers_rigs():
    pan = calibration.load_rig("panoptic5")
    arp = calibration.load_rig("arplab6")
    assert pan.names == ("trackera", "trackerb", "trackerc", "trackerd", "trackere")
    assert arp.names[-2:] == ("orinbot_l", "orinbot_r") and arp.num_cameras == 6
    assert pan.up == (0.0, -1.0, 0.0) and arp.up == (0.0, 0.0, -1.0)
    # The robot's two cameras are a short stereo pair (~10 cm apart).
    c = np.asarray(camera_centres(arp))
    assert 0.05 < np.linalg.norm(c[4] - c[5]) < 0.2


def test_native_round_trip(preset_rig, tmp_path):
    path = tmp_path / "rig.json"
    calibration.save_rig(preset_rig, path)
    _assert_same_rig(calibration.load_rig(path), preset_rig)
    assert calibration.load_rig(path).up == preset_rig.up
    sub = calibration.load_rig(path, cameras=[preset_rig.names[2], preset_rig.names[0]])
    assert sub.names == (preset_rig.names[2], preset_rig.names[0])


def test_panoptic_json_selects_cameras_and_converts_centimetres(tmp_path):
    pan = calibration.load_rig("panoptic5")
    path = tmp_path / "calibration_160224_haggling1.json"
    path.write_text(json.dumps(panoptic_dict(pan, source="160224_haggling1", vga_decoy=True)))
    rig = calibration.load_rig(path, cameras=["00_00", "00_01", "00_02", "00_03", "00_04"])
    np.testing.assert_allclose(rig.t, pan.t, atol=1e-6)
    np.testing.assert_allclose(rig.R, pan.R, atol=1e-7)
    assert rig.up == (0.0, -1.0, 0.0)
    assert calibration.load_rig(path).num_cameras == 6  # all cameras without a selection
    with pytest.raises(InputError) as e:
        calibration.load_rig(path, cameras=["00_03", "00_99"])
    assert e.value.camera == "00_99" and e.value.file == str(path)


def test_toml_anipose_pose2sim(tmp_path):
    arp = calibration.load_rig("arplab6")  # no distortion, so 4 coefficients lose nothing
    path = tmp_path / "Calib.toml"
    path.write_text(toml_text(arp))
    _assert_same_rig(calibration.load_rig(path), arp, atol=1e-5)
    # anipose in millimetres
    path.write_text(toml_text(arp, scale=1e-3))
    _assert_same_rig(calibration.load_rig(path, translation_scale=1e-3), arp, atol=1e-5)


def test_rodrigues_matches_opencv():
    rng = np.random.default_rng(0)
    for rvec in list(rng.normal(size=(20, 3))) + [np.zeros(3), np.array([np.pi, 0, 0])]:
        np.testing.assert_allclose(calibration.rodrigues(rvec), cv2.Rodrigues(rvec)[0], atol=1e-12)


def _native(**overrides):
    cam = {
        "name": "cam0",
        "width": 1920,
        "height": 1080,
        "K": [[1000, 0, 960], [0, 1000, 540], [0, 0, 1]],
        "dist": [0, 0, 0, 0, 0],
        "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        "t": [0, 0, 3],
    }
    cam.update(overrides)
    return {"cameras": [cam]}


@pytest.mark.parametrize(
    "text, field, camera, match",
    [
        ("", None, None, "empty"),
        ('{"cameras": [', None, None, "malformed JSON at line 1"),
        (json.dumps(_native(R=[[1, 0, 0], [0, 1, 0], [0, 0.5, 1]])), "R", "cam0", "orthonormal"),
        (json.dumps(_native(K=[[1000, 0, 960], [0, 0, 540], [0, 0, 1]])), "K", "cam0", "singular"),
        (json.dumps(_native(K=[[1000, 0], [0, 1000]])), "K", "cam0", "3x3"),
        (json.dumps(_native(t=[0, 0])), "t", "cam0", "3 numbers"),
        (json.dumps(_native(dist=[0, 0, 0])), "dist", "cam0", "4 or 5"),
        (json.dumps(_native(t=[0, "x", 1])), "t", "cam0", "numbers"),
        (json.dumps(_native(width=-5)), "size", "cam0", "positive"),
        (
            json.dumps(_native()).replace('"t": [0, 0, 3]', '"t": [0, NaN, 3]'),
            None,
            None,
            "non-finite",
        ),
        (json.dumps({"cameras": []}), "cameras", None, "non-empty"),
        (json.dumps(_native(name=None)), "name", 0, "camera name"),
        (json.dumps({"cameras": [{"name": "a"}]}), "K", "a", "missing"),
        ("[1, 2]", None, None, "cameras"),
    ],
)
def test_native_loader_rejects_bad_input(tmp_path, text, field, camera, match):
    path = tmp_path / "calib.json"
    path.write_text(text)
    with pytest.raises(InputError, match=match) as e:
        calibration.load_rig(path)
    assert e.value.file == str(path)
    assert e.value.field == field and e.value.camera == camera


@pytest.mark.parametrize(
    "text, field, match",
    [
        ("[cam_1\nname = 'a'", None, "malformed TOML"),
        ("[metadata]\nerror = 0.0\n", "cameras", "no camera tables"),
        (
            '[cam_1]\nname = "a"\nsize = [1920, 1080]\nmatrix = [[1000, 0, 960], [0, 1000, 540], [0, 0, 1]]\n'
            "distortions = [0, 0, 0, 0]\nrotation = [0, 0, 0]\ntranslation = [0, nan, 0]\n",
            "translation",
            "NaN",
        ),
        (
            '[cam_1]\nname = "a"\nsize = [1920, 1080]\nmatrix = [[1000, 0, 960], [0, 1000, 540], [0, 0, 1]]\n'
            "distortions = [0, 0, 0, 0]\nrotation = [0, 0, 0]\n",
            "translation",
            "missing",
        ),
        ('[cam_1]\nname = "a"\nfisheye = true\n', "fisheye", "not supported"),
    ],
)
def test_toml_loader_rejects_bad_input(tmp_path, text, field, match):
    path = tmp_path / "calib.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=match) as e:
        calibration.load_rig(path)
    assert e.value.file == str(path) and e.value.field == field


def test_unknown_preset_and_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        calibration.load_rig(tmp_path / "nope.json")
    with pytest.raises(InputError, match="no such file"):
        calibration.load_rig("panoptic6")  # not a preset: treated as a path
    with pytest.raises(InputError, match="unknown rig preset"):
        calibration.load_preset("panoptic6")


def test_millimetre_translations_without_a_scale_are_flagged(tmp_path):
    arp = calibration.load_rig("arplab6")
    path = tmp_path / "Calib.toml"
    path.write_text(toml_text(arp, scale=1e-3))  # translations in mm, read as metres
    with pytest.warns(calibration.CalibrationWarning, match="--translation-scale 0.001") as w:
        calibration.load_rig(path)
    assert "millimetres" in str(w[0].message) and str(path) in str(w[0].message)
    path.write_text(toml_text(arp, scale=1e3))  # in km: cameras millimetres apart
    with pytest.warns(calibration.CalibrationWarning, match="m from their centre"):
        calibration.load_rig(path)


@pytest.mark.parametrize("scale", [0.0, -1e-3, float("nan"), float("inf")])
def test_a_translation_scale_must_be_positive(tmp_path, scale):
    path = tmp_path / "Calib.toml"
    path.write_text(toml_text(calibration.load_rig("arplab6")))
    with pytest.raises(InputError, match="positive number") as e:
        calibration.load_rig(path, translation_scale=scale)
    assert e.value.field == "translation_scale"


def test_orthonormalise_repairs_rotations_written_with_four_decimals(tmp_path):
    pan = calibration.load_rig("panoptic5")
    doc = calibration.rig_to_dict(pan)
    for cam in doc["cameras"]:
        cam["R"] = np.round(np.asarray(cam["R"]), 4).tolist()
    path = tmp_path / "rounded.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="not orthonormal"):
        calibration.load_rig(path)
    with pytest.warns(calibration.CalibrationWarning, match="nearest rotations") as w:
        rig = calibration.load_rig(path, orthonormalise=True)
    change = float(str(w[0].message).split("largest change ")[1].split(",")[0])
    assert 1e-6 < change < 2e-4  # 4 decimals: each entry within 5e-5 of the truth
    R = np.asarray(rig.R, np.float64)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-6
    )
    np.testing.assert_allclose(R, np.asarray(pan.R), atol=1e-4)
    # The nearest rotation (closed form for a scaled rotation: the rotation itself).
    np.testing.assert_allclose(calibration.nearest_rotation(1.3 * np.asarray(pan.R[0], np.float64)),
                               np.asarray(pan.R[0]), atol=1e-6)  # fmt: skip


def test_orthonormalise_does_not_hide_a_wrong_matrix(tmp_path):
    doc = calibration.rig_to_dict(calibration.load_rig("panoptic5"))
    doc["cameras"][2]["R"] = (1.1 * np.asarray(doc["cameras"][2]["R"])).tolist()
    path = tmp_path / "scaled.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="far from a rotation") as e:
        calibration.load_rig(path, orthonormalise=True)
    assert e.value.camera == doc["cameras"][2]["name"] and e.value.field == "R"
