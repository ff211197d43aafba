"""Stage pnp: exact recovery of synthetic poses (every distortion model), the SPEC tag frame
checked end to end on rendered official tags, real corners, pass-through observations."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.spatial.transform import Rotation

from tagtrail.errors import SourceError
from tagtrail.geometry import se3
from tagtrail.geometry.camera import CameraModel
from tagtrail.io.camera_files import read_camera_file
from tagtrail.stages import extract, pnp
from tests.extracting import extract_from

CORNERS = [f"c{i}{a}" for i in range(4) for a in "xy"]
POSE = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]
K = [600.0, 0.0, 320.0, 0.0, 602.0, 240.0, 0.0, 0.0, 1.0]
MODELS = {
    "none": [],
    "plumb_bob": [0.1, -0.2, 0.001, 0.002, 0.05],
    "rational_polynomial": [0.1, -0.2, 0.001, 0.002, 0.05, 0.01, -0.02, 0.01],
    "equidistant": [0.05, -0.01, 0.002, -0.001],
}
# SPEC tag frame: x right, y up, z out of the face; detector corners 0..3
SPEC_CORNERS = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]])


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    """cam_T_tag (n, 4, 4): tags in front of the camera, facing it (tag z towards the camera)."""
    rng = np.random.default_rng(seed)
    facing = Rotation.from_euler("x", 180, degrees=True)
    R = (facing * Rotation.from_rotvec(rng.normal(0, 0.4, (n, 3)))).as_matrix()
    z = rng.uniform(0.6, 3.0, n)
    t = np.c_[rng.uniform(-0.3, 0.3, (n, 2)) * z[:, None], z]
    return se3.make_T(R, t)


def detections_table(corners: np.ndarray, tag_ids: np.ndarray) -> pd.DataFrame:
    n = len(corners)
    df = pd.DataFrame(
        {
            "t_ns": np.arange(n, dtype=np.int64) * 10,
            "frame_idx": np.arange(n),
            "tag_id": tag_ids,
            "hamming": 0,
            "decision_margin": 50.0,
        }
    )
    df[CORNERS] = corners.reshape(n, 8)
    return df


def empty_obs() -> pd.DataFrame:
    return pd.DataFrame({c: np.zeros(0) for c in ["t_ns", "frame_idx", "tag_id", *POSE]})


def poses_of(df: pd.DataFrame, prefix: str = "") -> np.ndarray:
    v = df[[prefix + c for c in POSE]].to_numpy()
    return se3.T_from_xyz_quat(v[:, :3], v[:, 3:])


@pytest.mark.parametrize("model", list(MODELS))
def test_synthetic_poses_recovered_exactly(model: str) -> None:
    cam = CameraModel(640, 480, K, MODELS[model], model)
    T = random_poses(60)
    tag_ids = np.arange(60) % 3
    params = pnp.Params(tag_size=0.16, tag_sizes={1: 0.05, 2: 0.3})
    sizes = params.sizes(tag_ids)
    px = cam.project(se3.transform_points(T[:, None], SPEC_CORNERS * sizes[:, None, None]))
    out = pnp.run(detections_table(px, tag_ids), cam, empty_obs(), params)
    obs = out["observations"]
    assert list(obs.columns) == pnp.COLUMNS and len(obs) == 60
    assert obs["size_m"].tolist() == sizes.tolist()
    dt, dr = se3.pose_error(poses_of(obs), T)
    assert dt.max() < 1e-6 and np.degrees(dr).max() < 1e-5
    assert obs["reproj_px"].max() < 1e-5
    assert (obs["alt_reproj_px"] > obs["reproj_px"]).all()  # best first
    assert (obs["ambiguity"] < 1e-3).all()
    alt = poses_of(obs, "alt_")
    assert np.isfinite(alt).all() and (se3.pose_error(alt, T)[1] > 1e-3).all()  # the other one


def test_pass_through_and_empty_inputs() -> None:
    obs = pd.DataFrame(
        {
            "t_ns": [5, 6],
            "frame_idx": [0, 1],
            "tag_id": [4, 9],
            "x_m": [0.1, 0.2],
            "y_m": 0.0,
            "z_m": 1.0,
            "qx": 0.0,
            "qy": 0.0,
            "qz": 0.0,
            "qw": 1.0,
        }
    )
    empty_det = detections_table(np.zeros((0, 4, 2)), np.zeros(0, int))
    params = pnp.Params(tag_size=0.2, tag_sizes={9: 0.1})
    out = pnp.run(empty_det, None, obs, params)["observations"]
    assert list(out.columns) == pnp.COLUMNS
    assert out["size_m"].tolist() == [0.2, 0.1] and out["x_m"].tolist() == [0.1, 0.2]
    assert out[["reproj_px", "alt_reproj_px", "ambiguity", "alt_x_m"]].isna().all().all()
    none = pnp.run(empty_det, None, empty_obs(), pnp.Params())["observations"]
    assert list(none.columns) == pnp.COLUMNS and len(none) == 0
    assert none.dtypes["t_ns"] == np.int64 and none.dtypes["tag_id"] == np.int32
    det = detections_table(np.ones((1, 4, 2)), np.array([1]))
    with pytest.raises(SourceError, match="extract.camera is empty"):
        pnp.run(det, None, empty_obs(), pnp.Params())
    with pytest.raises(ValueError, match=r"tag_sizes.3\n.*greater than or equal to 0.001"):
        pnp.Params(tag_sizes={3: 0.0})


def test_real_corners_give_the_expected_distances(realdata: Path) -> None:
    folder = realdata / "upenn_ar_tag36h11_id12_seq"
    cam = read_camera_file(folder / "frames/camera.yaml")
    corners = np.load(folder / "corners.npy") - 0.5  # C library → OpenCV pixel convention
    det = detections_table(corners, np.full(len(corners), 12))
    obs = pnp.run(det, cam, empty_obs(), pnp.Params(tag_size=0.14))["observations"]
    assert obs["z_m"].between(0.47, 0.73).all()  # README: camera-to-tag 0.478–0.726 m
    assert obs["reproj_px"].median() < 0.5 and obs["ambiguity"].median() < 0.1
    steps = np.linalg.norm(np.diff(obs[["x_m", "y_m", "z_m"]].to_numpy(), axis=0), axis=1)
    assert steps.max() < 0.05  # smooth hand-held motion, no flips


# --- the SPEC tag frame, end to end: render official tags at known poses, extract, pnp --------


def official_tag(tag_id: int, cell_px: int) -> np.ndarray:
    """The official tag36h11 image (OpenCV's is rotated 180°) with a 1-cell white quiet zone."""
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    img = np.rot90(cv2.aruco.generateImageMarker(d, tag_id, 8 * cell_px, borderBits=1), 2)
    return cv2.copyMakeBorder(
        img, cell_px, cell_px, cell_px, cell_px, cv2.BORDER_CONSTANT, value=255
    )


def render(
    tex: np.ndarray,
    size_m: float,
    cam_T_tag: np.ndarray,
    Km: np.ndarray,
    wh: tuple[int, int],
    ss: int = 4,
) -> np.ndarray:
    """Image of a textured tag (10 cells wide, black square = ``size_m``), supersampled ``ss``×.

    Texel (u, v), pixel centres at integers, sits at tag-frame x = (u + ½)·L/N − L/2,
    y = L/2 − (v + ½)·L/N (y up), L = 10/8 · size_m.
    """
    n, L = tex.shape[0], size_m * 10 / 8
    A = np.array([[L / n, 0, L / n / 2 - L / 2], [0, -L / n, L / 2 - L / n / 2], [0, 0, 1]])
    S = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1]])
    Hp = S @ Km @ np.c_[cam_T_tag[:3, :2], cam_T_tag[:3, 3]]
    big = cv2.warpPerspective(
        tex, Hp @ A, (wh[0] * ss, wh[1] * ss), flags=cv2.INTER_LINEAR, borderValue=140
    )
    return cv2.resize(big, wh, interpolation=cv2.INTER_AREA)


def test_spec_tag_frame_end_to_end(tmp_path: Path) -> None:
    cam = CameraModel(640, 480, K, [], "none")
    size = 0.16
    poses = [
        se3.make_T(Rotation.from_euler("xyz", [180 + a, b, c], degrees=True).as_matrix(), t)
        for a, b, c, t in [
            (20, -25, 5, [0.05, -0.02, 0.9]),
            (-30, 10, 95, [-0.1, 0.08, 1.1]),
            (10, 35, -150, [0.12, 0.05, 0.8]),
            (-15, 0, 45, [0.0, 0.0, 1.2]),
        ]
    ]
    tex = official_tag(7, cell_px=24)
    for k, T in enumerate(poses):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), render(tex, size, T, cam.K, (640, 480)))
    (tmp_path / "camera.yaml").write_text(
        yaml.safe_dump(
            {
                "image_width": 640,
                "image_height": 480,
                "camera_matrix": {"data": K},
                "distortion_model": "plumb_bob",
                "distortion_coefficients": {"data": [0.0] * 5},
            }
        )
    )
    ex = extract_from(tmp_path, extract.Params(workers=1))
    det = ex["detections"]
    assert det["tag_id"].tolist() == [7] * 4
    truth_px = np.stack([cam.project(se3.transform_points(T, SPEC_CORNERS * size)) for T in poses])
    offset = det[CORNERS].to_numpy().reshape(-1, 4, 2) - truth_px
    # corner i of the detector is SPEC corner i, in the OpenCV pixel convention (mean ≈ 0)
    # measured: mean (-0.006, +0.007) px, max 0.16 px; without the -0.5 px it would be +0.5
    assert np.abs(offset).max() < 0.3 and np.abs(offset.reshape(-1, 2).mean(0)).max() < 0.05
    obs = pnp.run(det, ex["camera"], ex["observations"], pnp.Params(tag_size=size))
    dt, dr = se3.pose_error(poses_of(obs["observations"]), np.stack(poses))
    # measured: ≤ 0.07 mm, ≤ 0.08° (a fronto-parallel tag would be the ambiguous case, ~4°)
    assert dt.max() < 0.001 and np.degrees(dr).max() < 0.3


def test_degenerate_corners_give_no_pose_and_no_runtime_warning(caplog) -> None:
    """Corners a detection message may carry (a point, a line, NaN, inf, far outside the image)
    and an exactly fronto-parallel tag (alternative reprojection error 0): no numpy warning."""
    import warnings

    T = random_poses(1, seed=3)
    for model, D in MODELS.items():
        cam = CameraModel(640, 480, K, D, model)
        good = cam.project(se3.transform_points(T[:, None], SPEC_CORNERS * 0.16))[0]
        front = cam.project(SPEC_CORNERS * 0.16 + [0.0, 0.0, 1.0])  # both IPPE solutions fit
        bad = [
            np.full((4, 2), 100.0),  # a point
            np.array([[100.0, 100.0], [200.0, 100.0], [300.0, 100.0], [400.0, 100.0]]),  # line
            np.full((4, 2), np.nan),
            np.where([[True, False]] + [[False, False]] * 3, np.inf, good),
            good * 1e60,  # far outside the image
        ]
        corners = np.stack([good, front, *bad])
        det = detections_table(corners, np.arange(len(corners)))
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # any warning fails the test
            obs = pnp.run(det, cam, empty_obs(), pnp.Params())["observations"]
        kept = obs["tag_id"].tolist()  # a pixel line is no ray line once undistorted: no check
        assert kept[:2] == [0, 1] and not {2, 4, 5, 6} & set(kept), (model, kept)
        assert np.isfinite(obs[["reproj_px", "alt_reproj_px", "ambiguity"]].to_numpy()).all()
        assert obs["ambiguity"].between(0, 1).all()
        assert obs.loc[1, "alt_reproj_px"] < 1e-5, model
    assert "5 of 7 detections gave no pose (degenerate corners)" in caplog.text  # "none"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        amb = pnp.ambiguity(np.array([0.0, 0.3, 0.2, np.nan]), np.array([0.0, 0.0, 0.4, np.nan]))
    np.testing.assert_array_equal(amb, [1.0, 1.0, 0.5, 1.0])  # x/0 → 1 (ambiguous)
