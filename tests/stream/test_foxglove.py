"""``tagtrail stream relocalize --foxglove``: a WebSocket client (the ``websockets`` package,
speaking the Foxglove protocol as the Foxglove app does) sees the node's advertised channels with
their ROS 2 schemas and receives D, phi and the reference path while ``stream replay`` feeds the
node over zenoh; values equal the offline report. Everything on 127.0.0.1 only."""

from __future__ import annotations

import json
import socket
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from tagtrail.stream import cli
from tests.stream.cases import synthetic_case
from tests.stream.helpers import free_port, loopback, running

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)  # plain Humble: what a ROS-free client decodes with
PREFIX = "reloc_fox"
TYPES = {
    "distance_m": "std_msgs/msg/Float64", "heading_error_deg": "std_msgs/msg/Float64",
    "current_pose": "geometry_msgs/msg/PoseStamped",
    "nearest_pose": "geometry_msgs/msg/PoseStamped",
    "markers": "visualization_msgs/msg/MarkerArray", "reference_path": "nav_msgs/msg/Path",
}  # fmt: skip


def _url(lines: list[str]) -> str:
    line = next(s for s in lines if "relocalize: foxglove " in s)
    url = line.split("relocalize: foxglove ", 1)[1].strip()
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


def test_foxglove_client_sees_channels_and_live_d(tmp_path: Path) -> None:
    pytest.importorskip("foxglove", reason="pip install 'tagtrail[foxglove]'")
    ws_client = pytest.importorskip("websockets.sync.client", reason="pip install 'tagtrail[test]'")
    case = synthetic_case(tmp_path, n_ref=200, n_query=40)
    port = free_port()
    node_args = ["relocalize", "--reference", case.reference, "--alignment", case.alignment,
                 "--prefix", PREFIX, "--listen", loopback(port), "--path-period", "0",
                 "--duration", "60", "--stats-period", "0", "--foxglove", "0"]
    with running(node_args) as (node,):
        node.wait_for("relocalize: ready")
        url = _url(node.lines)
        with ws_client.connect(url, subprotocols=["foxglove.sdk.v1"],
                               open_timeout=10) as ws:  # fmt: skip
            info = json.loads(ws.recv(timeout=10))
            assert info["op"] == "serverInfo"
            channels = _advertised(ws, len(TYPES) + 1)
            assert set(channels) == {f"/{PREFIX}/{k}" for k in (*TYPES, "state")}
            for key, typename in TYPES.items():
                c = channels[f"/{PREFIX}/{key}"]
                assert (c["encoding"], c["schemaName"], c["schemaEncoding"]) == (
                    "cdr", typename, "ros2msg")
            path_schema = channels[f"/{PREFIX}/reference_path"]["schema"]
            assert "MSG: geometry_msgs/PoseStamped" in path_schema  # the full definition
            assert channels[f"/{PREFIX}/state"]["encoding"] == "json"

            sub_of = {1: "distance_m", 2: "heading_error_deg", 3: "reference_path", 4: "state"}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": channels[f"/{PREFIX}/{k}"]["id"]}
                for i, k in sub_of.items()]}))  # fmt: skip
            got: dict[str, list[bytes]] = {k: [] for k in sub_of.values()}
            # the path was published once, before this client: it is latched for new subscribers
            while not got["reference_path"]:
                _collect(ws, sub_of, got)
            with running(["replay", case.query, "--rate", "0", "--connect", loopback(port),
                          "--wait", "10"]) as (rep,):  # fmt: skip
                assert rep.p.wait(30) == 0, rep.output
            while len(got["state"]) < len(case.offline) or len(got["distance_m"]) < len(
                    case.offline):  # fmt: skip
                _collect(ws, sub_of, got)
        assert node.stop() == 0, node.output

    off = case.offline.set_index("t_ns")
    states = [json.loads(b) for b in got["state"]]
    t_ns = [s["stamp_sec"] * 10**9 + s["stamp_nanosec"] for s in states]
    assert sorted(t_ns) == sorted(off.index)
    D = [HUMBLE.deserialize_cdr(b, "std_msgs/msg/Float64").data for b in got["distance_m"]]
    phi = [HUMBLE.deserialize_cdr(b, "std_msgs/msg/Float64").data
           for b in got["heading_error_deg"]]  # fmt: skip
    # one result per pose, in the order handled: D/phi line up with the states' stamps
    np.testing.assert_allclose(D, off.loc[t_ns, "distance_m"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(phi, off.loc[t_ns, "heading_error_deg"], rtol=0, atol=1e-9)
    path = HUMBLE.deserialize_cdr(got["reference_path"][0], "nav_msgs/msg/Path")
    assert len(path.poses) == 200 and path.header.frame_id == "map"


def _collect(ws: Any, sub_of: dict[int, str], got: dict[str, list[bytes]]) -> None:
    """One server message; a binary ``messageData`` (opcode 1: u32 subscription, u64 log time,
    payload) is appended to its subscription's list."""
    msg = ws.recv(timeout=20)
    if isinstance(msg, bytes) and msg[0] == 1:
        (sub_id,) = struct.unpack_from("<I", msg, 1)
        got[sub_of[sub_id]].append(msg[13:])


def test_missing_sdk_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                 capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    case = synthetic_case(tmp_path, n_ref=20, n_query=5)
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove → ImportError
    rc = cli.main(["relocalize", "--reference", str(case.reference), "--foxglove",
                   "--listen", loopback(free_port()), "--duration", "0"])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0] == "error: --foxglove needs the foxglove-sdk package: pip install " \
        "'tagtrail[foxglove]'"


def test_port_in_use_and_bad_port(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("foxglove", reason="pip install 'tagtrail[foxglove]'")
    case = synthetic_case(tmp_path, n_ref=20, n_query=5)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        busy = s.getsockname()[1]
        rc = cli.main(["relocalize", "--reference", str(case.reference), "--foxglove", str(busy),
                       "--listen", loopback(free_port()), "--duration", "0"])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith(
        f"error: --foxglove: cannot serve on 127.0.0.1:{busy}: "), err
    with pytest.raises(SystemExit) as exc:
        cli.build_parser().parse_args(["relocalize", "--reference", "x", "--foxglove", "70000"])
    assert exc.value.code == 2
    assert "must be a TCP port 0..65535" in capsys.readouterr().err
