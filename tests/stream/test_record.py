"""``tagtrail stream record``: real zenoh sessions on 127.0.0.1, real bags from the simulator.

A zenoh router in the test process stands in for the robot's zenoh-bridge-ros2dds (a router by
default); ``tagtrail stream replay`` (another process) publishes a simulated recording's topics
through it as the bridge would, and the recorders (other processes) write them into bags that
are then read back with rosbags and the ``mcap`` reader.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from tagtrail.errors import SourceError, SpecError
from tagtrail.io import msgs
from tagtrail.io.bags import open_bag
from tagtrail.schemas.profiles import PROFILES
from tagtrail.sim.simulate import simulate
from tagtrail.stream.bagwriter import TAIL, recover
from tagtrail.stream.record import normalize_type, parse_size, parse_topic, resolve_topics
from tests.stream.helpers import REPO, Proc, client_args

IMAGE, INFO = "/camera/color/image_raw", "/camera/color/camera_info"
DET, DET_INFO = "/detections", "/camera_info"


def source_messages(bag: Path, topics: list[str]) -> dict[str, list[bytes]]:
    reader = open_bag(bag)
    try:
        out: dict[str, list[bytes]] = {t: [] for t in topics}
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, _t, raw in reader.messages(connections=conns):
            out[conn.topic].append(bytes(raw))
        return out
    finally:
        reader.close()


def stamps(payloads: list[bytes], msgtype: str) -> list[tuple[int, int]]:
    store = msgs.typestore()
    return [
        (m.header.stamp.sec, m.header.stamp.nanosec)
        for m in (store.deserialize_cdr(p, msgtype) for p in payloads)
    ]


def read_rosbags(bag: Path) -> tuple[dict[str, list[bytes]], dict[str, list[int]], dict[str, str]]:
    """Payloads, log times and types per topic, through rosbags (tagtrail's ``open_bag``)."""
    reader = open_bag(bag)
    try:
        data: dict[str, list[bytes]] = {}
        times: dict[str, list[int]] = {}
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            data.setdefault(conn.topic, []).append(bytes(raw))
            times.setdefault(conn.topic, []).append(int(t))
        return data, times, types
    finally:
        reader.close()


def record(out: Path, port: int, *args: str) -> Proc:
    return Proc(["record", str(out), *client_args(port), "--stats-period", "1", *args])


def replay(bag: Path, port: int, topics: list[str], rate: str = "1") -> list[str]:
    return ["replay", str(bag), "--topics", *topics, *client_args(port), "--rate", rate]


@pytest.fixture(scope="module")
def images(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """10 s of 640x480 rgb8 images + camera_info at 30 Hz (the LIMO camera), 300 frames."""
    return simulate("circle", tmp_path_factory.mktemp("rec_src"), frames=300, fps=30.0)["circle"]


@pytest.mark.slow
def test_30hz_images_recorded_into_mcap_and_sqlite3(
    images: Path, bridge: Any, tmp_path: Path
) -> None:
    """The issue's done-when: 10 s of 30 Hz 640x480 images + camera_info over zenoh on
    loopback, recorded at once into MCAP and sqlite3: every message, in order, byte for byte,
    stamps kept, log time = receive time; read by rosbags and by the mcap reader; then the
    pipeline runs on both bags."""
    _, port = bridge
    src = source_messages(images, [IMAGE, INFO])
    assert len(src[IMAGE]) == len(src[INFO]) == 300
    out = {"mcap": tmp_path / "rec_mcap", "sqlite3": tmp_path / "rec_db3"}
    t_start = time.time_ns()
    recs = {k: record(o, port, "--storage", k, "--profile", "limo-images") for k, o in out.items()}
    try:
        for r in recs.values():
            r.wait_for("record: recording")
        rep = Proc(replay(images, port, [IMAGE, INFO]))
        assert rep.p.wait(60) == 0, rep.output
        assert "published 600 messages" in rep.output
        time.sleep(1.0)  # the last samples cross the router
        assert recs["mcap"].stop(sig=signal.SIGINT) == 0, recs["mcap"].output
        assert recs["sqlite3"].stop(sig=signal.SIGTERM) == 0, recs["sqlite3"].output
    finally:
        for r in recs.values():
            r.kill()
    t_end = time.time_ns()
    for kind, bag in out.items():
        outp = recs[kind].output
        assert "600 messages" in outp and "dropped 0" in outp, outp
        assert any(f"{IMAGE} " in ln and " Hz " in ln for ln in recs[kind].lines), outp
        data, times, types = read_rosbags(bag)
        assert types == {IMAGE: msgs.IMAGE, INFO: msgs.CAMERA_INFO}
        for topic in (IMAGE, INFO):
            assert data[topic] == src[topic], f"{kind} {topic}: not every message, in order"
            assert times[topic] == sorted(times[topic])
            assert t_start <= times[topic][0] and times[topic][-1] <= t_end  # receive time
        assert stamps(data[IMAGE], msgs.IMAGE) == stamps(src[IMAGE], msgs.IMAGE)
        meta = (bag / "metadata.yaml").read_text()
        assert meta.count("message_count: 300") == 2 and "message_count: 600" in meta
    # the mcap library: channels, full definitions, the same messages in order
    from mcap.reader import make_reader

    with open(out["mcap"] / "rec_mcap.mcap", "rb") as f:
        reader = make_reader(f)
        got: dict[str, list[bytes]] = {}
        for schema, channel, message in reader.iter_messages():
            got.setdefault(channel.topic, []).append(bytes(message.data))
            assert schema is not None and schema.encoding == "ros2msg"
            if channel.topic == IMAGE:
                assert schema.name == msgs.IMAGE and b"MSG: std_msgs/Header" in schema.data
        summary = reader.get_summary()
    assert got == {IMAGE: src[IMAGE], INFO: src[INFO]}
    assert summary is not None and sum(summary.statistics.channel_message_counts.values()) == 600
    with sqlite3.connect(out["sqlite3"] / "rec_db3.db3") as con:  # definitions in sqlite3 too
        defs = dict(
            con.execute(
                "SELECT topic_type, encoded_message_definition FROM message_definitions"
            ).fetchall()
        )
    assert "uint8[] data" in defs[msgs.IMAGE] and "float64[9] k" in defs[msgs.CAMERA_INFO]
    # the pipeline on both recordings
    project = tmp_path / "project"
    project.mkdir()
    init = tagtrail(
        project,
        "init",
        "--profile",
        "limo-images",
        "--tag-size",
        "0.16",
        "--reference",
        str(out["mcap"]),
        "--query",
        str(out["sqlite3"]),
    )
    assert init.returncode == 0, init.stderr
    run = tagtrail(project, "run")
    assert run.returncode == 0, run.stderr[-2000:]
    traj = (project / "outputs" / "reference" / "trajectory.csv").read_text().splitlines()
    assert len(traj) > 250
    summary_q = json.loads((project / "outputs" / "query" / "summary.json").read_text())
    assert summary_q["distance_m"]["mean"] < 0.01  # the same images: the same path


def tagtrail(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tagtrail.cli", *args],
        cwd=cwd,
        text=True,
        capture_output=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


@pytest.mark.slow  # a crash test (kill -9 mid-recording, ~4 s): make test-all
def test_kill_9_leaves_a_readable_bag(detections: Path, bridge: Any, tmp_path: Path) -> None:
    """kill -9 mid-recording: the bag reads as it is (rosbags, mcap), up to the last flush, a
    prefix of what was sent; --recover then counts every complete chunk into metadata.yaml."""
    _, port = bridge
    src = source_messages(detections, [DET, DET_INFO])
    for kind in ("mcap", "sqlite3"):
        bag = tmp_path / f"killed_{kind}"
        rec = record(bag, port, "--profile", "limo", "--storage", kind, "--flush-period", "0.2")
        try:
            rec.wait_for("record: recording")
            rep = Proc(replay(detections, port, [DET, DET_INFO], rate="0.5"))
            rec.wait_for(f"{DET} ", 20)  # a live line with messages: some flushed
            deadline = time.monotonic() + 20
            while not any(
                f"{DET}" in ln and f"{DET} 0.0 Hz 0 " not in ln and " Hz " in ln
                for ln in rec.lines[-1:]
            ):
                assert time.monotonic() < deadline, rec.output
                time.sleep(0.05)
            time.sleep(0.5)
            rec.p.send_signal(signal.SIGKILL)
            rec.p.wait(5)
        finally:
            rec.kill()
            rep.kill()
        data, _, _ = read_rosbags(bag)  # as the kill left it
        n = len(data.get(DET, []))
        assert 0 < n < len(src[DET]), n
        assert data[DET] == src[DET][:n] and data[DET_INFO] == src[DET_INFO][: len(data[DET_INFO])]
        if kind == "mcap":
            from mcap.reader import make_reader

            with open(bag / f"{bag.name}.mcap", "rb") as f:
                assert f.read()[-len(TAIL) :] == TAIL  # the provisional end
                f.seek(0)
                assert sum(1 for _ in make_reader(f).iter_messages()) == n + len(data[DET_INFO])
        line = recover(bag)
        assert line.startswith(f"recovered {bag}") and f"{DET} " in line
        after, _, _ = read_rosbags(bag)
        assert len(after[DET]) >= n and after[DET] == src[DET][: len(after[DET])]


def test_wrong_type_and_silent_key_stop_in_one_line(
    detections: Path, bridge: Any, tmp_path: Path
) -> None:
    _, port = bridge
    wrong = tmp_path / "wrong"
    rec = record(
        wrong,
        port,
        "--topic",
        f"{DET}:apriltag_msgs/msg/AprilTagDetectionArray",
        "--topic",
        f"{DET_INFO}:sensor_msgs/msg/Image",
    )
    try:
        rec.wait_for("record: recording")
        rep = Proc(replay(detections, port, [DET, DET_INFO], rate="0"))
        assert rec.p.wait(30) == 2, rec.output
    finally:
        rec.kill()
        rep.kill()
    errors = [ln for ln in rec.lines if ln.startswith("error:")]
    assert (
        len(errors) == 1
        and "key camera_info: the messages are not sensor_msgs/msg/Image" in errors[0]
        and f"kept in {wrong}" in errors[0]
    ), rec.output
    data, _, _ = read_rosbags(wrong)  # what was recorded is kept, readable
    assert DET_INFO not in data or not data[DET_INFO]

    silent = tmp_path / "silent"
    rec = record(silent, port, "--topic", "/nobody:std_msgs/msg/Float64", "--wait", "1")
    assert rec.p.wait(20) == 2, rec.output
    errors = [ln for ln in rec.lines if ln.startswith("error:")]
    assert len(errors) == 1 and "no message on nobody after 1 s" in errors[0], rec.output
    assert read_rosbags(silent)[0] == {}  # an empty, readable bag
    again = record(silent, port, "--topic", "/nobody:std_msgs/msg/Float64")
    assert again.p.wait(20) == 2 and "exists already" in again.output


def test_topics_discovered_from_the_bridge_admin_space(bridge: Any, tmp_path: Path) -> None:
    """No --topic, no profile: the recorder takes the topics (and types) the bridge announces
    with its liveliness tokens, and records them."""
    session, port = bridge
    zid = str(session.zid())
    tokens = [
        session.liveliness().declare_token(
            f"@/{zid}/@ros2_lv/MP/{key.replace('/', '§')}/{typ.replace('/', '§')}/:1:1:1,10"
        )
        for key, typ in (("tag_only_pose", msgs.POSE_STAMPED), ("rosout", "rcl_interfaces/msg/Log"))
    ]
    from tagtrail.stream import codec

    enc = codec.PoseStampedEncoder("map")
    bag = tmp_path / "discovered"
    try:
        rec = record(bag, port)
        rec.wait_for("record: recording")
        assert "/tag_only_pose (geometry_msgs/msg/PoseStamped)" in rec.output
        assert "rosout" not in rec.lines[-1]
        pub = session.declare_publisher("tag_only_pose")
        deadline = time.monotonic() + 10
        while not pub.matching_status.matching:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            time.sleep(0.02)
        sent = [enc(100 + i, 0, float(i), 0.0, 0.0, 0.0, 0.0, 0.0, 1.0) for i in range(50)]
        for p in sent:
            pub.put(p)
        time.sleep(0.5)
        assert rec.stop() == 0, rec.output
        pub.undeclare()
    finally:
        for t in tokens:
            t.undeclare()
    data, _, types = read_rosbags(bag)
    assert types == {"/tag_only_pose": msgs.POSE_STAMPED} and data["/tag_only_pose"] == sent


@pytest.mark.slow  # a full disk (tmpfs) under the recorder (~5 s): make test-all
def test_full_disk_keeps_the_bag_up_to_its_last_flush(
    detections: Path, bridge: Any, tmp_path: Path
) -> None:
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if (
        subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=120k", "tmpfs", str(mnt)], capture_output=True
        ).returncode
        != 0
    ):
        if os.environ.get("CI") == "true":
            pytest.fail("CI runs as root and must be able to mount a tmpfs")
        pytest.skip("cannot mount a tmpfs here (not root)")
    _, port = bridge
    try:
        for kind in ("mcap", "sqlite3"):
            bag = mnt / f"full_{kind}"
            rec = record(
                bag,
                port,
                "--profile",
                "limo",
                "--storage",
                kind,
                "--flush-period",
                "0.1",
                "--duration",
                "40",
            )
            try:
                rec.wait_for("record: recording")
                rep = Proc(replay(detections, port, [DET, DET_INFO], rate="2"))
                assert rec.p.wait(60) == 2, rec.output
            finally:
                rec.kill()
                rep.kill()
            errors = [ln for ln in rec.lines if ln.startswith("error:")]
            assert len(errors) == 1 and "No space left on device" in errors[0], rec.output
            data, _, _ = read_rosbags(bag)
            n = len(data.get(DET, []))
            assert n > 0 and data[DET] == source_messages(detections, [DET])[DET][:n]
            for p in bag.iterdir():
                p.unlink()
            bag.rmdir()
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_topic_arguments() -> None:
    assert parse_topic("/camera_info:sensor_msgs/CameraInfo") == ("/camera_info", msgs.CAMERA_INFO)
    assert parse_topic("detections") == ("/detections", None)
    assert normalize_type("sensor_msgs::msg::dds_::Image_") == msgs.IMAGE
    with pytest.raises(SpecError, match="did you mean sensor_msgs/msg/Image"):
        normalize_type("sensor_msgs/msg/Imag")
    with pytest.raises(SpecError, match="not a ROS topic"):
        parse_topic("bad topic:std_msgs/msg/Float64")
    assert parse_size("500M") == 500_000_000 and parse_size("1.5GB") == 1_500_000_000
    with pytest.raises(SpecError):
        parse_size("lots")
    limo = PROFILES["limo"]
    assert [(t.topic, t.msgtype) for t in resolve_topics([], limo, {})] == list(limo.record)
    got = resolve_topics(["/camera_info"], limo, {"/x": msgs.IMAGE})
    assert [(t.topic, t.key) for t in got] == [("/camera_info", "camera_info")]
    with pytest.raises(SpecError, match="give its type"):
        resolve_topics(["/unknown"], None, {})
    with pytest.raises(SpecError, match="nothing to record"):
        resolve_topics([], None, {})
    with pytest.raises(SpecError, match="the bridge publishes it as"):
        resolve_topics([f"{DET_INFO}:{msgs.IMAGE}"], None, {DET_INFO: msgs.CAMERA_INFO})
    with pytest.raises(SourceError):
        recover(Path("/nonexistent/bag"))


def test_max_size_and_duration_stop_cleanly(detections: Path, bridge: Any, tmp_path: Path) -> None:
    _, port = bridge
    bag = tmp_path / "capped"
    rec = record(bag, port, "--profile", "limo", "--max-size", "20k", "--duration", "60")
    try:
        rec.wait_for("record: recording")
        rep = Proc(replay(detections, port, [DET, DET_INFO], rate="1"))
        assert rec.p.wait(60) == 0, rec.output
    finally:
        rec.kill()
        rep.kill()
    assert "record: --max-size reached" in rec.output, rec.output
    data, _, _ = read_rosbags(bag)
    size = sum(len(p) for msgs_ in data.values() for p in msgs_)
    assert (
        20_000 <= size < 40_000
        and data[DET] == source_messages(detections, [DET])[DET][: len(data[DET])]
    )
    timed = record(
        tmp_path / "timed",
        port,
        "--topic",
        "/nobody:std_msgs/msg/Float64",
        "--wait",
        "0",
        "--duration",
        "1",
    )
    assert timed.p.wait(20) == 0 and "record: --duration 1 s: 0 messages" in timed.output
