"""``tagtrail stream relocalize|localize --foxglove``: the live outputs on the Foxglove WebSocket
that ``foxglove-sdk`` serves. The client here is written in the test from the Foxglove WebSocket
protocol (the ``websockets`` package; the SDK has no client): subprotocol ``foxglove.sdk.v1``,
JSON ``serverInfo``/``advertise``/``subscribe``, binary ``messageData`` (opcode 1, u32
subscription id, u64 log time, payload). Each channel's CDR is decoded by rosbags against the
``ros2msg`` schema the server advertised (not tagtrail's types) and compared with what the node
publishes on zenoh (byte for byte) and with values the node did not compute (the offline report,
the simulator's ground truth). Everything on 127.0.0.1 only."""

from __future__ import annotations

import json
import socket
import struct
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from tagtrail.io.layouts import read_trajectory
from tagtrail.sim.simulate import simulate
from tagtrail.stream import cli
from tests.stream.cases import synthetic_case
from tests.stream.helpers import Collector, free_port, loopback, running

PREFIX = "reloc_fox"
TYPES = {
    "distance_m": "std_msgs/msg/Float64",
    "heading_error_deg": "std_msgs/msg/Float64",
    "current_pose": "geometry_msgs/msg/PoseStamped",
    "nearest_pose": "geometry_msgs/msg/PoseStamped",
    "markers": "visualization_msgs/msg/MarkerArray",
    "reference_path": "nav_msgs/msg/Path",
    "cross_track_m": "std_msgs/msg/Float64",
    "progress_m": "std_msgs/msg/Float64",
    "curvature_1pm": "std_msgs/msg/Float64",
    "lookahead_pose": "geometry_msgs/msg/PoseStamped",
}
SUBPROTOCOL = "foxglove.sdk.v1"  # what foxglove-sdk's server accepts (and the Foxglove app sends)
Got = dict[str, list[tuple[int, bytes]]]  # channel topic → [(log time ns, payload)]


def _sdk_and_client() -> Any:
    pytest.importorskip("foxglove", reason="pip install 'tagtrail[foxglove]'")
    return pytest.importorskip("websockets.sync.client", reason="pip install 'tagtrail[test]'")


def _url(lines: list[str], node: str) -> str:
    line = next(s for s in lines if f"{node}: foxglove " in s)
    url = line.split(f"{node}: foxglove ", 1)[1].strip()
    assert url.startswith("ws://127.0.0.1:"), url
    return url


def _advertised(ws: Any, n: int) -> dict[str, dict[str, Any]]:
    """The channels of the server's ``advertise`` messages, by topic, once ``n`` are known."""
    channels: dict[str, dict[str, Any]] = {}
    while len(channels) < n:
        msg = ws.recv(timeout=10)
        if isinstance(msg, str):
            doc = json.loads(msg)
            if doc["op"] == "advertise":
                channels.update({c["topic"]: c for c in doc["channels"]})
    return channels


def _open(ws: Any, n_channels: int) -> dict[str, dict[str, Any]]:
    """The handshake's outcome: the subprotocol, ``serverInfo`` first, then the channels."""
    assert ws.subprotocol == SUBPROTOCOL
    info = json.loads(ws.recv(timeout=10))
    assert info["op"] == "serverInfo", info
    return _advertised(ws, n_channels)


def _subscribe(ws: Any, channels: dict[str, dict[str, Any]], topics: list[str]) -> dict[int, str]:
    """Subscribe to ``topics``; subscription id → topic."""
    sub_of = dict(enumerate(topics, start=1))
    ws.send(
        json.dumps(
            {
                "op": "subscribe",
                "subscriptions": [
                    {"id": i, "channelId": channels[t]["id"]} for i, t in sub_of.items()
                ],
            }
        )
    )
    return sub_of


def _collect(ws: Any, sub_of: dict[int, str], got: Got) -> None:
    """One server message; a binary ``messageData`` is appended to its subscription's list."""
    msg = ws.recv(timeout=20)
    if isinstance(msg, bytes) and msg[0] == 1:
        sub_id, log_time = struct.unpack_from("<IQ", msg, 1)
        got[sub_of[sub_id]].append((log_time, msg[13:]))


def _decoder(channel: dict[str, Any]) -> Any:
    """A rosbags type store holding only the channel's advertised ``ros2msg`` schema (the full
    definition, dependencies after ``===`` lines), as a ROS-free client builds it."""
    assert (channel["encoding"], channel["schemaEncoding"]) == ("cdr", "ros2msg"), channel
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(channel["schema"], channel["schemaName"]))
    return store


def _decode(channel: dict[str, Any], payloads: list[bytes]) -> list[Any]:
    store = _decoder(channel)
    return [store.deserialize_cdr(b, channel["schemaName"]) for b in payloads]


def _check_log_times(got: Got, t0_ns: int, t1_ns: int) -> None:
    """Live log times: wall-clock nanoseconds within the test's window, in order per channel."""
    for topic, items in got.items():
        t = [lt for lt, _ in items]
        assert t == sorted(t) and all(t0_ns <= x <= t1_ns for x in t), topic


def test_relocalize_serves_d_and_phi_as_published_on_zenoh(tmp_path: Path) -> None:
    ws_client = _sdk_and_client()
    case = synthetic_case(tmp_path, n_ref=200, n_query=40)
    port = free_port()
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
        "0",
        "--duration",
        "60",
        "--stats-period",
        "0",
        "--foxglove",
        "0",
    ]
    d_key, phi_key = f"{PREFIX}/distance_m", f"{PREFIX}/heading_error_deg"
    n = len(case.offline)
    t0 = time.time_ns()
    with running(node_args) as (node,):
        node.wait_for("relocalize: ready")
        zsub = Collector(port, [d_key, phi_key])
        try:
            with ws_client.connect(
                _url(node.lines, "relocalize"), subprotocols=[SUBPROTOCOL], open_timeout=10
            ) as ws:
                channels = _open(ws, len(TYPES) + 1)
                assert set(channels) == {f"/{PREFIX}/{k}" for k in (*TYPES, "state")}
                for key, typename in TYPES.items():
                    c = channels[f"/{PREFIX}/{key}"]
                    assert (c["encoding"], c["schemaName"], c["schemaEncoding"]) == (
                        "cdr",
                        typename,
                        "ros2msg",
                    )
                assert (
                    "MSG: geometry_msgs/PoseStamped"
                    in channels[f"/{PREFIX}/reference_path"]["schema"]
                )  # the full definition
                assert channels[f"/{PREFIX}/state"]["encoding"] == "json"
                sub_of = _subscribe(ws, channels, sorted(channels))
                got: Got = {t: [] for t in channels}
                # the path was published once, before this client: latched for new subscribers
                while not got[f"/{PREFIX}/reference_path"]:
                    _collect(ws, sub_of, got)
                with running(
                    [
                        "replay",
                        case.query,
                        "--rate",
                        "0",
                        "--connect",
                        loopback(port),
                        "--wait",
                        "10",
                    ]
                ) as (rep,):
                    assert rep.p.wait(30) == 0, rep.output
                # one message per pose on each channel; markers: + the latched path's marker
                want = {t: n + (t == f"/{PREFIX}/markers") for t in channels}
                del want[f"/{PREFIX}/reference_path"]
                while any(len(got[t]) < k for t, k in want.items()):
                    _collect(ws, sub_of, got)
            on_zenoh = {k: zsub.wait(k, n) for k in (d_key, phi_key)}
        finally:
            zsub.close()
        assert node.stop() == 0, node.output
    _check_log_times(got, t0, time.time_ns())

    # the same bytes, in the same order, as the node put on zenoh
    for key in (d_key, phi_key):
        assert [b for _, b in got[f"/{key}"]] == on_zenoh[key], key
    # decoded against the advertised schema, equal to the offline report (not the node's code)
    off = case.offline.set_index("t_ns")
    states = [json.loads(b) for _, b in got[f"/{PREFIX}/state"]]
    t_ns = [s["stamp_sec"] * 10**9 + s["stamp_nanosec"] for s in states]
    assert sorted(t_ns) == sorted(off.index)
    D = [m.data for m in _decode(channels[f"/{d_key}"], [b for _, b in got[f"/{d_key}"]])]
    phi = [m.data for m in _decode(channels[f"/{phi_key}"], [b for _, b in got[f"/{phi_key}"]])]
    # one result per pose, in the order handled: D/phi line up with the states' stamps
    np.testing.assert_allclose(D, off.loc[t_ns, "distance_m"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(phi, off.loc[t_ns, "heading_error_deg"], rtol=0, atol=1e-9)
    # every message of every CDR channel decodes against its advertised schema
    decoded = {
        t: _decode(channels[t], [b for _, b in got[t]])
        for t in channels
        if channels[t]["encoding"] == "cdr"
    }
    for key in ("current_pose", "nearest_pose"):
        stamps = [
            m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in decoded[f"/{PREFIX}/{key}"]
        ]
        assert stamps == t_ns, key
    assert len(decoded[f"/{PREFIX}/markers"]) == n + 1
    (path,) = _decode(
        channels[f"/{PREFIX}/reference_path"], [got[f"/{PREFIX}/reference_path"][0][1]]
    )
    ref = read_trajectory(case.reference)
    assert len(path.poses) == 200 and path.header.frame_id == "map"
    np.testing.assert_allclose([p.pose.position.x for p in path.poses], ref["x_m"], atol=1e-12)


def test_localize_serves_its_poses(tmp_path: Path) -> None:
    """``stream localize --foxglove``: the PoseStamped of each frame, as published on zenoh, equal
    to the simulator's ground truth (noise-free corners: exact)."""
    ws_client = _sdk_and_client()
    n_frames = 20
    rec = simulate(
        "circle", tmp_path, frames=n_frames, detections=True, corner_noise_px=0.0, seed=3
    )["circle"]
    gt = read_trajectory(rec / "ground_truth" / "trajectory.csv").set_index("t_ns")
    port = free_port()
    node_args = [
        "localize",
        "--map",
        rec / "ground_truth" / "tag_map.yaml",
        "--listen",
        loopback(port),
        "--duration",
        "60",
        "--stats-period",
        "0",
        "--foxglove",
        "0",
    ]
    t0 = time.time_ns()
    with running(node_args) as (node,):
        node.wait_for("localize: ready")
        zsub = Collector(port, ["tag_only_pose"])
        try:
            with ws_client.connect(
                _url(node.lines, "localize"), subprotocols=[SUBPROTOCOL], open_timeout=10
            ) as ws:
                channels = _open(ws, 1)
                assert set(channels) == {"/tag_only_pose"}
                c = channels["/tag_only_pose"]
                assert (c["schemaName"], c["encoding"]) == ("geometry_msgs/msg/PoseStamped", "cdr")
                sub_of = _subscribe(ws, channels, ["/tag_only_pose"])
                with running(
                    [
                        "replay",
                        rec,
                        "--topics",
                        "/camera_info",
                        "/detections",
                        "--connect",
                        loopback(port),
                        "--rate",
                        "0",
                    ]
                ) as (rep,):
                    assert rep.p.wait(30) == 0, rep.output
                # a detection before the first CameraInfo is kept until it comes: every frame
                on_zenoh = zsub.wait("tag_only_pose", n_frames)
                time.sleep(0.5)
                on_zenoh = zsub.wait("tag_only_pose", len(on_zenoh))
                got: Got = {"/tag_only_pose": []}
                while len(got["/tag_only_pose"]) < len(on_zenoh):
                    _collect(ws, sub_of, got)
        finally:
            zsub.close()
        assert node.stop() == 0, node.output
    _check_log_times(got, t0, time.time_ns())
    payloads = [b for _, b in got["/tag_only_pose"]]
    assert payloads == on_zenoh
    for msg in _decode(c, payloads):
        row = gt.loc[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec]
        p = msg.pose.position
        assert msg.header.frame_id == "map"
        assert np.linalg.norm([p.x - row.x_m, p.y - row.y_m, p.z - row.z_m]) < 1e-6


def test_viewer_must_speak_the_sdk_subprotocol() -> None:
    """The SDK's server (what ``--foxglove`` runs, in process here) answers ``foxglove.sdk.v1``
    and refuses a client offering only the older ``foxglove.websocket.v1`` (HTTP 400): viewers
    too old to offer the new name (docs/FOXGLOVE.md) cannot connect."""
    ws_client = _sdk_and_client()
    from websockets.exceptions import InvalidStatus

    from tagtrail.stream.foxglove import FoxgloveServer

    fox = FoxgloveServer({"fox_test/d": "std_msgs/msg/Float64"}, port=0)
    try:
        assert fox.url.startswith("ws://127.0.0.1:")
        with ws_client.connect(
            fox.url, subprotocols=["foxglove.websocket.v1", SUBPROTOCOL], open_timeout=10
        ) as ws:
            channels = _open(ws, 1)
            assert channels["/fox_test/d"]["schemaName"] == "std_msgs/msg/Float64"
        with pytest.raises(InvalidStatus) as info:
            ws_client.connect(fox.url, subprotocols=["foxglove.websocket.v1"], open_timeout=10)
        assert info.value.response.status_code == 400
    finally:
        fox.close()


def test_missing_sdk_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    case = synthetic_case(tmp_path, n_ref=20, n_query=5)
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove → ImportError
    rc = cli.main(
        [
            "relocalize",
            "--reference",
            str(case.reference),
            "--foxglove",
            "--listen",
            loopback(free_port()),
            "--duration",
            "0",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert (
        err[0] == "error: --foxglove needs the foxglove-sdk package: pip install "
        "'tagtrail[foxglove]'"
    )


def test_port_in_use_and_bad_port(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("foxglove", reason="pip install 'tagtrail[foxglove]'")
    case = synthetic_case(tmp_path, n_ref=20, n_query=5)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        busy = s.getsockname()[1]
        rc = cli.main(
            [
                "relocalize",
                "--reference",
                str(case.reference),
                "--foxglove",
                str(busy),
                "--listen",
                loopback(free_port()),
                "--duration",
                "0",
            ]
        )
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        rc == 2
        and len(err) == 1
        and err[0].startswith(f"error: --foxglove: cannot serve on 127.0.0.1:{busy}: ")
    ), err
    with pytest.raises(SystemExit) as exc:
        cli.build_parser().parse_args(["relocalize", "--reference", "x", "--foxglove", "70000"])
    assert exc.value.code == 2
    assert "must be a TCP port 0..65535" in capsys.readouterr().err
