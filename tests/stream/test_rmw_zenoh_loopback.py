"""tagtrail's nodes on rmw_zenoh's wire, met by a ROS-2-like peer written here from the rules of
rmw_zenoh's design document (raw zenoh, none of tagtrail's wire code), on 127.0.0.1 only.

The peer announces itself with liveliness tokens, publishes CDR (made with rosbags) on rmw_zenoh
data keys with the 33-byte attachment, and subscribes the same way; tagtrail runs as real
``tagtrail stream …`` processes.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from tagtrail.io.bags import open_bag
from tagtrail.sim.simulate import simulate
from tests.stream.cases import synthetic_case
from tests.stream.helpers import REPO, Proc, free_port, listening, loopback

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
QOS = "::,10:,:,:,,"  # rclcpp's QoS(10) as rmw_zenoh's qos_to_keyexpr writes it
SENSOR_QOS = "2::,5:,:,:,,"  # SensorDataQoS: best effort, keep last 5


def type_hash(msgtype: str, distro: str) -> str:
    if distro == "humble":
        return "TypeHashNotSupported"
    return str(get_typestore(Stores.ROS2_JAZZY).hash_rihs01(msgtype))


def dds(msgtype: str) -> str:
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def data_key(topic: str, msgtype: str, distro: str, domain: int = 0) -> str:
    return f"{domain}/{topic.strip('/')}/{dds(msgtype)}/{type_hash(msgtype, distro)}"


@dataclass
class RosPeer:
    """A ROS 2 node as rmw_zenoh makes one, written from design.md: one zenoh session, an NN
    token, and per endpoint an MP/MS token; every put carries seq/time/GID."""

    session: zenoh.Session
    node: str
    distro: str = "humble"
    domain: int = 0
    entities: list[Any] = field(default_factory=list)
    received: dict[str, list[tuple[bytes, bytes | None]]] = field(default_factory=dict)
    seen: list[str] = field(default_factory=list)  # every token that appeared, in order
    _eid: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def zid(self) -> str:
        return str(self.session.info.zid())

    def token(
        self, kind: str, topic: str | None = None, msgtype: str | None = None, qos: str = QOS
    ) -> str:
        eid, self._eid = self._eid, self._eid + 1
        head = f"@ros2_lv/{self.domain}/{self.zid}/0/{eid}/{kind}/%/%/{self.node}"
        if topic is None or msgtype is None:
            return head
        return (
            f"{head}/{topic.replace('/', '%')}/{dds(msgtype)}/"
            f"{type_hash(msgtype, self.distro)}/{qos}"
        )

    def announce(self) -> None:
        """The node's token, and a watch on the domain's tokens (as rmw_zenoh's graph cache)."""
        self.entities.append(self.session.liveliness().declare_token(self.token("NN")))

        def on_token(s: zenoh.Sample) -> None:
            if s.kind == zenoh.SampleKind.PUT:
                with self._lock:
                    self.seen.append(str(s.key_expr))

        self.entities.append(
            self.session.liveliness().declare_subscriber(
                f"@ros2_lv/{self.domain}/**", on_token, history=True
            )
        )

    def publisher(self, topic: str, msgtype: str, qos: str = QOS) -> Publisher:
        tok = self.token("MP", topic, msgtype, qos)
        self.entities.append(self.session.liveliness().declare_token(tok))
        pub = self.session.declare_publisher(data_key(topic, msgtype, self.distro, self.domain))
        self.entities.append(pub)
        return Publisher(pub, bytes(range(16, 32)) if "image" in topic else bytes(range(16)))

    def subscribe(self, topic: str, msgtype: str) -> None:
        self.entities.append(
            self.session.liveliness().declare_token(self.token("MS", topic, msgtype))
        )
        self.received[topic] = []

        def on_sample(s: zenoh.Sample) -> None:
            att = s.attachment.to_bytes() if s.attachment is not None else None
            with self._lock:
                self.received[topic].append((s.payload.to_bytes(), att))

        self.entities.append(
            self.session.declare_subscriber(
                data_key(topic, msgtype, self.distro, self.domain), on_sample
            )
        )

    def tokens(self) -> list[str]:
        replies = self.session.liveliness().get(f"@ros2_lv/{self.domain}/**", timeout=2.0)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    def close(self) -> None:
        for e in reversed(self.entities):
            e.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]


@dataclass
class Publisher:
    pub: zenoh.Publisher
    gid: bytes
    seq: int = 0

    def put(self, payload: bytes, attach: bool = True) -> None:
        self.seq += 1
        att = struct.pack("<qqB", self.seq, time.time_ns(), 16) + self.gid if attach else None
        self.pub.put(payload, attachment=att)

    def wait_matched(self, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while not self.pub.matching_status.matching:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline, "no matching subscriber"
            time.sleep(0.02)


@pytest.fixture()
def peer() -> Iterator[tuple[RosPeer, int]]:
    port = free_port()
    p = RosPeer(listening(port, "peer"), "robot")
    try:
        yield p, port
    finally:
        p.close()


def wait_token(p: RosPeer, fragment: str, timeout: float = 20.0) -> list[str]:
    deadline = time.monotonic() + timeout
    while True:
        toks = p.tokens()
        if any(fragment in t for t in toks):
            return toks
        assert time.monotonic() < deadline, f"no token with {fragment!r} in {toks}"
        time.sleep(0.1)


def pose_cdr(row: Any) -> bytes:
    T = HUMBLE.types
    msg = T["geometry_msgs/msg/PoseStamped"](
        T["std_msgs/msg/Header"](
            T["builtin_interfaces/msg/Time"](int(row.t_ns // 10**9), int(row.t_ns % 10**9)), "map"
        ),
        T["geometry_msgs/msg/Pose"](
            T["geometry_msgs/msg/Point"](row.x_m, row.y_m, row.z_m),
            T["geometry_msgs/msg/Quaternion"](row.qx, row.qy, row.qz, row.qw),
        ),
    )
    return bytes(HUMBLE.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_relocalize_speaks_rmw_zenoh(
    peer: tuple[RosPeer, int], tmp_path: Path, distro: str
) -> None:
    """A ROS-like peer publishes poses on /tag_only_pose (rmw_zenoh keys, attachments, tokens;
    the last two without attachment); ``stream relocalize --wire rmw_zenoh`` answers D and phi
    on rmw_zenoh keys with well-formed attachments, sequence numbers 1, 2, … per publisher, and
    announces its node and endpoints with tokens that go away when it stops."""
    from tagtrail.io.layouts import read_trajectory

    p, port = peer
    p.distro = distro
    case = synthetic_case(tmp_path, n_ref=300, n_query=40)
    query = read_trajectory(case.query)
    n = len(query)
    p.announce()
    p.subscribe("/relocalization/distance_m", "std_msgs/msg/Float64")
    p.subscribe("/relocalization/heading_error_deg", "std_msgs/msg/Float64")
    pose_pub = p.publisher("/tag_only_pose", "geometry_msgs/msg/PoseStamped")
    node = Proc(
        [
            "relocalize",
            "--reference",
            case.reference,
            "--alignment",
            case.alignment,
            "--plane",
            case.plane,
            "--wire",
            "rmw_zenoh",
            "--ros-distro",
            distro,
            "--connect",
            loopback(port),
            "--stats-period",
            "0",
        ]
    )
    t0 = time.time_ns()
    try:
        node.wait_for("relocalize: ready")
        f64, pose = dds("std_msgs/msg/Float64"), dds("geometry_msgs/msg/PoseStamped")
        h64, hpose = (
            type_hash(t, distro) for t in ("std_msgs/msg/Float64", "geometry_msgs/msg/PoseStamped")
        )
        toks = wait_token(p, f"/MS/%/%/tagtrail_relocalize/%tag_only_pose/{pose}/{hpose}/{QOS}")
        pose_pub.wait_matched()
        for i, row in enumerate(query.itertuples()):
            pose_pub.put(pose_cdr(row), attach=i < n - 2)
        deadline = time.monotonic() + 20
        while min(len(v) for v in p.received.values()) < n:
            assert time.monotonic() < deadline, {k: len(v) for k, v in p.received.items()}
            time.sleep(0.02)
        assert node.stop() == 0, node.output
        gone = p.tokens()
    finally:
        node.kill()
    t1 = time.time_ns()
    # the node and its endpoints, as `ros2 node list` / `ros2 topic list` would read them
    ours = [t for t in toks if "/tagtrail_relocalize" in t]
    zids = {t.split("/")[2] for t in ours}
    assert len(zids) == 1 and p.zid not in zids, ours
    zid = zids.pop()
    assert f"@ros2_lv/0/{zid}/0/0/NN/%/%/tagtrail_relocalize" in ours
    for topic in ("distance_m", "heading_error_deg"):
        assert any(
            t.startswith(f"@ros2_lv/0/{zid}/0/")
            and t.endswith(f"/MP/%/%/tagtrail_relocalize/%relocalization%{topic}/{f64}/{h64}/{QOS}")
            for t in ours
        ), ours
    eids = [t.split("/")[4] for t in ours]
    assert len(eids) == len(set(eids))  # one entity id per endpoint
    assert not [t for t in gone if "/tagtrail_relocalize" in t]  # undeclared on the way out
    # D and phi: the offline report's values, in order
    got = {
        k: [HUMBLE.deserialize_cdr(d, "std_msgs/msg/Float64").data for d, _ in v]
        for k, v in p.received.items()
    }
    np.testing.assert_allclose(
        got["/relocalization/distance_m"], case.offline["distance_m"], atol=1e-9, rtol=0
    )
    np.testing.assert_allclose(
        got["/relocalization/heading_error_deg"],
        case.offline["heading_error_deg"],
        atol=1e-9,
        rtol=0,
    )
    gids = set()
    for topic, samples in p.received.items():
        atts = [a for _, a in samples]
        assert all(a is not None and len(a) == 33 for a in atts), topic
        seq, stamp, glen = zip(*(struct.unpack("<qqB", a[:17]) for a in atts if a), strict=True)
        assert list(seq) == list(range(1, n + 1)), topic  # +1 per publisher, from 1
        assert set(glen) == {16}
        assert all(t0 <= s <= t1 for s in stamp) and list(stamp) == sorted(stamp)
        g = {a[17:] for a in atts if a}
        assert len(g) == 1, topic  # one GID per publisher
        gids |= g
    assert len(gids) == 2  # the two publishers differ
    stats = node.stats()
    assert stats["processed"] == n and stats["dropped"] == {}
    assert stats["without_attachment"] == 2 and stats["bad_attachment"] == 0
    assert stats["sequence_gaps"] == 0 and stats["wire"] == "rmw_zenoh"


IMAGE, INFO = "/camera/color/image_raw", "/camera/color/camera_info"


@pytest.fixture(scope="module")
def images(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 s of 640x480 rgb8 images + camera_info at 30 Hz (the LIMO camera), 180 frames."""
    return simulate("circle", tmp_path_factory.mktemp("rmw_src"), frames=180, fps=30.0)["circle"]


def bag_messages(bag: Path) -> tuple[dict[str, list[bytes]], dict[str, str]]:
    reader = open_bag(bag)
    try:
        out: dict[str, list[bytes]] = {}
        for conn, _t, raw in reader.messages():
            out.setdefault(conn.topic, []).append(bytes(raw))
        return out, {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()


@pytest.mark.slow
def test_record_discovers_and_records_a_humble_camera(
    images: Path, peer: tuple[RosPeer, int], tmp_path: Path
) -> None:
    """A Humble camera driver on rmw_zenoh (tokens, keys, attachments; sensor-data QoS):
    ``stream record --wire rmw_zenoh`` finds both topics and their types from the tokens alone,
    records every message byte for byte, and ``tagtrail run`` maps the bag."""
    p, port = peer
    src, types = bag_messages(images)
    assert len(src[IMAGE]) == len(src[INFO]) == 180
    p.node = "camera"
    p.announce()
    pubs = {t: p.publisher(t, types[t], SENSOR_QOS) for t in (IMAGE, INFO)}
    # an unrelated subscriber and a node token: not recorded (only publishers are)
    p.subscribe("/cmd_vel", "geometry_msgs/msg/Twist")
    out = tmp_path / "rec"
    rec = Proc(
        [
            "record",
            str(out),
            "--wire",
            "rmw_zenoh",
            "--connect",
            loopback(port),
            "--stats-period",
            "1",
            "--wait",
            "30",
        ]
    )
    try:
        rec.wait_for("record: recording")
        for pub in pubs.values():
            pub.wait_matched()
        for img, info in zip(src[IMAGE], src[INFO], strict=True):
            pubs[IMAGE].put(img)
            pubs[INFO].put(info)
            time.sleep(0.005)
        deadline = time.monotonic() + 30
        while not any(
            "| dropped" in ln and f"{IMAGE} " in ln and " 180 |" in ln and f"{INFO} " in ln
            for ln in rec.lines[-3:]
        ):
            assert time.monotonic() < deadline and rec.p.poll() is None, rec.output
            time.sleep(0.2)
        assert rec.stop(sig=signal.SIGINT) == 0, rec.output
    finally:
        rec.kill()
    assert (
        f"recording {INFO} (sensor_msgs/msg/CameraInfo), {IMAGE} (sensor_msgs/msg/Image)"
        in rec.output
    ), rec.output
    assert "360 messages" in rec.output and "dropped 0" in rec.output, rec.output
    wire = json.loads(next(ln for ln in rec.lines if ln.startswith("record: {"))[8:])
    assert wire["without_attachment"] == 0 and wire["sequence_gaps"] == 0
    got, got_types = bag_messages(out)
    assert got_types == {IMAGE: "sensor_msgs/msg/Image", INFO: "sensor_msgs/msg/CameraInfo"}
    assert got[IMAGE] == src[IMAGE] and got[INFO] == src[INFO]  # nothing lost, in order
    project = tmp_path / "project"
    project.mkdir()
    init = _tagtrail(
        project, "init", "--profile", "limo-images", "--tag-size", "0.16", "--reference", str(out)
    )
    assert init.returncode == 0, init.stderr
    run = _tagtrail(project, "run")
    assert run.returncode == 0, run.stderr[-2000:]
    traj = (project / "outputs" / "reference" / "trajectory.csv").read_text().splitlines()
    assert len(traj) > 150
    tag_map = (project / "outputs" / "reference" / "tag_map.csv").read_text().splitlines()
    assert len(tag_map) >= 3


def _tagtrail(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tagtrail.cli", *args],
        cwd=cwd,
        text=True,
        capture_output=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


def test_replay_and_echo_speak_rmw_zenoh(peer: tuple[RosPeer, int], tmp_path: Path) -> None:
    """``stream replay --wire rmw_zenoh`` publishes like a ROS 2 node on rmw_zenoh (key,
    attachment 1..N, tokens), waiting for the peer's subscription; ``stream echo --wire
    rmw_zenoh`` prints the peer's Float64 samples (any type hash) and a JSON document on the
    bare key."""
    from tagtrail.io.layouts import read_trajectory

    p, port = peer
    case = synthetic_case(tmp_path, n_ref=50, n_query=25)
    n = len(read_trajectory(case.query))
    p.announce()
    p.subscribe("/tag_only_pose", "geometry_msgs/msg/PoseStamped")
    t0 = time.time_ns()
    rep = Proc(
        [
            "replay",
            case.query,
            "--rate",
            "0",
            "--wire",
            "rmw_zenoh",
            "--connect",
            loopback(port),
            "--wait",
            "20",
        ]
    )
    try:
        assert rep.p.wait(60) == 0, rep.output
    finally:
        rep.kill()
    toks = list(p.seen)
    assert any(
        t.endswith(
            "/MP/%/%/tagtrail_replay/%tag_only_pose/geometry_msgs::msg::dds_::"
            f"PoseStamped_/TypeHashNotSupported/{QOS}"
        )
        for t in toks
    ), toks
    assert any(t.endswith("/0/0/NN/%/%/tagtrail_replay") for t in toks), toks
    deadline = time.monotonic() + 10
    while len(p.received["/tag_only_pose"]) < n:
        assert time.monotonic() < deadline, len(p.received["/tag_only_pose"])
        time.sleep(0.02)
    got = p.received["/tag_only_pose"]
    atts = [a for _, a in got]
    assert all(a is not None and len(a) == 33 and a[16] == 16 for a in atts)
    seqs = [struct.unpack_from("<q", a)[0] for a in atts if a]
    assert seqs == list(range(1, n + 1))
    assert all(t0 <= struct.unpack_from("<q", a, 8)[0] <= time.time_ns() for a in atts if a)
    poses = [HUMBLE.deserialize_cdr(d, "geometry_msgs/msg/PoseStamped") for d, _ in got]
    query = read_trajectory(case.query)
    np.testing.assert_allclose([m.pose.position.x for m in poses], query["x_m"], atol=0)
    # echo: the peer's Float64 (a Jazzy hash: echo takes any) and a JSON document
    jazzy_key = data_key("/relocalization/distance_m", "std_msgs/msg/Float64", "jazzy")
    echo = Proc(
        [
            "echo",
            "relocalization/distance_m",
            "--wire",
            "rmw_zenoh",
            "--connect",
            loopback(port),
            "--count",
            "3",
            "--wait",
            "20",
        ]
    )
    pub = p.session.declare_publisher(jazzy_key)
    bare = p.session.declare_publisher("relocalization/distance_m")
    try:
        deadline = time.monotonic() + 20
        while not (
            pub.matching_status.matching  # type: ignore[attr-defined]
            and bare.matching_status.matching
        ):  # type: ignore[attr-defined]
            assert time.monotonic() < deadline, echo.output
            time.sleep(0.02)
        f64 = bytes(
            HUMBLE.serialize_cdr(HUMBLE.types["std_msgs/msg/Float64"](1.5), "std_msgs/msg/Float64")
        )
        pub.put(f64, attachment=struct.pack("<qqB", 1, time.time_ns(), 16) + bytes(16))
        pub.put(f64)
        bare.put(b'{"distance_m": 1.5}')
        assert echo.p.wait(20) == 0, echo.output
    finally:
        echo.kill()
        pub.undeclare()
        bare.undeclare()
    assert echo.lines.count("relocalization/distance_m: <12 bytes of CDR>") == 2, echo.output
    assert 'relocalization/distance_m: {"distance_m": 1.5}' in echo.lines, echo.output
