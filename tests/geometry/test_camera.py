"""CameraModel: YAML/CameraInfo/JSON forms, projection ↔ undistortion for every model."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tagtrail.errors import SourceError
from tagtrail.geometry.camera import CameraModel
from tagtrail.io.camera_files import read_camera_file
from tests.io import bags

K = [500.0, 0.0, 320.0, 0.0, 505.0, 240.0, 0.0, 0.0, 1.0]
MODELS = {
    "none": [],
    "plumb_bob": [0.1, -0.2, 0.001, 0.002, 0.05],
    "rational_polynomial": [0.1, -0.2, 0.001, 0.002, 0.05, 0.01, -0.02, 0.01],
    "equidistant": [0.05, -0.01, 0.002, -0.001],
}


def points_cam(n: int = 200) -> np.ndarray:
    rng = np.random.default_rng(0)
    z = rng.uniform(0.5, 3.0, n)
    xy = rng.uniform(-0.5, 0.5, (n, 2)) * z[:, None]
    return np.c_[xy, z].reshape(10, -1, 3)  # a batch dimension too


@pytest.mark.parametrize("model", list(MODELS))
def test_undistort_inverts_project(model: str) -> None:
    cam = CameraModel(640, 480, K, MODELS[model], model)
    p = points_cam()
    px = cam.project(p)
    assert px.shape == p.shape[:-1] + (2,)
    np.testing.assert_allclose(cam.undistort(px), p[..., :2] / p[..., 2:], atol=1e-10)


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial", "equidistant"])
def test_project_matches_opencv(model: str) -> None:
    cam = CameraModel(640, 480, K, MODELS[model], model)
    p = points_cam().reshape(-1, 3)
    Km = np.array(K).reshape(3, 3)
    if model == "equidistant":
        ref, _ = cv2.fisheye.projectPoints(
            p[None], np.zeros(3), np.zeros(3), Km, np.array(MODELS[model])
        )
    else:
        ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), Km, np.array(MODELS[model]))
    np.testing.assert_allclose(cam.project(p), ref.reshape(-1, 2), atol=1e-9)
    assert not np.allclose(cam.project(p), CameraModel(640, 480, K, [], "none").project(p))


@pytest.mark.parametrize("model", list(MODELS))
def test_scaled_maps_pixels_about_the_image_corner(model: str) -> None:
    cam = CameraModel(640, 480, K, MODELS[model], model)
    big = cam.scaled(1280, 720)
    assert (big.width, big.height, big.distortion_model) == (1280, 720, model)
    np.testing.assert_array_equal(big.D, cam.D)
    p = points_cam()
    # The image's outer corner (-0.5, -0.5) stays put; pixel sizes scale by 2 and 1.5.
    np.testing.assert_allclose(big.project(p) + 0.5, (cam.project(p) + 0.5) * [2.0, 1.5], atol=1e-9)
    assert big.scaled(640, 480).same_as(cam)
    with pytest.raises(SourceError, match="0x480"):
        cam.scaled(0, 480)


def test_none_model_is_k_inverse() -> None:
    cam = CameraModel(640, 480, K, [], "none")
    np.testing.assert_allclose(cam.undistort([[320.0, 240.0], [820.0, 745.0]]), [[0, 0], [1, 1]])


@pytest.mark.parametrize("model", list(MODELS))
def test_from_camera_info_and_json_round_trip(model: str) -> None:
    cam = CameraModel(640, 480, K, MODELS[model], model)
    back = CameraModel.from_camera_info(bags.camera_info_msg(cam))
    assert back.same_as(cam)
    d = json.loads(json.dumps(cam.to_dict()))
    assert set(d) == {"width", "height", "distortion_model", "K", "D"}
    assert len(d["K"]) == 9 and d["D"] == MODELS[model]
    assert CameraModel.from_dict(d).same_as(cam)


def test_from_yaml_camera_calibration_format(realdata: Path) -> None:
    cam = read_camera_file(realdata / "photonvision_frc2024_field/images/camera.yaml")
    assert (cam.width, cam.height, cam.distortion_model) == (1280, 720, "plumb_bob")
    assert cam.K[0, 0] == 1142.3413236140077 and cam.D[4] == 2.502076853514765


def test_from_yaml_simple_meta_form(realdata: Path) -> None:
    cam = read_camera_file(realdata / "swatbotics_mapping_feb_2014/meta.yaml")
    assert (cam.width, cam.height, cam.distortion_model) == (816, 612, "none")
    np.testing.assert_allclose(cam.K, [[765.0, 0, 393.72], [0, 764.18, 304.66], [0, 0, 1]])
    cam = read_camera_file(realdata / "photonvision_frc2024_field/meta.yaml")
    assert cam.distortion_model == "plumb_bob" and cam.D.size == 5


def test_bad_camera_input_raises_source_error(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="unsupported distortion model 'kannala'"):
        CameraModel(640, 480, K, [0.1], "kannala")
    with pytest.raises(SourceError, match=r"fx = 0, fy = 0 \(both must be > 0\)"):
        CameraModel(640, 480, [0.0] * 9, [], "none")
    f = tmp_path / "cam.yaml"
    f.write_text("image_width: 640\n")
    with pytest.raises(SourceError, match=r"cam\.yaml: not a camera_info YAML"):
        read_camera_file(f)
    with pytest.raises(SourceError, match="missing.yaml: cannot read camera file"):
        read_camera_file(tmp_path / "missing.yaml")


GOOD_CAMERA = """image_width: 640
image_height: 480
camera_matrix:
  rows: 3
  cols: 3
  data: [500.0, 0.0, 320.0, 0.0, 505.0, 240.0, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.1, -0.2, 0.001, 0.002, 0.05]
"""
BAD_CAMERAS = {  # edit of GOOD_CAMERA → what the one error line must say after the file name
    "missing K": (
        lambda t: t.replace("camera_matrix:", "camera_matrixx:"),
        "not a camera_info YAML: no camera_matrix; a camera_info YAML needs",
    ),
    "K too short": (
        lambda t: t.replace(", 0.0, 0.0, 1.0]", "]"),
        "camera_matrix.data has 6 numbers, needs 9",
    ),
    "K not numeric": (
        lambda t: t.replace("505.0", "abc"),
        "camera_matrix.data[4] is 'abc', not a number",
    ),
    "D not numeric": (
        lambda t: t.replace("-0.2", "x"),
        "distortion_coefficients.data[1] is 'x', not a number",
    ),
    "width": (lambda t: t.replace("640", "wide"), "image_width is 'wide', not a positive integer"),
    "fx zero": (
        lambda t: t.replace("500.0", "0.0"),
        "camera matrix K is not a calibration: fx = 0, fy = 505 (both must be > 0)",
    ),
    "K infinite": (lambda t: t.replace("500.0", ".inf"), "camera matrix K has non-finite values"),
    "not YAML": (
        lambda t: t.replace("data: [500.0,", "data: [500.0,: ,"),
        "not valid YAML (camera file): line 6, column 16: expected the node content",
    ),
    "not a mapping": (lambda t: "- 1\n- 2\n", "not a camera_info YAML (it holds list"),
    "empty": (lambda t: "", "empty file; a camera_info YAML needs"),
    "model": (lambda t: t.replace("plumb_bob", "kannala"), "unsupported distortion model"),
}


def image_folder(folder: Path, camera_text: str) -> Path:
    folder.mkdir()
    cv2.imwrite(str(folder / "f0.png"), np.full((480, 640), 128, np.uint8))
    (folder / "camera.yaml").write_text(camera_text)
    return folder


def test_good_camera_yaml_loads(tmp_path: Path) -> None:  # the file the cases below break
    cam = read_camera_file(image_folder(tmp_path / "imgs", GOOD_CAMERA) / "camera.yaml")
    assert (cam.width, cam.height, cam.K[1, 1], cam.D[1]) == (640, 480, 505.0, -0.2)


@pytest.mark.parametrize("case", sorted(BAD_CAMERAS))
def test_bad_camera_yaml_is_one_line(tmp_path: Path, capsys, case: str) -> None:
    from tagtrail.cli import main

    edit, message = BAD_CAMERAS[case]
    folder = image_folder(tmp_path / "imgs", edit(GOOD_CAMERA))
    with pytest.raises(SourceError) as info:  # one line at the source, not only once folded
        read_camera_file(folder / "camera.yaml")
    assert "\n" not in str(info.value)
    assert (
        main(
            [
                "init",
                "--reference",
                str(folder),
                "--tag-size",
                "0.16",
                "-o",
                str(tmp_path / "p.yaml"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"error: {folder / 'camera.yaml'}: ") and message in err[0], err[0]
    assert not (tmp_path / "p.yaml").exists()
