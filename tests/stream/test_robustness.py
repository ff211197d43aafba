"""Bad input to a running relocalize node (separate process, 127.0.0.1): malformed payloads,
wrong types, NaN/inf poses, a zero quaternion, a DELETE, stamps out of order — every bad sample is
counted and dropped, the good ones are answered, the node keeps running and exits cleanly."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import zenoh

from tagtrail.stream import codec
from tests.stream.cases import synthetic_case
from tests.stream.helpers import Collector, free_port, loopback, running

PREFIX = "robust"


def _pose(sec: int, x: float = 1.0, q: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0)) -> bytes:
    return codec.serialize(codec.pose_stamped(sec, 0, "map", (x, 0.0, 0.5), q))


def test_bad_payloads_are_counted_and_dropped(tmp_path: Path) -> None:
    case = synthetic_case(tmp_path, n_ref=50, n_query=5)
    T = codec.types()
    cov = T["geometry_msgs/msg/PoseWithCovarianceStamped"](
        codec.header(1, 0, "map"),
        T["geometry_msgs/msg/PoseWithCovariance"](
            codec.pose((1, 2, 3), (0, 0, 0, 1)), np.zeros(36)
        ),
    )
    good = _pose(5)
    malformed = [
        b"",
        b"garbage",
        b"\x01\x00\x00\x00" + good[4:],
        good[:60],
        good + b"\x00" * 16,
        codec.encode_float64(1.0),
        codec.serialize(cov),
        good[:12] + (10_000).to_bytes(4, "little") + good[16:],  # string longer than the payload
    ]
    bad_values = [_pose(6, x=math.nan), _pose(6, x=math.inf), _pose(6, q=(0.0, 0.0, 0.0, 0.0))]
    port = free_port()
    node_args = [
        "relocalize",
        "--reference",
        case.reference,
        "--prefix",
        PREFIX,
        "--plane",
        "xz",
        "--listen",
        loopback(port),
        "--duration",
        "45",
        "--stats-period",
        "0",
    ]
    with running(node_args) as (node,):
        node.wait_for("relocalize: ready")
        sub = Collector(port, [f"{PREFIX}/distance_m", f"{PREFIX}/reference_path"])
        pub = sub.session.declare_publisher(
            "tag_only_pose", congestion_control=zenoh.CongestionControl.BLOCK
        )
        try:
            sub.wait(f"{PREFIX}/reference_path", 1, timeout=15)
            for payload in [*malformed, *bad_values]:
                pub.put(payload)
            pub.delete()
            for sec in (5, 3, 7):  # 3 is out of order: tolerated
                pub.put(_pose(sec))
            out = sub.wait(f"{PREFIX}/distance_m", 3)
            assert node.p.poll() is None, node.output
        finally:
            pub.undeclare()
            sub.close()
        assert node.stop() == 0, node.output
    assert len(out) == 3
    stats = node.stats()
    assert stats["processed"] == 3, stats
    assert stats["dropped"] == {
        "malformed": len(malformed),
        "non_finite": 2,
        "bad_quaternion": 1,
        "delete": 1,
    }, stats
    assert stats["received"] == len(malformed) + len(bad_values) + 1 + 3
    assert stats["out_of_order"] == 1
    assert "Traceback" not in node.output
