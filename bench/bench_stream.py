"""Streaming relocalization: end-to-end latency (pose published → distance received) and throughput.

A ``tagtrail stream relocalize`` node runs in its own process (tcp/127.0.0.1 only) on a reference
trajectory of N samples (1,000 and 1,000,000 by default); this process publishes CDR PoseStamped
poses and receives ``relocalization/distance_m`` (+ ``state``, to check order and drops) on the
same clock. Per reference size and repeat:

- ``ping-pong``: one pose at a time (the next after its distance arrives): the latency itself;
- ``paced``: poses at ``--rate`` (default 2,000/s, the throughput goal) — latency under load, and
  whether every pose is answered, in order, with no backlog;
- ``flood``: as fast as possible — the sustained throughput.

Query poses: a drive along the reference with a lateral offset sweeping ±0.3 m on both sides
(``--random-poses``: anywhere near the loop, no continuity).

Prints p50/p99 latency and poses/s (medians over repeats) and ratios to the goals
(p99 < 2 ms at 1,000,000 samples; ≥ 2,000 poses/s without a drop).

    .venv/bin/python bench/bench_stream.py [--poses 10000] [--repeats 3] [--sizes 1000 1000000]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tagtrail.io.layouts import POSE_COLS  # noqa: E402
from tagtrail.stream import codec  # noqa: E402
from tagtrail.stream.session import make_config, wait_matching  # noqa: E402
from tests.stream.cases import frame, planar_poses  # noqa: E402

GOAL_P99_MS, GOAL_RATE = 2.0, 2000.0


def write_reference(path: Path, n: int) -> None:
    """An ellipse (3 × 2 m) in x–z with n samples, as a TUM file (fast to write and read)."""
    s = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    T = planar_poses(
        1.5 * np.cos(s), np.sin(s), np.arctan2(np.cos(s), -1.5 * np.sin(s)), np.full(n, -0.13)
    )
    df = frame(T, np.arange(n, dtype=np.int64) * 10_000_000)
    arr = np.column_stack([df["t_ns"].to_numpy() * 1e-9, df[POSE_COLS].to_numpy()])
    np.savetxt(path, arr, fmt="%.17g")


def queries(n: int, random: bool = False, seed: int = 0) -> list[bytes]:
    """n poses near the ellipse; pose i has stamp (i, 0) so results can be matched.

    Default: a drive along the reference (3 laps) with the lateral offset sweeping ±0.3 m (both
    sides of the loop, the concave one included) and the heading off by up to ±30°, as a robot
    tracking it. ``random``: every pose anywhere near the loop (no continuity at all).
    """
    rng = np.random.default_rng(seed)
    if random:
        s = rng.uniform(0, 2 * np.pi, n)
        off, dh = rng.uniform(-0.3, 0.3, n), rng.uniform(-np.pi, np.pi, n)
    else:
        s = np.linspace(0, 6 * np.pi, n)
        off = 0.3 * np.sin(np.linspace(0, 40 * np.pi, n))
        dh = np.radians(30) * np.sin(np.linspace(0, 26 * np.pi, n))
    tu, tv = -1.5 * np.sin(s), np.cos(s)
    norm = np.hypot(tu, tv)
    u = 1.5 * np.cos(s) + off * tv / norm  # offset along the normal
    v = np.sin(s) - off * tu / norm
    T = planar_poses(u, v, np.arctan2(tv, tu) + dh, np.full(n, -0.13))
    df = frame(T, np.zeros(n, dtype=np.int64))
    enc = codec.PoseStampedEncoder("map")
    return [enc(i, 0, *v) for i, v in enumerate(df[POSE_COLS].to_numpy().tolist())]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Bench:
    """The publishing/receiving side, connected to the node."""

    def __init__(self, port: int, express: bool) -> None:
        self.session = zenoh.open(make_config("peer", connect=[f"tcp/127.0.0.1:{port}"]))
        self.pub = self.session.declare_publisher(
            "tag_only_pose", congestion_control=zenoh.CongestionControl.BLOCK, express=express
        )
        self.recv_ns: list[int] = []
        self.stamps: list[int] = []
        self.got = threading.Event()
        self.path = threading.Event()
        self.subs = [
            self.session.declare_subscriber("relocalization/distance_m", self._on_distance),
            self.session.declare_subscriber("relocalization/state", self._on_state),
            self.session.declare_subscriber(
                "relocalization/reference_path", lambda _s: self.path.set()
            ),
        ]

    def _on_distance(self, _sample: zenoh.Sample) -> None:
        self.recv_ns.append(time.perf_counter_ns())
        self.got.set()

    def _on_state(self, sample: zenoh.Sample) -> None:
        self.stamps.append(json.loads(sample.payload.to_bytes())["stamp_sec"])

    def ready(self, timeout: float = 120.0) -> None:
        stop = threading.Event()
        if not wait_matching(self.pub, timeout, stop) or not self.path.wait(timeout):
            raise RuntimeError("the node did not come up")
        self.subs.pop().undeclare()  # the periodic reference path is not what is measured

    def run(self, payloads: list[bytes], mode: str, rate: float) -> dict[str, float]:
        self.recv_ns, self.stamps = [], []
        n = len(payloads)
        send = np.zeros(n, dtype=np.int64)
        put, clock = self.pub.put, time.perf_counter_ns
        t0 = clock()
        for i, p in enumerate(payloads):
            if mode == "ping-pong":
                self.got.clear()
                send[i] = clock()
                put(p)
                if not self.got.wait(2.0):
                    break
                continue
            if mode == "paced":
                delay = (t0 + i * 1e9 / rate - clock()) * 1e-9
                if delay > 0:
                    time.sleep(delay)
            send[i] = clock()
            put(p)
        deadline = time.monotonic() + 30
        while (len(self.recv_ns) < n or len(self.stamps) < n) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
        recv = np.asarray(self.recv_ns[:n], dtype=np.int64)
        lat_ms = (recv - send[: len(recv)]) / 1e6
        in_order = self.stamps == list(range(n))
        span_s = (recv[-1] - send[0]) / 1e9 if len(recv) else float("nan")
        pct = np.percentile(lat_ms, [50, 99])
        return {
            "received": len(recv),
            "in_order": float(in_order),
            "p50_ms": float(pct[0]),
            "p99_ms": float(pct[1]),
            "max_ms": float(lat_ms.max()),
            "rate": len(recv) / span_s,
        }

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.pub.undeclare()
        self.session.close()


def bench_size(n_ref: int, args: argparse.Namespace, tmp: Path) -> dict[str, list[dict]]:
    ref = tmp / f"ref_{n_ref}.tum"
    t = time.perf_counter()
    write_reference(ref, n_ref)
    print(f"\nreference {n_ref:,} samples (written in {time.perf_counter() - t:.1f} s)")
    port = free_port()
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
        "--path-period",
        "1",
    ] + (["--no-express"] if args.node_batching else [])
    node = subprocess.Popen(
        cmd,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    results: dict[str, list[dict]] = {"ping-pong": [], "paced": [], "flood": []}
    bench = None
    try:
        t = time.perf_counter()
        bench = Bench(port, args.express)
        bench.ready()
        print(f"  node ready in {time.perf_counter() - t:.1f} s")
        payloads = queries(args.poses, args.random_poses)
        bench.run(payloads[:500], "ping-pong", 0)  # warm-up
        for r in range(args.repeats):
            for mode in results:
                res = bench.run(payloads, mode, args.rate)
                results[mode].append(res)
                print(
                    f"  [{r + 1}/{args.repeats}] {mode:9s} received {res['received']:6d}/"
                    f"{args.poses} in order {bool(res['in_order'])!s:5s} p50 {res['p50_ms']:.3f} "
                    f"ms p99 {res['p99_ms']:.3f} ms max {res['max_ms']:.1f} ms "
                    f"{res['rate']:8.0f} poses/s"
                )
    finally:
        if bench is not None:
            bench.close()
        node.terminate()
        out, _ = node.communicate(timeout=30)
    stats = [json.loads(s[6:]) for s in out.splitlines() if s.startswith("stats ")]
    if stats:
        st = stats[-1]
        print(
            f"  node: processed {st['processed']}, dropped {st['dropped'] or 0}, processing "
            f"(receive → last publish) p50 {st['proc_p50_us']:.0f} us p99 "
            f"{st['proc_p99_us']:.0f} us over the last 10,000"
        )
    return results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1_000, 1_000_000])
    ap.add_argument("--poses", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rate", type=float, default=GOAL_RATE, help="paced mode rate (poses/s)")
    ap.add_argument(
        "--express",
        action="store_true",
        help="zenoh express on this (the robot's) side too (the node's default: on)",
    )
    ap.add_argument(
        "--node-batching",
        action="store_true",
        help="run the node with --no-express (zenoh batches its outputs)",
    )
    ap.add_argument(
        "--random-poses",
        action="store_true",
        help="query poses anywhere near the loop (default: a drive along it)",
    )
    args = ap.parse_args()
    print(
        f"bench_stream: {args.poses:,} poses x {args.repeats} repeats, paced at "
        f"{args.rate:.0f}/s, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}"
    )
    summary = {}
    with tempfile.TemporaryDirectory() as d:
        for n in args.sizes:
            summary[n] = bench_size(n, args, Path(d))
    print("\nsummary (medians over repeats)")
    print(
        f"{'reference':>10} {'mode':>9} {'p50 ms':>8} {'p99 ms':>8} {'poses/s':>9} "
        f"{'lost':>5} {'p99 vs 2 ms':>11} {'rate vs 2000/s':>14}"
    )
    for n, res in summary.items():
        for mode, runs in res.items():
            med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            lost = max(args.poses - r["received"] for r in runs)
            ok_order = all(r["in_order"] for r in runs)
            print(
                f"{n:>10,} {mode:>9} {med['p50_ms']:8.3f} {med['p99_ms']:8.3f} "
                f"{med['rate']:9.0f} {lost:5d} {GOAL_P99_MS / med['p99_ms']:10.2f}x "
                f"{med['rate'] / GOAL_RATE:13.2f}x" + ("" if ok_order else "  OUT OF ORDER")
            )
    print("(p99 vs goal: > 1x meets p99 < 2 ms; rate vs goal: flood > 1x meets >= 2000 poses/s)")


if __name__ == "__main__":
    main()
