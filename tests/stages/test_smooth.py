"""Stage smooth: noise reduction on SO(3) x R^3, yaw crossing +-180 deg, gaps, outlier frames."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pydantic
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.geometry.se3 import R_from_quat_xyzw, quat_xyzw_from_R
from tagtrail.runner.stage import stage_spec
from tagtrail.stages import smooth
from tests.stages.mapping_scene import POSE, T0_NS


def path(t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera on a 2 m circle (floor x-z), yaw 140 -> 220 deg (through 180), pitch wobble."""
    yaw = np.deg2rad(140.0 + 80.0 * t_s / t_s[-1])
    p = np.stack([2 * np.cos(0.3 * t_s), 0.1 * np.sin(t_s), 2 * np.sin(0.3 * t_s)], axis=1)
    R = Rotation.from_euler("YX", np.c_[yaw, 0.1 * np.sin(0.7 * t_s)]).as_matrix()
    return R, p


def frame(t_s: np.ndarray, R: np.ndarray, p: np.ndarray) -> pd.DataFrame:
    df = pd.DataFrame({"t_ns": T0_NS + np.round(t_s * 1e9).astype(np.int64)})
    df[POSE] = np.concatenate([p, quat_xyzw_from_R(R)], axis=1)
    df["n_tags"] = np.int32(2)
    return df


def noisy(t_s: np.ndarray, seed: int, pos: float = 0.02, rot_deg: float = 1.0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    R, p = path(t_s)
    dR = Rotation.from_rotvec(rng.normal(scale=np.deg2rad(rot_deg), size=(len(t_s), 3)))
    return frame(t_s, R @ dR.as_matrix(), p + rng.normal(scale=pos, size=p.shape))


def errors(df: pd.DataFrame, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R, p = path(t_s)
    v = df[POSE].to_numpy()
    dt = np.linalg.norm(v[:, :3] - p, axis=1)
    dR = np.swapaxes(R, -1, -2) @ R_from_quat_xyzw(v[:, 3:])
    return dt, np.rad2deg(np.linalg.norm(Rotation.from_matrix(dR).as_rotvec(), axis=1))


def test_stage_contract() -> None:
    spec = stage_spec("smooth", smooth)
    assert str(spec.inputs["trajectory"]) == "trajectory.trajectory"
    with pytest.raises(pydantic.ValidationError):
        smooth.Params(method="kalman")


def test_none_is_identity() -> None:
    df = noisy(np.arange(50) * 0.1, 0)
    out = smooth.run(df, smooth.Params(method="none"))["trajectory"]
    pd.testing.assert_frame_equal(out, df)


@pytest.mark.parametrize("uniform", [True, False])
def test_reduces_noise_through_180_deg_yaw(uniform: bool) -> None:
    rng = np.random.default_rng(1)
    dt = np.full(200, 0.1) if uniform else rng.uniform(0.03, 0.17, 200)
    t_s = np.cumsum(dt) - dt[0]
    df = noisy(t_s, 2)
    out = smooth.run(df, smooth.Params())["trajectory"]
    assert list(out.columns) == list(df.columns) and (out["t_ns"] == df["t_ns"]).all()
    (p0, r0), (p1, r1) = errors(df, t_s), errors(out, t_s)
    rms = lambda x: float(np.sqrt(np.mean(x**2)))  # noqa: E731
    assert rms(p1) < 0.6 * rms(p0)
    assert rms(r1) < 0.6 * rms(r0)
    assert r1.max() < r0.max()  # no wrap-around artefact at +-180 deg


def test_gaps_split_segments() -> None:
    t_s = np.r_[np.arange(40) * 0.1, 10.0 + np.arange(40) * 0.1]
    df = noisy(t_s, 3)
    both = smooth.run(df, smooth.Params())["trajectory"]
    parts = pd.concat(
        [
            smooth.run(df.iloc[:40], smooth.Params())["trajectory"],
            smooth.run(df.iloc[40:].reset_index(drop=True), smooth.Params())["trajectory"],
        ],
        ignore_index=True,
    )
    assert np.abs(both[POSE[:3]].to_numpy() - parts[POSE[:3]].to_numpy()).max() < 1e-4


def test_outlier_frame_is_pulled_back() -> None:
    """An IPPE-like 40 deg flip in one frame: the robust data term lets the neighbours win."""
    t_s = np.arange(60) * 0.1
    df = noisy(t_s, 4, pos=0.005, rot_deg=0.3)
    q = df.loc[30, POSE[3:]].to_numpy(np.float64)
    flip = Rotation.from_quat(q) * Rotation.from_euler("x", 40, degrees=True)
    df.loc[30, POSE[3:]] = flip.as_quat()
    df.loc[30, "x_m"] += 0.3
    out = smooth.run(df, smooth.Params())["trajectory"]
    dt, dr = errors(out, t_s)
    assert dr[30] < 3.0 and dt[30] < 0.05


def test_untimed_frames_are_neither_smoothed_nor_held_by_the_prior() -> None:
    """An image folder without stamps.csv has only its files' order (extract.frames.timed
    False): smooth passes the trajectory through, and the joint trajectory has no prior."""
    from tagtrail.stages import smooth as smooth_stage

    t_ns = np.arange(5, dtype=np.int64) * 100_000_000
    traj = pd.DataFrame(
        {
            "t_ns": t_ns,
            "x_m": [0.0, 1.0, 0.0, 1.0, 0.0],
            "y_m": 0.0,
            "z_m": 0.0,
            "qx": 0.0,
            "qy": 0.0,
            "qz": 0.0,
            "qw": 1.0,
            "n_tags": 1,
        }
    )
    frames = pd.DataFrame({"t_ns": t_ns, "frame_idx": np.arange(5), "n_det": 1, "timed": False})
    out = smooth_stage.run(traj, smooth_stage.Params(method="lsq"), frames)["trajectory"]
    assert out["x_m"].tolist() == traj["x_m"].tolist()
    moved = smooth_stage.run(traj, smooth_stage.Params(method="lsq"), frames.assign(timed=True))[
        "trajectory"
    ]
    assert moved["x_m"].tolist() != traj["x_m"].tolist()


def test_the_change_it_makes_is_added_to_the_frames_shift_from_their_evidence() -> None:
    """A frame-by-frame trajectory is its own evidence (shift 0, its corner RMS known): after
    smoothing each row's shift is what the smoothing moved it, and its corner RMS is unknown."""
    t_s = np.arange(0.0, 20.0, 0.1)
    raw = noisy(t_s, 4)
    raw["reproj_px"] = raw["alone_reproj_px"] = 0.2
    raw["shift_m"] = raw["shift_deg"] = raw["shift_sigma"] = 0.0
    out = smooth.run(raw, smooth.Params())["trajectory"]
    moved = np.linalg.norm(out[POSE[:3]].to_numpy() - raw[POSE[:3]].to_numpy(), axis=1)
    turned = np.degrees(
        Rotation.from_matrix(
            R_from_quat_xyzw(out[POSE[3:]].to_numpy()).transpose(0, 2, 1)
            @ R_from_quat_xyzw(raw[POSE[3:]].to_numpy())
        ).magnitude()
    )
    assert moved.mean() > 0.005  # the 2 cm noise was smoothed
    np.testing.assert_allclose(out["shift_m"], moved, atol=1e-12)
    np.testing.assert_allclose(out["shift_deg"], turned, atol=1e-9)
    assert out["reproj_px"].isna().all() and out["shift_sigma"].isna().all()
    assert (out["alone_reproj_px"] == 0.2).all()
