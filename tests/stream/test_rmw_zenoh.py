"""rmw_zenoh's wire, byte for byte, from the rules of its design document (ros2/rmw_zenoh
``docs/design.md``) and its sources — not from tagtrail's code.

Every expected value below is written out by hand (or computed with rosbags / zenoh's own
serializer), then compared with what :mod:`tagtrail.stream.wire` produces:

- data key ``<domain_id>/<fully qualified name without leading />/<DDS type>/<type hash>``;
  type hash ``TypeHashNotSupported`` on Humble, ``RIHS01_<sha256>`` (REP-2016) on Jazzy+;
- attachment: int64 LE sequence number, int64 LE source time (ns), one byte GID length (16),
  the 16-byte GID — 33 bytes, what zenoh-ext's serializer makes of ``(i64, i64, [u8; 16])``;
- liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<ns>/<node>
  [/<topic>/<type>/<hash>/<qos>]``, each ``/`` inside a name as ``%``;
- QoS strings as ``qos_to_keyexpr`` writes them: ``rel:dur:hist,depth:dl:ls:lv`` with every
  value equal to rmw_zenoh's default (reliable, volatile, keep last, depth 42, infinite
  durations, automatic liveliness) left empty.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator

import pytest
import zenoh
import zenoh.ext as zext
from rosbags.typesys import Stores, get_typestore

from tagtrail.errors import SpecError
from tagtrail.stream import wire as W

ZID = "aac3178e146ba6f1fc6e6a4085e77f21"  # the session id of design.md's `listener` example
STRING_RIHS01 = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


@pytest.fixture(scope="module")
def session() -> Iterator[zenoh.Session]:
    """A zenoh session with a fixed id that connects nowhere (tokens need a session)."""
    cfg = zenoh.Config()
    cfg.insert_json5("id", json.dumps(ZID))
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/endpoints", "[]")
    s = zenoh.open(cfg)
    yield s
    s.close()  # type: ignore[no-untyped-call]


def test_data_keys_humble_and_jazzy(session: zenoh.Session) -> None:
    humble = W.make_wire("rmw_zenoh", session, "humble", 0)
    assert humble.key("/relocalization/distance_m", "std_msgs/msg/Float64") == (
        "0/relocalization/distance_m/std_msgs::msg::dds_::Float64_/TypeHashNotSupported"
    )
    assert humble.key("tag_only_pose", "geometry_msgs/msg/PoseStamped") == (
        "0/tag_only_pose/geometry_msgs::msg::dds_::PoseStamped_/TypeHashNotSupported"
    )
    # design.md's examples (demo_nodes_cpp on a Jazzy+ distro)
    jazzy = W.make_wire("rmw_zenoh", session, "jazzy", 0)
    assert jazzy.key("/chatter", "std_msgs/msg/String") == (
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_RIHS01}"
    )
    assert jazzy.key("/robot1/chatter", "std_msgs/msg/String") == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_RIHS01}"
    )
    assert (
        W.make_wire("rmw_zenoh", session, "rolling", 2).key("/chatter", "std_msgs/msg/String")
        == f"2/chatter/std_msgs::msg::dds_::String_/{STRING_RIHS01}"
    )
    # any Jazzy type: rosbags' REP-2016 hash of Jazzy's definition
    jazzy_store = get_typestore(Stores.ROS2_JAZZY)
    for t in (
        "std_msgs/msg/Float64",
        "sensor_msgs/msg/Image",
        "nav_msgs/msg/Path",
        "visualization_msgs/msg/MarkerArray",
    ):
        pkg, _, name = t.split("/")
        want = f"5/x/{pkg}::msg::dds_::{name}_/{jazzy_store.hash_rihs01(t)}"
        assert W.make_wire("rmw_zenoh", session, "jazzy", 5).key("/x", t) == want
        assert want.split("/")[-1].startswith("RIHS01_") and len(want.split("/")[-1]) == 71
    # the bridge: the topic without its leading '/', whatever the type
    bridge = W.make_wire("bridge", session)
    assert bridge.key("/relocalization/distance_m", "std_msgs/msg/Float64") == (
        "relocalization/distance_m"
    )
    with pytest.raises(SpecError, match="ros-distro"):
        W.make_wire("rmw_zenoh", session, "iron", 0)
    with pytest.raises(SpecError, match="--wire"):
        W.make_wire("dds", session)


def test_attachment_layout() -> None:
    gid = bytes(range(0xA0, 0xB0))
    want = bytes.fromhex(
        "0100000000000000"  # sequence number 1, int64 little endian
        "0807060504030201"  # source time 0x0102030405060708 ns, int64 little endian
        "10"  # GID length: 16
        "a0a1a2a3a4a5a6a7a8a9aaabacadaeaf"  # the GID
    )
    assert len(want) == 33
    assert W.attachment(1, 0x0102030405060708, gid) == want
    # what rmw_zenoh's zenoh-ext serializer makes of (int64, int64, std::array<uint8_t, 16>)
    ours = zext.z_serialize(
        (zext.Int64(1), zext.Int64(0x0102030405060708), [zext.UInt8(b) for b in gid])
    ).to_bytes()
    assert ours == want
    big = W.attachment(2**62, 1_764_000_000_123_456_789, gid)
    assert struct.unpack("<qqB", big[:17]) == (2**62, 1_764_000_000_123_456_789, 16)
    assert W.parse_attachment(want) == (1, 0x0102030405060708, gid)
    with pytest.raises(ValueError, match="32 bytes"):
        W.parse_attachment(want[:-1])
    with pytest.raises(ValueError, match="GID length 15"):
        W.parse_attachment(want[:16] + b"\x0f" + want[17:])


def test_gid_is_16_bytes_fixed_per_token_and_distinct() -> None:
    tail = "std_msgs::msg::dds_::Float64_/H/::,10:,:,:,,"
    a = W.gid_of(f"@ros2_lv/0/z/0/1/MP/%/%/n/%a/{tail}")
    b = W.gid_of(f"@ros2_lv/0/z/0/2/MP/%/%/n/%b/{tail}")
    assert len(a) == len(b) == 16 and a != b
    assert a == W.gid_of(f"@ros2_lv/0/z/0/1/MP/%/%/n/%a/{tail}")


@pytest.mark.parametrize(
    ("qos", "text"),
    [
        (W.QoS(), "::,10:,:,:,,"),  # rclcpp QoS(10): design.md's listener/server examples
        (W.QoS(depth=7), "::,7:,:,:,,"),  # design.md's talker
        (W.QoS(1, 2, 1, 42), "::,:,:,:,,"),  # rmw_zenoh's defaults throughout
        (W.QoS(reliability=2, depth=5), "2::,5:,:,:,,"),  # SensorDataQoS: best effort, depth 5
        (W.QoS(durability=1, depth=1), ":1:,1:,:,:,,"),  # transient local, depth 1 (a latched map)
        (W.QoS(history=2, depth=42), "::2,:,:,:,,"),  # keep all
    ],
)
def test_qos_strings(qos: W.QoS, text: str) -> None:
    assert W.qos_string(qos) == text


def test_liveliness_tokens(session: zenoh.Session) -> None:
    for distro, hash_f64 in (
        ("humble", "TypeHashNotSupported"),
        ("jazzy", get_typestore(Stores.ROS2_JAZZY).hash_rihs01("std_msgs/msg/Float64")),
    ):
        w = W.RmwZenohWire(session, distro, 0)
        w.node = "tagtrail_relocalize"
        assert w.zid == ZID
        assert w.token("NN") == f"@ros2_lv/0/{ZID}/0/0/NN/%/%/tagtrail_relocalize"
        assert w.token("MP", 3, "relocalization/distance_m", "std_msgs/msg/Float64") == (
            f"@ros2_lv/0/{ZID}/0/3/MP/%/%/tagtrail_relocalize/%relocalization%distance_m/"
            f"std_msgs::msg::dds_::Float64_/{hash_f64}/::,10:,:,:,,"
        )
    w = W.RmwZenohWire(session, "humble", 7)
    w.node = "tagtrail_record"
    assert w.token("MS", 12, "/camera/color/image_raw", "sensor_msgs/msg/Image") == (
        f"@ros2_lv/7/{ZID}/0/12/MS/%/%/tagtrail_record/%camera%color%image_raw/"
        "sensor_msgs::msg::dds_::Image_/TypeHashNotSupported/::,10:,:,:,,"
    )


def test_tokens_parsed_as_rmw_zenoh_reads_them() -> None:
    sub = (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_RIHS01}/::,10:,:,:,,"
    )  # design.md
    ep = W.parse_token(sub)
    assert ep is not None
    assert (ep.domain_id, ep.zid, ep.nid, ep.eid, ep.kind) == (2, ZID, "0", "10", "MS")
    assert (ep.enclave, ep.namespace, ep.node) == ("/", "/", "listener")
    assert (ep.topic, ep.dds_type, ep.type_hash, ep.qos) == (
        "/chatter",
        "std_msgs::msg::dds_::String_",
        STRING_RIHS01,
        "::,10:,:,:,,",
    )
    node = W.parse_token("@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener")
    assert node is not None and node.kind == "NN" and node.topic is None
    ns = W.parse_token(
        "@ros2_lv/0/z/0/4/MP/%/%robot1/talker/%robot1%chatter/"
        "std_msgs::msg::dds_::String_/TypeHashNotSupported/::,7:,:,:,,"
    )
    assert ns is not None and ns.namespace == "/robot1" and ns.topic == "/robot1/chatter"
    # the bridge's tokens, other admin spaces and truncated tokens are not rmw_zenoh entities
    for other in (
        "@/z/@ros2_lv/MP/chatter/std_msgs§msg§String/x",
        "@ros2_lv/0/z/0/0/NN/%/%",
        "@ros2_lv/x/z/0/0/NN/%/%/n",
    ):
        assert W.parse_token(other) is None


def test_type_names() -> None:
    assert W.dds_type("sensor_msgs/msg/CameraInfo") == "sensor_msgs::msg::dds_::CameraInfo_"
    assert W.ros_type("sensor_msgs::msg::dds_::CameraInfo_") == "sensor_msgs/msg/CameraInfo"
    assert W.ros_type(W.dds_type("apriltag_msgs/msg/AprilTagDetectionArray")) == (
        "apriltag_msgs/msg/AprilTagDetectionArray"
    )
    with pytest.raises(ValueError, match="DDS type"):
        W.ros_type("sensor_msgs/msg/Image")


def test_defaults_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ROS_DISTRO", raising=False)
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert (W.default_distro(), W.default_domain()) == ("humble", 0)
    monkeypatch.setenv("ROS_DISTRO", "jazzy")
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert (W.default_distro(), W.default_domain()) == ("jazzy", 42)


@pytest.mark.parametrize(
    "cmd",
    [
        ["relocalize", "--reference", "ref"],
        ["localize", "--map", "m.yaml"],
        ["replay", "t.csv"],
        ["record", "out"],
        ["echo", "relocalization/state"],
        ["follow", "--path-length", "1"],
    ],
)
def test_every_stream_command_takes_the_wire_flags(cmd: list[str]) -> None:
    from tagtrail.stream.cli import build_parser
    from tagtrail.stream.session import config_from_args

    p = build_parser()
    ns = p.parse_args(cmd)
    assert (ns.wire, ns.ros_distro, ns.domain_id) == ("bridge", None, None)
    ns = p.parse_args([*cmd, "--wire", "rmw_zenoh", "--ros-distro", "jazzy", "--domain-id", "3"])
    assert (ns.wire, ns.ros_distro, ns.domain_id) == ("rmw_zenoh", "jazzy", 3)
    # rmw_zenoh's topology when no endpoint is given: connect to the local router, gossip on
    cfg = config_from_args(ns, "listen")
    assert cfg.get_json("connect/endpoints") == '["tcp/localhost:7447"]'
    assert cfg.get_json("scouting/gossip/enabled") == "true"
    assert cfg.get_json("scouting/multicast/enabled") == "false"
    # explicit endpoints win (tests: 127.0.0.1 only)
    ns = p.parse_args([*cmd, "--wire", "rmw_zenoh", "--connect", "tcp/127.0.0.1:7999"])
    assert config_from_args(ns, "listen").get_json("connect/endpoints") == (
        '["tcp/127.0.0.1:7999"]'
    )
    for bad in (["--domain-id", "-1"], ["--wire", "dds"], ["--ros-distro", "iron"]):
        with pytest.raises(SystemExit) as exc:
            p.parse_args([*cmd, *bad])
        assert exc.value.code == 2
