"""Issue 26, live side: a recording onto a disk that fills is always a readable bag whose counts
are the ones the recorder printed (item 4); one stamp far off (future, past, zero) is counted once
and does not poison the out-of-order counters of the live nodes (item 7).

Real processes on 127.0.0.1: ``tagtrail stream record`` / ``relocalize`` / ``localize`` /
``replay``, a zenoh router in the test standing in for zenoh-bridge-ros2dds; real bags in
``tmp_path``; the full disk is a real tmpfs (root only, as tests/test_faults.py).
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tagtrail.io import msgs
from tagtrail.io.bags import open_bag
from tagtrail.stream import codec
from tagtrail.stream.bagwriter import recover
from tagtrail.stream.session import wait_matching
from tests.stream.cases import synthetic_case
from tests.stream.helpers import REPO, Collector, Proc, free_port, loopback, running
from tests.stream.helpers import client_args as _client

DET, DET_INFO = "/detections", "/camera_info"
FAR_FUTURE = 2**31 - 1  # s: the largest stamp a builtin_interfaces/Time holds


def _counts(bag: Path) -> dict[str, int]:
    """Messages per topic as rosbags reads them (metadata and messages must agree)."""
    reader = open_bag(bag)
    try:
        found: dict[str, int] = {}
        for conn, _t, _raw in reader.messages():
            found[conn.topic] = found.get(conn.topic, 0) + 1
        meta = {c.topic: c.msgcount for c in reader.connections if c.msgcount}
        assert meta == found, f"metadata.yaml says {meta}, the file holds {found}"
        return found
    finally:
        reader.close()


@contextmanager
def small_disk(tmp_path: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` (a real full disk); skipped where mount is refused (not root)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if (
        subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)], capture_output=True
        ).returncode
        != 0
    ):
        if os.environ.get("CI") == "true":
            pytest.fail("CI runs as root and must be able to mount a tmpfs")
        pytest.skip("cannot mount a tmpfs here (not root)")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["mcap", "sqlite3"])
@pytest.mark.parametrize(("flush", "size"), [("60", "64k"), ("0.2", "240k")])
def test_full_disk_bag_is_readable_and_counts_are_true(
    detections: Path, bridge: Any, tmp_path: Path, kind: str, flush: str, size: str
) -> None:
    """Item 4: the disk fills before the first flush (``--flush-period 60``) or after a few:
    the bag has its metadata.yaml, rosbags and ``tagtrail init`` read it, and the counts of the
    error line are what rosbags finds, and what ``--recover`` recounts."""
    with small_disk(tmp_path, size) as disk:
        _record_onto_a_full_disk(detections, bridge[1], disk, kind, flush)


def _record_onto_a_full_disk(
    detections: Path, port: int, small_disk: Path, kind: str, flush: str
) -> None:
    bag = small_disk / f"full_{kind}"
    rec = Proc(
        [
            "record",
            str(bag),
            *_client(port),
            "--profile",
            "limo",
            "--storage",
            kind,
            "--flush-period",
            flush,
            "--duration",
            "15",
            "--stats-period",
            "1",
        ]
    )
    try:
        rec.wait_for("record: recording")
        rep = Proc(
            ["replay", str(detections), "--topics", DET, DET_INFO, *_client(port), "--rate", "4"]
        )
        assert rec.p.wait(60) == 2, rec.output
    finally:
        rec.kill()
        rep.kill()
    errors = [ln for ln in rec.lines if ln.startswith("error:")]
    assert len(errors) == 1 and "No space left on device" in errors[0], rec.output
    said = re.search(r"kept in \S+ \((.*)\) \(up to its last flush\)", errors[0])
    assert said, errors[0]
    printed = {t: int(n) for t, n in re.findall(r"(/\S+) (\d+)", said.group(1))}
    assert (bag / "metadata.yaml").is_file() and not (bag / ".tagtrail-reserve").exists()
    found = _counts(bag)
    assert {t: n for t, n in printed.items() if n} == found, (errors[0], found)
    if flush == "0.2":
        assert found.get(DET, 0) > 0, rec.output  # flushed ones are kept
    line = recover(bag)
    assert _counts(bag) == found, line
    project = small_disk.parent / "project"
    project.mkdir()
    init = subprocess.run(
        [
            sys.executable,
            "-m",
            "tagtrail.cli",
            "init",
            "--profile",
            "limo",
            "--tag-size",
            "0.16",
            "--reference",
            str(bag),
        ],
        cwd=project,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    if found.get(DET, 0) and found.get(DET_INFO, 0):
        assert init.returncode == 0, init.stderr
    else:  # a readable bag short of a topic: init names what is missing, in one line
        errors = [ln for ln in init.stderr.splitlines() if ln.startswith("error:")]
        assert init.returncode == 2 and len(errors) == 1, init.stderr
        assert (
            "metadata" not in errors[0]
            and "no messages" in errors[0]
            or "not in the bag" in errors[0]
        ), errors


def _pose(sec: int, nanosec: int = 0, x: float = 1.0) -> bytes:
    return codec.serialize(
        codec.pose_stamped(sec, nanosec, "map", (x, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0))
    )


def test_one_far_stamp_does_not_poison_relocalize_counters(tmp_path: Path) -> None:
    """Item 7 as filed: 15 poses, one stamped 2^31-1 s, then 20,000 in order (with a zero stamp
    and one far in the past among them): every in-order pose is in order, each of the three
    outliers is counted once as such."""
    case = synthetic_case(tmp_path, n_ref=50, n_query=5)
    t0 = 1_700_000_000
    stamps = [(t0 + i // 100, (i % 100) * 10_000_000) for i in range(20_015)]
    outliers = {15: (FAR_FUTURE, 0), 5_000: (0, 0), 12_000: (1, 0)}
    sent = [_pose(*outliers.get(i, st)) for i, st in enumerate(stamps)]
    sent.insert(8_000, _pose(t0 + 80, 4_000_000_000))  # not a stamp: dropped, counted
    port = free_port()
    node_args = [
        "relocalize",
        "--reference",
        case.reference,
        "--prefix",
        "rel",
        "--plane",
        "xz",
        "--listen",
        loopback(port),
        "--duration",
        "120",
        "--stats-period",
        "0",
    ]
    with running(node_args) as (node,):
        node.wait_for("relocalize: ready")
        sub = Collector(port, ["rel/distance_m"])
        pub = sub.session.declare_publisher(
            "tag_only_pose", congestion_control=zenoh.CongestionControl.BLOCK
        )
        try:
            assert wait_matching(pub, 15, threading.Event())
            for payload in sent:
                pub.put(payload)
            sub.wait("rel/distance_m", len(sent) - 1, timeout=90)
        finally:
            pub.undeclare()
            sub.close()
        assert node.stop() == 0, node.output
    stats = node.stats()
    assert stats["received"] == len(sent) and stats["processed"] == 20_015, stats
    assert stats["dropped"] == {"bad_stamp": 1}, stats
    assert stats["out_of_order"] == 0 and stats["stamp_outliers"] == 3, stats


def _pose_bag(path: Path, stamps: list[tuple[int, int]]) -> Path:
    """A rosbag2 (MCAP) of PoseStamped on /tag_only_pose with these header stamps, logged at
    10 Hz whatever the stamps say."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = msgs.typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/tag_only_pose", msgs.POSE_STAMPED, typestore=store)
        for i, st in enumerate(stamps):
            w.write(conn, 1_700_000_000 * 10**9 + i * 10**8, _pose(*st, x=1.0 + 0.01 * i))
    return path


def test_outlier_stamp_through_replay_record_and_relocalize(bridge: Any, tmp_path: Path) -> None:
    """Item 7 on every node that tracks stamps: a pose bag (40 poses at 10 Hz, one stamped
    2^31-1 s) is replayed at the recorded rate: the replay paces around the outlier (it used to
    wait for the outlier's stamp: 68 years), and neither relocalize nor record counts the poses
    after it out of order; each counts one outlier."""
    _, port = bridge
    t0 = 1_700_000_000
    stamps = [(t0 + i // 10, (i % 10) * 100_000_000) for i in range(40)]
    stamps[20] = (FAR_FUTURE, 0)
    bag = _pose_bag(tmp_path / "poses", stamps)
    case = synthetic_case(tmp_path, n_ref=50, n_query=5)
    out = tmp_path / "recorded"
    with running(
        [
            "relocalize",
            "--reference",
            case.reference,
            "--prefix",
            "rel",
            "--plane",
            "xz",
            *_client(port),
            "--duration",
            "60",
            "--stats-period",
            "0",
        ],
        [
            "record",
            str(out),
            *_client(port),
            "--topic",
            f"/tag_only_pose:{msgs.POSE_STAMPED}",
            "--duration",
            "60",
        ],
    ) as (node, rec):
        node.wait_for("relocalize: ready")
        rec.wait_for("record: recording")
        t = time.monotonic()
        with running(["replay", str(bag), *_client(port), "--rate", "1"]) as (rep,):
            assert rep.p.wait(30) == 0, rep.output
        took = time.monotonic() - t
        assert "published 40 messages" in rep.output and "1 lone stamp outlier" in rep.output
        assert took < 15, (took, rep.output)  # 3.9 s of poses
        time.sleep(1.0)
        assert node.stop() == 0, node.output
        assert rec.stop() == 0, rec.output
    stats = node.stats()
    assert stats["processed"] == 40, stats
    assert stats["out_of_order"] == 0 and stats["stamp_outliers"] == 1, stats
    last = rec.lines[-1]
    assert "40 messages" in last and "stamp outliers: /tag_only_pose 1" in last, rec.output
    assert "out of order" not in last, last


def _edit_stamp(sec: int, nanosec: int) -> Callable[[Any], None]:
    def edit(msg: Any) -> None:
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec

    return edit


def _edit_corner(msg: Any) -> None:
    msg.detections[0].corners[1].y = math.nan


def _edit_id(msg: Any) -> None:
    msg.detections[0].id = -3


def test_outlier_stamp_in_localize(detections: Path, tmp_path: Path) -> None:
    """Item 7, localize: detection messages with one stamp far in the future and one zero among
    240 in order: 2 outliers, none out of order. Item 13's class live: a NaN corner, a negative
    tag id, a stamp of 4e9 ns are dropped and counted by reason (a bag source refuses them)."""
    from tagtrail.stream.replay import bag_messages

    m = bag_messages(detections, [DET_INFO, DET])
    payloads = list(m.payloads)
    det_at = [i for i, k in enumerate(m.keys) if k == DET.lstrip("/")]
    edits = {
        100: _edit_stamp(FAR_FUTURE, 0),
        150: _edit_stamp(0, 0),
        60: _edit_corner,
        70: _edit_id,
        80: _edit_stamp(1_700_000_008, 4_000_000_000),
    }
    for j, edit in edits.items():
        msg = codec.deserialize(payloads[det_at[j]], msgs.DETECTIONS)
        edit(msg)
        payloads[det_at[j]] = codec.serialize(msg, msgs.DETECTIONS)
    port = free_port()
    node_args = [
        "localize",
        "--map",
        detections / "ground_truth" / "tag_map.yaml",
        "--listen",
        loopback(port),
        "--detections-key",
        "detections",
        "--camera-info-key",
        "camera_info",
        "--duration",
        "60",
        "--stats-period",
        "0",
    ]
    with running([str(a) for a in node_args]) as (node,):
        node.wait_for("localize: ready")
        sub = Collector(port, ["tag_only_pose"])
        pubs = {
            k: sub.session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
            for k in set(m.keys)
        }
        try:
            for p in pubs.values():
                assert wait_matching(p, 15, threading.Event())
            for k, p in zip(m.keys, payloads, strict=True):
                pubs[k].put(p)
            sub.wait("tag_only_pose", len(det_at) - 5, timeout=60)
            time.sleep(0.5)
        finally:
            for p in pubs.values():
                p.undeclare()
            sub.close()
        assert node.stop() == 0, node.output
    stats = node.stats()
    assert stats["received"] == len(payloads), stats
    assert stats["dropped"]["bad_detection"] == 2 and stats["dropped"]["bad_stamp"] == 1, stats
    assert stats["out_of_order"] == 0 and stats["stamp_outliers"] == 2, stats


def test_disk_full_before_the_first_byte_leaves_no_folder(tmp_path: Path) -> None:
    """The probe's case: no room for even the bag's first metadata.yaml: one line, and the half
    made folder is removed (it said "kept in OUT" of a folder without metadata)."""
    with small_disk(tmp_path, "64k") as disk:
        with open(disk / "filler", "wb", buffering=0) as f:  # fill the disk to its last byte
            try:
                while True:
                    f.write(bytes(4096))
            except OSError:
                pass
        bag = disk / "bag"
        rec = Proc(
            [
                "record",
                str(bag),
                "--topic",
                "/x:std_msgs/msg/Float64",
                "--listen",
                loopback(free_port()),
                "--wait",
                "5",
            ]
        )
        try:
            assert rec.p.wait(30) == 2, rec.output
        finally:
            rec.kill()
        errors = [ln for ln in rec.lines if "error:" in ln]
        assert (
            len(errors) == 1
            and f"cannot write {bag}: No space left on device" in errors[0]
            and "kept in" not in errors[0]
        ), rec.output
        assert not bag.exists()
