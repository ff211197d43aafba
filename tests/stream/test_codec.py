"""The hand-packed CDR encoders/decoders agree with rosbags byte for byte."""

from __future__ import annotations

import numpy as np
import pytest

from tagtrail.io.msgs import typestore
from tagtrail.stream import codec
from tagtrail.stream.markers import TEXT_LEN, PoseMarkers, path_markers

FRAMES = ["", "m", "map", "odom", "world_frame", "camera_color_optical_frame"]
VALS = (1.25, -2.5, 3e-3, 0.1, -0.2, 0.3, 0.927)


@pytest.mark.parametrize("frame", FRAMES)
def test_pose_stamped_encoder_matches_rosbags(frame: str) -> None:
    ref = codec.serialize(codec.pose_stamped(1_700_000_000, 123, frame, VALS[:3], VALS[3:]))
    assert codec.PoseStampedEncoder(frame)(1_700_000_000, 123, *VALS) == ref
    assert codec.decode_pose(ref) == codec.PoseIn(1_700_000_000, 123, frame, *VALS)


def test_map_pose_is_76_bytes_with_le_header() -> None:
    b = codec.PoseStampedEncoder("map")(1, 2, *VALS)
    assert len(b) == 76 and b[:4] == codec.CDR_LE  # NOTES: zenoh-bridge-ros2dds payload


@pytest.mark.parametrize("frame", FRAMES)
def test_decode_covariance_and_odometry(frame: str) -> None:
    T = codec.types()
    pwc = T["geometry_msgs/msg/PoseWithCovariance"](codec.pose(VALS[:3], VALS[3:]), np.arange(36.0))
    cov = codec.serialize(
        T["geometry_msgs/msg/PoseWithCovarianceStamped"](codec.header(7, 8, frame), pwc)
    )
    twist = T["geometry_msgs/msg/TwistWithCovariance"](
        T["geometry_msgs/msg/Twist"](
            T["geometry_msgs/msg/Vector3"](1, 2, 3), T["geometry_msgs/msg/Vector3"](4, 5, 6)
        ),
        np.ones(36),
    )
    odo = codec.serialize(
        T["nav_msgs/msg/Odometry"](codec.header(7, 8, frame), "base_link" + frame, pwc, twist)
    )
    want = codec.PoseIn(7, 8, frame, *VALS)
    assert codec.decode_pose(cov, "pose_with_covariance") == want
    assert codec.decode_pose(odo, "odometry") == want
    ps = codec.serialize(codec.pose_stamped(7, 8, frame, VALS[:3], VALS[3:]))
    for data, kind in [
        (cov, "pose_stamped"),
        (odo, "pose_stamped"),
        (ps, "pose_with_covariance"),
        (ps, "odometry"),
        (odo, "pose_with_covariance"),
    ]:
        with pytest.raises(codec.CodecError):
            codec.decode_pose(data, kind)


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\x00\x01\x00\x00",
        b"\x02\x00\x00\x00" + bytes(72),
        bytes(76),
        b"\x00\x01\x00\x00" + b"\xff" * 72,
    ],
)
def test_decode_rejects_garbage(data: bytes) -> None:
    with pytest.raises(codec.CodecError):
        codec.decode_pose(data)


def test_float64() -> None:
    ts = typestore()
    for v in (0.0, -1.5, 1e300, float("nan")):
        assert codec.encode_float64(v) == bytes(
            ts.serialize_cdr(ts.types["std_msgs/msg/Float64"](v), "std_msgs/msg/Float64")
        )


def test_marker_template_equals_full_serialization() -> None:
    pm = PoseMarkers("map", (0.0, -1.0, 0.0))
    cur, near = (1.0, -0.13, 2.0), (1.2, -0.13, 2.1)
    fast = pm(5, 6, cur, near, 0.2236, -12.5)
    slow = pm._build(5, 6, (*near, *cur, *near, 1.0, -0.38, 2.0), "D   0.224 m  phi  -12.50 deg")
    assert fast == slow
    ma = typestore().deserialize_cdr(fast, codec.MARKER_ARRAY)
    assert [m.ns for m in ma.markers] == ["nearest", "error", "text"]
    assert all((m.header.stamp.sec, m.header.stamp.nanosec) == (5, 6) for m in ma.markers)
    # a text that does not fit the template falls back to a full serialization
    far = typestore().deserialize_cdr(pm(5, 6, cur, near, 12345.0, 1.0), codec.MARKER_ARRAY)
    assert far.markers[2].text.startswith("D 12345.000") and TEXT_LEN < len(far.markers[2].text)


def test_path_and_path_marker() -> None:
    P = np.random.default_rng(0).normal(size=(50, 3))
    q = np.tile([0.0, 0.0, 0.0, 1.0], (50, 1))
    path = typestore().deserialize_cdr(codec.encode_path(P, q, 0, 0, "map"), codec.PATH)
    assert len(path.poses) == 50 and path.header.frame_id == "map"
    assert path.poses[7].pose.position.y == P[7, 1]
    ma = typestore().deserialize_cdr(path_markers(P, "map"), codec.MARKER_ARRAY)
    assert len(ma.markers[0].points) == 50 and ma.markers[0].points[3].z == P[3, 2]
