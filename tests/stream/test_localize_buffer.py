"""Inputs of ``stream localize`` that arrive before the first CameraInfo are kept — a bounded
queue (the last ``WAIT_N`` inputs, ``WAIT_BYTES``, for ``WAIT_S``) — and posed when it comes;
what the bound pushes out is dropped and counted as ``no_camera_info``."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
import zenoh

from tagtrail.io.layouts import read_tag_map
from tagtrail.sim.simulate import simulate
from tagtrail.stream import codec, localize
from tagtrail.stream.localize import Localizer
from tagtrail.stream.replay import bag_messages
from tagtrail.stream.session import wait_matching
from tagtrail.stream.stats import Deferred, Stats
from tests.stream.helpers import Collector, free_port, loopback, running

N = localize.WAIT_N + 5


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate("circle", tmp_path_factory.mktemp("loc_buf"), frames=N, detections=True)[
        "circle"
    ]


def _inputs(rec: Path) -> tuple[bytes, list[bytes]]:
    m = bag_messages(rec, ["/camera_info", "/detections"])
    info = m.payloads[m.keys.index("camera_info")]
    return info, [p for k, p in zip(m.keys, m.payloads, strict=True) if k == "detections"]


def _stamps(out: list[tuple[str, bytes]]) -> list[int]:
    return [codec.decode_pose(p).sec * 10**9 + codec.decode_pose(p).nanosec for _, p in out]


def _det_stamp(data: bytes) -> int:
    h = codec.deserialize(data, "apriltag_msgs/msg/AprilTagDetectionArray").header.stamp
    return int(h.sec) * 10**9 + int(h.nanosec)


def test_the_last_n_inputs_are_kept(rec: Path) -> None:
    info, dets = _inputs(rec)
    assert len(dets) == N
    stats = Stats("localize")
    loc = Localizer(read_tag_map(rec / "ground_truth" / "tag_map.yaml")[0], stats=stats)
    for d in dets:
        with pytest.raises(Deferred):
            loc.on_detections(d)
    assert stats.dropped["no_camera_info"] == N - localize.WAIT_N
    out = loc.on_camera_info(info)
    assert _stamps(out) == [_det_stamp(d) for d in dets[-localize.WAIT_N :]]
    assert stats.processed == localize.WAIT_N and not loc.waiting
    assert loc.on_camera_info(info) == []  # released once
    assert len(loc.on_detections(dets[0])) == 1  # and then handled at once


def test_kept_inputs_expire(rec: Path) -> None:
    info, dets = _inputs(rec)
    now = [100.0]
    stats = Stats("localize")
    loc = Localizer(
        read_tag_map(rec / "ground_truth" / "tag_map.yaml")[0], stats=stats, clock=lambda: now[0]
    )
    for d, t in zip(dets[:3], (100.0, 100.5, 100.9), strict=True):
        now[0] = t
        with pytest.raises(Deferred):
            loc.on_detections(d)
    now[0] = 100.0 + localize.WAIT_S + 0.2  # the first is too old, the others within WAIT_S
    out = loc.on_camera_info(info)
    assert _stamps(out) == [_det_stamp(d) for d in dets[1:3]]
    assert dict(stats.dropped) == {"no_camera_info": 1} and stats.processed == 2


def test_kept_inputs_are_bounded_in_bytes(rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    info, dets = _inputs(rec)
    monkeypatch.setattr(localize, "WAIT_BYTES", 2 * len(dets[0]) + 10)
    stats = Stats("localize")
    loc = Localizer(read_tag_map(rec / "ground_truth" / "tag_map.yaml")[0], stats=stats)
    for d in dets[:5]:
        with pytest.raises(Deferred):
            loc.on_detections(d)
    assert len(loc.waiting) == 2 and stats.dropped["no_camera_info"] == 3
    assert _stamps(loc.on_camera_info(info)) == [_det_stamp(d) for d in dets[3:5]]


def test_node_poses_detections_sent_before_the_camera_info(rec: Path) -> None:
    """A real node: every detection published before the first CameraInfo is posed once it
    comes; a detection before the first CameraInfo used to be dropped."""
    info, dets = _inputs(rec)
    dets = dets[: localize.WAIT_N]
    port = free_port()
    args = [
        "localize",
        "--map",
        str(rec / "ground_truth" / "tag_map.yaml"),
        "--listen",
        loopback(port),
        "--duration",
        "40",
        "--stats-period",
        "0",
    ]
    with running(args) as (node,):
        node.wait_for("localize: ready")
        sub = Collector(port, ["tag_only_pose"])
        pubs = {
            k: sub.session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
            for k in ("detections", "camera_info")
        }
        try:
            for p in pubs.values():
                assert wait_matching(p, 15, threading.Event())
            for d in dets:
                pubs["detections"].put(d)
            pubs["camera_info"].put(info)
            got = sub.wait("tag_only_pose", len(dets), timeout=30)
        finally:
            for p in pubs.values():
                p.undeclare()
            sub.close()
        assert node.stop() == 0, node.output
    assert sorted(_stamps([("", p) for p in got])) == [_det_stamp(d) for d in dets]
    stats = node.stats()
    assert stats["processed"] == len(dets) + 1 and not stats["dropped"], stats
