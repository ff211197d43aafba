"""``tagtrail simulate`` records the LIMO's wheel odometry: ``/odom`` against the base's truth,
its publication latency, ``/tf_static`` against the scene's mount, the options, and frames that
stay the same with or without it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from tagtrail.cli import main
from tagtrail.geometry.rotations import wrap_angle
from tagtrail.geometry.se3 import T_from_xyz_quat, compose, inv
from tagtrail.io.layouts import POSE_COLS, read_trajectory
from tagtrail.sim import simulate
from tagtrail.sim.camera import FRAME_ID
from tagtrail.sim.odometry import base_T_cam
from tagtrail.sim.scene import Mount
from tests.sim.helpers import read_topic


def _odom(bag: Path) -> pd.DataFrame:
    """The bag's ``/odom``: log time, header stamp, frames, planar pose and twist."""
    rows = []
    for t, m in read_topic(bag, "/odom"):
        p, q = m.pose.pose.position, m.pose.pose.orientation
        rows.append(
            {
                "log_ns": t,
                "t_ns": m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                "frame": m.header.frame_id,
                "child": m.child_frame_id,
                "x": p.x,
                "y": p.y,
                "yaw": 2 * np.arctan2(q.z, q.w),
                "v": m.twist.twist.linear.x,
                "cov": np.asarray(m.pose.covariance),
            }
        )
    return pd.DataFrame(rows)


def _truth(bag: Path) -> tuple[pd.DataFrame, np.ndarray]:
    """``odometry_truth.csv`` and its world_T_base ``(N, 4, 4)``."""
    gt = pd.read_csv(bag / "ground_truth" / "odometry_truth.csv")
    T = T_from_xyz_quat(gt[POSE_COLS[:3]].to_numpy(), gt[POSE_COLS[3:]].to_numpy())
    return gt, T


@pytest.fixture(scope="module")
def corridor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The corridor as detections, 2 % wheel scale error on both wheels, 1 s of 20 % slip."""
    out = tmp_path_factory.mktemp("odom")
    argv = ["simulate", "corridor", "--out", str(out), "--detections", "--seed", "4"]
    assert main([*argv, "--odom-scale-error", "0.02", "--odom-slip", "5,1,0.2"]) == 0
    return out / "corridor"


def test_odom_distance_is_truth_times_scale_outside_the_slip(corridor: Path) -> None:
    odom, (gt, T) = _odom(corridor), _truth(corridor)
    assert len(odom) == len(gt) > 1900  # 50 Hz over the ~40 s drive
    np.testing.assert_array_equal(odom["t_ns"], gt["t_ns"])
    np.testing.assert_array_equal(odom["log_ns"], odom["t_ns"])  # recorded at publication
    assert set(odom["frame"]) == {"odom"} and set(odom["child"]) == {"base_link"}
    step_odom = np.hypot(np.diff(odom["x"]), np.diff(odom["y"]))
    step_true = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    t_s = (gt["meas_t_ns"].to_numpy()[:-1] - gt["meas_t_ns"].iloc[0]) / 1e9
    slip = (t_s >= 5.0) & (t_s < 6.0)
    moving = step_true > 1e-4
    ratio = step_odom[moving] / step_true[moving]
    np.testing.assert_allclose(ratio[~slip[moving]], 1.02, rtol=1e-6)
    np.testing.assert_allclose(ratio[slip[moving]], 1.02 * 1.2, rtol=1e-6)
    assert slip.sum() == 50
    # the odom frame starts at the base's true first pose; the error grows with distance only
    odom_T_base = compose(inv(T[0])[None], T)
    assert abs(odom["x"].iloc[0]) < 1e-12 and abs(odom_T_base[0, 0, 3]) < 1e-12
    travelled = step_true.sum()
    excess = step_odom.sum() - travelled
    assert excess == pytest.approx(0.02 * travelled + 0.2 * 1.02 * step_true[slip].sum(), rel=1e-6)


def test_odom_yaw_drifts_at_the_drawn_rate(corridor: Path) -> None:
    odom, (gt, T) = _odom(corridor), _truth(corridor)
    doc = yaml.safe_load((corridor / "ground_truth" / "scene.yaml").read_text())["odometry"]
    assert doc["scale_left"] == doc["scale_right"] == pytest.approx(1.02)
    odom_T_base = compose(inv(T[0])[None], T)  # world is the anchor's frame: z is not up
    yaw_true = np.unwrap(np.arctan2(odom_T_base[:, 1, 0], odom_T_base[:, 0, 0]))
    np.testing.assert_allclose(odom_T_base[:, 2, 2], 1.0, atol=1e-12)  # planar: z stays up
    err = wrap_angle((odom["yaw"] - yaw_true).to_numpy())
    dt = 0.02
    t_s = (gt["meas_t_ns"].to_numpy()[:-1] - gt["meas_t_ns"].iloc[0]) / 1e9
    drift = np.radians(doc["drift_dps"])
    assert abs(doc["drift_dps"]) <= 0.3 and abs(drift * t_s[-1]) > 1e-3
    # the documented model: both wheels 2 % (20 % more in the slip), yaw rate over-read by
    # 3 % per m/s² of lateral acceleration, plus the drift
    dh = np.diff(yaw_true)
    v = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / dt
    f = np.where((t_s >= 5) & (t_s < 6), 1.2, 1.0)
    want = np.cumsum(dh * (1.02 * f * (1 + doc["slip_per_mps2"] * np.abs(v * dh / dt)) - 1))
    want += drift * dt * np.arange(1, len(dh) + 1)
    np.testing.assert_allclose(err[1:], want, atol=1e-9)


def test_latency_within_2_to_8_ms(corridor: Path) -> None:
    gt, _ = _truth(corridor)
    lat_ms = (gt["t_ns"] - gt["meas_t_ns"]).to_numpy() / 1e6
    assert lat_ms.min() >= 2.0 and lat_ms.max() <= 8.0
    assert lat_ms.max() - lat_ms.min() > 5.0  # jitter drawn per message, not one constant
    assert np.all(np.diff(gt["meas_t_ns"]) == 20_000_000)


def test_tf_static_composes_to_the_mount(corridor: Path) -> None:
    ((_, tf),) = read_topic(corridor, "/tf_static")
    (t,) = tf.transforms
    assert (t.header.frame_id, t.child_frame_id) == ("base_link", FRAME_ID)
    (_, info), *_ = read_topic(corridor, "/camera_info")
    assert info.header.frame_id == t.child_frame_id
    tr, q = t.transform.translation, t.transform.rotation
    base_T_camera = T_from_xyz_quat([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w])
    m = Mount()
    np.testing.assert_allclose(base_T_camera[:3, 3], [m.forward_m, 0.0, m.height_m], atol=1e-12)
    # optical: z ahead (base x), x right (base -y), y down (base -z)
    np.testing.assert_allclose(base_T_camera[:3, 2], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(base_T_camera[:3, 0], [0, -1, 0], atol=1e-12)
    # truth of the base @ the mount = the camera's truth, where a tick meets a frame (every 0.1 s)
    gt, world_T_base = _truth(corridor)
    traj = read_trajectory(corridor / "ground_truth" / "trajectory.csv")
    frames = traj.set_index("t_ns")
    both = gt["meas_t_ns"].isin(frames.index).to_numpy()
    assert both.sum() > 300
    cam = frames.loc[gt["meas_t_ns"][both], POSE_COLS].to_numpy()
    world_T_cam = T_from_xyz_quat(cam[:, :3], cam[:, 3:])
    np.testing.assert_allclose(world_T_base[both] @ base_T_camera, world_T_cam, atol=1e-9)
    doc = yaml.safe_load((corridor / "ground_truth" / "scene.yaml").read_text())
    want = T_from_xyz_quat(doc["base_T_camera"][:3], doc["base_T_camera"][3:])
    np.testing.assert_allclose(want, base_T_camera, atol=1e-12)
    np.testing.assert_allclose(base_T_cam(m), base_T_camera, atol=1e-12)


def test_tf_static_offers_transient_local(corridor: Path) -> None:
    meta = yaml.safe_load((corridor / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    qos = topics["/tf_static"]["topic_metadata"]["offered_qos_profiles"]
    assert qos[0]["durability"] == "transient_local"
    assert topics["/tf_static"]["message_count"] == 1


def test_default_scale_drawn_and_seeded(tmp_path: Path) -> None:
    """No --odom-scale-error: each wheel 1–3 % off; same seed, same odometry."""
    a = simulate("circle", tmp_path / "a", frames=30, detections=True, seed=9)["circle"]
    b = simulate("circle", tmp_path / "b", frames=30, detections=True, seed=9)["circle"]
    doc = yaml.safe_load((a / "ground_truth" / "scene.yaml").read_text())["odometry"]
    for k in ("scale_left", "scale_right"):
        assert 0.01 - 1e-12 <= abs(doc[k] - 1) <= 0.03 + 1e-12
    oa, ob = _odom(a), _odom(b)
    pd.testing.assert_frame_equal(oa.drop(columns="cov"), ob.drop(columns="cov"))
    np.testing.assert_allclose(oa["cov"][0], np.diag([0.1, 0.1, 0.1, 1, 1, 1]).reshape(-1))


def test_frames_identical_with_and_without_odom(tmp_path: Path) -> None:
    """The odometry draws from its own generator: the frames do not change."""
    on = simulate("room", tmp_path / "on", frames=6, query_frames=2, seed=2)
    off = simulate("room", tmp_path / "off", frames=6, query_frames=2, seed=2, odom=False)
    for name in on:
        for topic in ("/camera/color/image_raw", "/ground_truth/camera_pose"):
            a, b = read_topic(on[name], topic), read_topic(off[name], topic)
            assert len(a) == len(b) > 0
            assert all(
                ta == tb
                and bytes(ma.data if hasattr(ma, "data") else b"")
                == bytes(mb.data if hasattr(mb, "data") else b"")
                for (ta, ma), (tb, mb) in zip(a, b, strict=True)
            )
        assert not read_topic(off[name], "/odom") and not read_topic(off[name], "/tf_static")
        assert not (off[name] / "ground_truth" / "odometry_truth.csv").exists()
    # a parked query: the base stands still, the odometry only drifts in yaw
    odom = _odom(on["query_1"])
    assert np.allclose(odom[["x", "y", "v"]].to_numpy(), 0.0)


def test_observations_have_no_odometry_and_bad_options_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = simulate("observations", tmp_path, frames=10)["observations"]
    assert not (out / "ground_truth" / "odometry_truth.csv").exists()
    base = ["simulate", "circle", "--out", str(tmp_path / "x"), "--frames", "5"]
    cases = [
        (["--odom-slip", "5,1"], "--odom-slip: cannot parse"),
        (["--odom-slip", "5,0,0.2"], "--odom-slip: start_s >= 0 and duration_s > 0"),
        (["--odom-scale-error", "0.7"], "--odom-scale-error: 0.7 is out of range"),
        (["--odom-scale-error", "nan"], "--odom-scale-error"),
    ]
    for extra, msg in cases:
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and msg in err[0], err
    obs = ["simulate", "observations", "--out", str(tmp_path / "o"), "--odom"]
    assert main(obs) == 2
    assert "observations scenario writes no bag" in capsys.readouterr().err


def test_twist_integrates_to_the_pose(corridor: Path) -> None:
    """Each message's twist is the step that led to its pose (mid-point rule over 20 ms)."""
    rows = []
    for _, m in read_topic(corridor, "/odom"):
        p, q = m.pose.pose.position, m.pose.pose.orientation
        tw = m.twist.twist
        rows.append((p.x, p.y, 2 * np.arctan2(q.z, q.w), tw.linear.x, tw.angular.z))
    x, y, yaw, v, w = np.array(rows).T
    dt = 0.02
    mid = yaw[:-1] + 0.5 * w[1:] * dt
    np.testing.assert_allclose(np.diff(x), v[1:] * np.cos(mid) * dt, atol=1e-12)
    np.testing.assert_allclose(np.diff(y), v[1:] * np.sin(mid) * dt, atol=1e-12)
    np.testing.assert_allclose(wrap_angle(np.diff(yaw)), w[1:] * dt, atol=1e-12)
