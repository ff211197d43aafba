"""End to end over real zenoh sessions in separate processes, on 127.0.0.1 only:
``stream replay`` (a trajectory file) → ``stream relocalize`` → this test's subscriber, which
decodes the CDR outputs with rosbags' ROS 2 Humble typestore (as a ROS node behind
zenoh-bridge-ros2dds would) and finds the offline report's D and phi."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from tagtrail.io.layouts import read_trajectory
from tests.stream.cases import Case, limo_case, synthetic_case
from tests.stream.helpers import Collector, free_port, loopback, running

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)  # plain Humble, not tagtrail's store
PREFIX = "reloc_test"
KEYS = (
    "distance_m",
    "heading_error_deg",
    "current_pose",
    "nearest_pose",
    "reference_path",
    "markers",
    "state",
)


@pytest.fixture(params=["synthetic", "limo"])
def case(request: pytest.FixtureRequest, tmp_path: Path) -> Case:
    if request.param == "limo":
        return limo_case(tmp_path, request.getfixturevalue("realdata") / "limo_seed_runs")
    return synthetic_case(tmp_path)


def test_replay_relocalize_matches_offline_report(case: Case) -> None:
    port = free_port()
    n = len(case.offline)
    node_args = [
        "relocalize",
        "--reference",
        case.reference,
        "--alignment",
        case.alignment,
        "--prefix",
        PREFIX,
        "--listen",
        loopback(port),
        "--path-period",
        "0.5",
        "--duration",
        "45",
        "--stats-period",
        "0",
    ]
    with running(node_args) as (node,):
        node.wait_for("relocalize: ready")
        sub = Collector(port, [f"{PREFIX}/{k}" for k in KEYS])
        try:
            # a periodic reference path arriving = our subscriptions are known to the node
            path_raw = sub.wait(f"{PREFIX}/reference_path", 1, timeout=15)[0]
            replies = list(sub.session.get(f"{PREFIX}/reference_path", timeout=5.0))
            with running(
                ["replay", case.query, "--rate", "0", "--connect", loopback(port), "--wait", "10"]
            ) as (rep,):
                assert rep.p.wait(30) == 0, rep.output
            got = {k: sub.wait(f"{PREFIX}/{k}", n) for k in KEYS if k != "reference_path"}
            got["markers"] = sub.wait_until(
                f"{PREFIX}/markers",
                lambda v: (
                    sum(
                        len(HUMBLE.deserialize_cdr(b, "visualization_msgs/msg/MarkerArray").markers)
                        == 3
                        for b in v
                    )
                    >= n
                ),
            )
        finally:
            sub.close()
        assert node.p.poll() is None, "the node stopped on its own"
        assert node.stop() == 0, node.output
    stats = node.stats()
    assert stats["processed"] == n and stats["dropped"] == {}, stats

    # D and phi: identical to the offline report, pose by pose (matched by stamp)
    states = [json.loads(b) for b in got["state"]]
    assert len(states) == n
    D = [HUMBLE.deserialize_cdr(b, "std_msgs/msg/Float64").data for b in got["distance_m"]]
    phi = [HUMBLE.deserialize_cdr(b, "std_msgs/msg/Float64").data for b in got["heading_error_deg"]]
    off = case.offline.set_index("t_ns")
    t_ns = np.array([s["stamp_sec"] * 10**9 + s["stamp_nanosec"] for s in states])
    assert sorted(t_ns) == sorted(off.index)
    row = off.loc[t_ns]
    np.testing.assert_allclose(D, row["distance_m"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(phi, row["heading_error_deg"], rtol=0, atol=1e-9)
    np.testing.assert_allclose([s["distance_m"] for s in states], row["distance_m"], atol=1e-9)
    np.testing.assert_allclose(
        [s["heading_error_rad"] for s in states], np.radians(row["heading_error_deg"]), atol=1e-9
    )
    np.testing.assert_allclose([s["u"] for s in states], row["query_u"], atol=1e-9)
    np.testing.assert_allclose([s["v"] for s in states], row["query_v"], atol=1e-9)
    assert [s["nearest_ref_idx"] for s in states] == row["nearest_ref_idx"].tolist()
    assert list(states[0])[:8] == [
        "stamp_sec",
        "stamp_nanosec",
        "distance_m",
        "heading_error_deg",
        "heading_error_rad",
        "nearest_ref_idx",
        "u",
        "v",
    ]  # the seed's keys first; the tracker's follow
    assert set(states[0]) - set(list(states[0])[:8]) == {
        "cross_track_m",
        "progress_m",
        "curvature_1pm",
        "lookahead_u",
        "lookahead_v",
        "lost",
    }

    # every output decodes as its ROS type; poses carry the input stamps
    ref = read_trajectory(case.reference)
    ref_xyz = ref[["x_m", "y_m", "z_m"]].to_numpy()
    for raw, s in zip(got["nearest_pose"], states, strict=True):
        m = HUMBLE.deserialize_cdr(raw, "geometry_msgs/msg/PoseStamped")
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (s["stamp_sec"], s["stamp_nanosec"])
        p = m.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], ref_xyz[s["nearest_ref_idx"]], atol=1e-12)
    cur = HUMBLE.deserialize_cdr(got["current_pose"][0], "geometry_msgs/msg/PoseStamped")
    assert cur.header.frame_id == "map"
    path = HUMBLE.deserialize_cdr(path_raw, "nav_msgs/msg/Path")
    assert len(path.poses) == len(ref)
    np.testing.assert_allclose(
        [[q.pose.position.x, q.pose.position.y, q.pose.position.z] for q in path.poses],
        ref_xyz,
        atol=1e-12,
    )
    assert replies and replies[0].ok is not None
    assert replies[0].ok.payload.to_bytes() == path_raw
    arrays = [
        HUMBLE.deserialize_cdr(b, "visualization_msgs/msg/MarkerArray") for b in got["markers"]
    ]
    per_pose = [a for a in arrays if len(a.markers) == 3]
    line = [a for a in arrays if len(a.markers) == 1]
    assert len(per_pose) == n and line, "per-pose markers and the path line strip"
    assert line[0].markers[0].type == 4 and len(line[0].markers[0].points) == len(ref)
    sphere, seg, text = per_pose[-1].markers
    assert (sphere.type, seg.type, text.type) == (2, 5, 9)
    assert len(seg.points) == 2 and f"{states[-1]['distance_m']:7.3f}" in text.text


def test_stream_help_lists_commands(capsys: pytest.CaptureFixture[str]) -> None:
    from tagtrail.stream.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    out = capsys.readouterr().out
    assert all(c in out for c in ("relocalize", "replay", "localize"))
