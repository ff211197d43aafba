"""Camera files users already have, recognised by content (issue 15): Kalibr / TagSLAM camchains,
OpenCV FileStorage YAML and JSON, PhotonVision's calibration JSON; one error line otherwise."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tagtrail.errors import SourceError
from tagtrail.io.camera_files import read_camera_file

KALIBR = """cam0:
  camera_model: pinhole
  intrinsics: [1506.9, 1506.28, 641.176, 524.495]
  distortion_model: radtan
  distortion_coeffs: [-0.233024, 0.217972, 0.000104351, -9.65731e-05, -0.0913426]
  resolution: [1280, 1024]
  rostopic: /ximea_cam/image_raw
"""
OPENCV = """%YAML:1.0
---
image_width: 640
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 500., 0., 320., 0., 505., 240., 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.1, 0.01, 0., 0., 0. ]
avg_reprojection_error: 0.3
"""


def test_tagslam_cameras_yaml(realdata: Path) -> None:
    cam = read_camera_file(realdata / "tagslam_test_16" / "cameras.yaml")
    assert (cam.width, cam.height, cam.distortion_model) == (1280, 1024, "plumb_bob")
    assert np.allclose(cam.K, [[1506.9, 0, 641.176], [0, 1506.28, 524.495], [0, 0, 1]])
    assert np.allclose(cam.D, [-0.233024, 0.217972, 0.000104351, -9.65731e-05, -0.0913426])


def test_kalibr_camchain_names_a_camera(tmp_path: Path) -> None:
    f = tmp_path / "camchain.yaml"
    f.write_text(
        KALIBR
        + KALIBR.replace("cam0", "cam1")
        .replace("radtan", "equidistant")
        .replace("-0.0913426]", "]")
        .replace("1506.9,", "700.0,")
    )
    with pytest.raises(SourceError, match=r"2 cameras \(cam0, cam1\): name one as FILE#NAME"):
        read_camera_file(f)
    cam = read_camera_file(f"{f}#cam1")
    assert cam.distortion_model == "equidistant" and cam.K[0, 0] == 700.0 and cam.D.size == 4
    with pytest.raises(SourceError, match=r"no camera 'cam7' \(it has cam0, cam1\)"):
        read_camera_file(f"{f}#cam7")
    f.write_text(KALIBR.replace("pinhole", "omni"))
    with pytest.raises(SourceError, match="camera_model 'omni' is not supported"):
        read_camera_file(f)


def test_opencv_filestorage_yaml_and_json(tmp_path: Path) -> None:
    f = tmp_path / "calib.yaml"
    f.write_text(OPENCV)
    cam = read_camera_file(f)
    assert (cam.width, cam.height, cam.distortion_model) == (640, 480, "plumb_bob")
    assert cam.K[1, 1] == 505.0 and np.allclose(cam.D, [-0.1, 0.01, 0, 0, 0])
    j = tmp_path / "calib.json"
    j.write_text(
        json.dumps(
            {
                "camera_matrix": [[500, 0, 320], [0, 505, 240], [0, 0, 1]],
                "distortion_coefficients": [[-0.1, 0.01, 0, 0, 0]],
                "image_size": [640, 480],
            }
        )
    )
    cj = read_camera_file(j)
    assert np.array_equal(cj.K, cam.K) and np.array_equal(cj.D, cam.D)
    f.write_text(OPENCV.replace("image_width: 640\nimage_height: 480\n", ""))
    with pytest.raises(SourceError, match="no image size"):
        read_camera_file(f)


def test_photonvision_calibration_json(realdata: Path) -> None:
    root = realdata / "photonvision_frc2024_field"
    cam = read_camera_file(root / "lifecam_1280.json")
    meta = read_camera_file(root / "meta.yaml")  # the same calibration, written out by hand
    assert (cam.width, cam.height) == (1280, 720) and np.allclose(cam.K, meta.K)
    assert np.allclose(cam.D, meta.D) and cam.distortion_model == meta.distortion_model


def test_unrecognised_file_is_one_error(tmp_path: Path) -> None:
    f = tmp_path / "x.yaml"
    f.write_text("foo: 1\n")
    with pytest.raises(SourceError, match="not a camera_info YAML"):
        read_camera_file(f)
