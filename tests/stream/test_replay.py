"""Replay sources (trajectory files in both layouts, bag pose topics, raw bag topics), pacing,
and session configs. No network here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tagtrail.errors import SourceError, SpecError
from tagtrail.io.layouts import read_trajectory, write_trajectory_csv
from tagtrail.sim.simulate import simulate
from tagtrail.stream import codec
from tagtrail.stream.replay import bag_messages, load_poses, pose_messages, schedule_s
from tagtrail.stream.session import endpoint, make_config
from tests.stream.cases import query_frame


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate("circle", tmp_path_factory.mktemp("replay_bag"), frames=12, detections=True)[
        "circle"
    ]


def test_trajectory_files_both_layouts(tmp_path: Path) -> None:
    q = query_frame(20, out_of_order=False)
    write_trajectory_csv(tmp_path / "a" / "trajectory.csv", q)
    write_trajectory_csv(tmp_path / "b" / "trajetoria_camera.csv", q)
    for src in (tmp_path / "a", tmp_path / "b", tmp_path / "b" / "trajetoria_camera.csv"):
        poses = load_poses(src)
        assert np.array_equal(poses.t_ns, q["t_ns"].to_numpy()) and poses.frames[0] == "map"
        msgs = pose_messages(poses, "tag_only_pose")
        p = codec.decode_pose(msgs.payloads[3])
        assert p.sec * 10**9 + p.nanosec == q["t_ns"].iloc[3] and p.qw == q["qw"].iloc[3]
    with pytest.raises(SourceError):
        load_poses(tmp_path / "missing.csv")


def test_bag_pose_topic_and_raw_topics(bag: Path) -> None:
    gt = read_trajectory(bag / "ground_truth" / "trajectory.csv")
    poses = load_poses(bag)  # the only PoseStamped topic: /ground_truth/camera_pose
    assert len(poses) == len(gt)
    np.testing.assert_allclose(poses.values[:, :3], gt[["x_m", "y_m", "z_m"]], atol=1e-12)
    raw = bag_messages(bag, ["/detections", "/camera_info"])
    assert set(raw.keys) == {"detections", "camera_info"} and len(raw.keys) == 2 * len(gt)
    assert all(p[:4] == codec.CDR_LE for p in raw.payloads)
    with pytest.raises(SourceError, match="/nope"):
        bag_messages(bag, ["/nope"])
    # a profile's optional topics (the LIMO's /odom) are replayed when the bag has them
    some = bag_messages(bag, ["/detections", "/odom", "/wheel/odom"], ["/odom", "/wheel/odom"])
    assert set(some.keys) == {"detections", "odom"}
    with pytest.raises(SourceError, match="not a pose topic"):
        load_poses(bag, topic="/detections")


def test_schedule() -> None:
    t = np.array([0, 100, 50, 300], dtype=np.int64) * 1_000_000  # one stamp goes back
    np.testing.assert_allclose(schedule_s(t, 1.0), [0, 0.1, 0.1, 0.3])
    np.testing.assert_allclose(schedule_s(t, 2.0), [0, 0.05, 0.05, 0.15])
    assert not schedule_s(t, 0.0).any()


def test_session_config_is_explicit() -> None:
    cfg = make_config("peer", listen=["127.0.0.1:7000"], connect=["tcp/127.0.0.1:7001"])
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7000"]
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7001"]
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("scouting/gossip/enabled")) is False
    assert endpoint("udp/127.0.0.1:9") == "udp/127.0.0.1:9"
    assert json.loads(cfg.get_json("transport/unicast/lowlatency")) is False  # zenoh's own
    fast = make_config("peer", connect=["tcp/127.0.0.1:7001"], low_latency=True)
    assert json.loads(fast.get_json("transport/unicast/lowlatency")) is True
    assert json.loads(fast.get_json("transport/unicast/qos/enabled")) is False  # zenoh needs it
    with pytest.raises(SpecError):
        make_config("router")
    with pytest.raises(SpecError):
        make_config("client")
