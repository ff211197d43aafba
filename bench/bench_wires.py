"""The relocalization node on both wires: ping-pong latency over zenoh-bridge-ros2dds's keys and
over rmw_zenoh's (keys, 33-byte attachments, liveliness tokens), side by side in one run.

Two ``tagtrail stream relocalize`` processes run at once on the same reference (tcp/127.0.0.1
only), one with ``--wire bridge``, one with ``--wire rmw_zenoh --ros-distro humble``. This
process speaks each node's wire (:mod:`tagtrail.stream.wire`: on rmw_zenoh it publishes with
the attachment and announces its endpoints, as a ROS 2 node on rmw_zenoh would) and sends one
CDR PoseStamped at a time, the next when its ``distance_m`` comes back; the repeats alternate
between the wires so both see the same machine load. Latency = pose put → distance received,
on one clock.

Prints p50/p99 per wire (medians over repeats) and the ratio rmw_zenoh / bridge;
``--write`` puts the table into ``bench/WIRES.md``.

    .venv/bin/python bench/bench_wires.py [--poses 2000] [--repeats 5] [--reference 1000] [--write]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_stream import free_port, queries, write_reference  # noqa: E402

from tagtrail.stream.session import make_config, wait_matching  # noqa: E402
from tagtrail.stream.wire import make_wire  # noqa: E402

WIRES = ("bridge", "rmw_zenoh")
POSE, F64, PATH = "geometry_msgs/msg/PoseStamped", "std_msgs/msg/Float64", "nav_msgs/msg/Path"


class Peer:
    """This side of one node: a session that speaks ``wire``."""

    def __init__(self, wire: str, port: int) -> None:
        self.session = zenoh.open(make_config("peer", connect=[f"tcp/127.0.0.1:{port}"]))
        self.wire = make_wire(wire, self.session, "humble", 0)
        self.wire.declare_node("bench_robot")
        self.pub = self.wire.declare_publisher(
            "tag_only_pose", POSE, express=True, congestion_control=zenoh.CongestionControl.BLOCK
        )
        self.got = threading.Event()
        self.recv_ns = 0
        self.path = threading.Event()
        self.subs = [
            self.wire.declare_subscriber("relocalization/distance_m", F64, self._on_d),
            self.wire.declare_subscriber(
                "relocalization/reference_path", PATH, lambda _s: self.path.set()
            ),
        ]

    def _on_d(self, _sample: zenoh.Sample) -> None:
        self.recv_ns = time.perf_counter_ns()
        self.got.set()

    def ready(self, timeout: float = 60.0) -> None:
        if not wait_matching(self.pub, timeout, threading.Event()) or not self.path.wait(timeout):
            raise RuntimeError("the node did not come up")
        self.subs.pop().undeclare()

    def ping_pong(self, payloads: list[bytes]) -> np.ndarray:
        lat = np.full(len(payloads), np.nan)
        clock = time.perf_counter_ns
        for i, p in enumerate(payloads):
            self.got.clear()
            t = clock()
            self.pub.put(p)
            if not self.got.wait(2.0):
                break
            lat[i] = (self.recv_ns - t) / 1e6
        return lat

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.pub.undeclare()
        self.wire.close()
        self.session.close()  # type: ignore[no-untyped-call]


def start_node(wire: str, ref: Path, port: int) -> subprocess.Popen[str]:
    cmd = [
        sys.executable,
        "-m",
        "tagtrail.stream.cli",
        "relocalize",
        "--reference",
        str(ref),
        "--plane",
        "xz",
        "--listen",
        f"tcp/127.0.0.1:{port}",
        "--stats-period",
        "0",
        "--wire",
        wire,
        "--ros-distro",
        "humble",
    ]
    return subprocess.Popen(
        cmd,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--reference", type=int, default=1000, help="reference samples")
    ap.add_argument("--write", action="store_true", help="write bench/WIRES.md")
    args = ap.parse_args()
    load = os.getloadavg()[0]
    print(
        f"bench_wires: {args.poses:,} ping-pong poses x {args.repeats} repeats per wire, "
        f"{args.reference:,}-sample reference, {os.cpu_count()} cores, load {load:.2f}"
    )
    payloads = queries(args.poses)
    runs: dict[str, list[dict[str, float]]] = {w: [] for w in WIRES}
    stats: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as d:
        ref = Path(d) / "ref.tum"
        write_reference(ref, args.reference)
        ports = {w: free_port() for w in WIRES}
        nodes = {w: start_node(w, ref, ports[w]) for w in WIRES}
        peers: dict[str, Peer] = {}
        try:
            for w in WIRES:
                peers[w] = Peer(w, ports[w])
                peers[w].ready()
                peers[w].ping_pong(payloads[:300])  # warm-up
            for r in range(args.repeats):
                for w in WIRES if r % 2 == 0 else WIRES[::-1]:
                    lat = peers[w].ping_pong(payloads)
                    ok = lat[np.isfinite(lat)]
                    p50, p99 = np.percentile(ok, [50, 99])
                    runs[w].append({"p50": p50, "p99": p99, "lost": float(len(lat) - len(ok))})
                    print(
                        f"  [{r + 1}/{args.repeats}] {w:9s} p50 {p50:.3f} ms p99 {p99:.3f} ms "
                        f"lost {len(lat) - len(ok)}"
                    )
        finally:
            for p in peers.values():
                p.close()
            for w, node in nodes.items():
                node.terminate()
                out, _ = node.communicate(timeout=30)
                got = [json.loads(s[6:]) for s in out.splitlines() if s.startswith("stats ")]
                stats[w] = got[-1] if got else {}
    med = {w: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for w, rs in runs.items()}
    b, z = med["bridge"], med["rmw_zenoh"]
    lines = [
        "| wire | ping-pong p50 (ms) | p99 (ms) | lost | node proc p50 / p99 (us) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for w in WIRES:
        st = stats.get(w, {})
        proc = (
            f"{st['proc_p50_us']:.0f} / {st['proc_p99_us']:.0f}"
            if st.get("proc_p50_us") is not None
            else "-"
        )
        lines.append(
            f"| {w} | {med[w]['p50']:.3f} | {med[w]['p99']:.3f} | "
            f"{int(max(r['lost'] for r in runs[w]))} | {proc} |"
        )
    ratio = f"rmw_zenoh / bridge: p50 {z['p50'] / b['p50']:.2f}x, p99 {z['p99'] / b['p99']:.2f}x"
    print("\n" + "\n".join(lines) + "\n" + ratio)
    wire_stats = stats.get("rmw_zenoh", {})
    print(
        f"rmw_zenoh node: without_attachment {wire_stats.get('without_attachment')}, "
        f"sequence_gaps {wire_stats.get('sequence_gaps')}"
    )
    if args.write:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True, capture_output=True
        ).stdout.strip()
        (ROOT / "bench" / "WIRES.md").write_text(
            "# The relocalization node on both wires\n\n"
            f"Written by `bench/bench_wires.py --write` ({commit}, "
            f"{dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC, {os.cpu_count()} cores, 1-min "
            f"load {load:.2f} at the start). {args.poses:,} poses one at a time (the next after "
            f"its `distance_m` arrives), {args.repeats} repeats per wire alternating between "
            f"the wires, a {args.reference:,}-sample reference, both nodes and this peer on "
            "tcp/127.0.0.1; medians over the repeats. On rmw_zenoh both sides put the 33-byte "
            "attachment on every sample and hold liveliness tokens, as ROS 2 nodes on "
            "rmw_zenoh do.\n\n" + "\n".join(lines) + f"\n\n{ratio}.\n"
        )
        print("wrote bench/WIRES.md")


if __name__ == "__main__":
    main()
