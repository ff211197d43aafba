"""Helpers of the streaming tests: free loopback ports, node processes, a collecting subscriber.

Every session binds or connects to 127.0.0.1 only, scouting off. Every wait has a timeout and
node processes are killed in ``finally`` blocks (:func:`running`), so a test can fail but not hang.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import zenoh

from tagtrail.stream.session import make_config
from tests.cli_helpers import terminal_signals

REPO = Path(__file__).resolve().parents[2]
# Nodes run here, not in the repository: its pipeline.yaml (the demo's) would be their default
# --pipeline. No pipeline.yaml here, so they take the stages' defaults.
NODE_CWD = Path(__file__).resolve().parent


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def client_args(port: int) -> list[str]:
    """A node's options to connect, as a zenoh client, to the router on 127.0.0.1:``port``."""
    return ["--mode", "client", "--connect", loopback(port)]


class Proc:
    """A ``python -m tagtrail.stream.cli …`` child whose output lines are collected."""

    def __init__(self, args: Sequence[str]) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.p = subprocess.Popen(
            [sys.executable, "-m", "tagtrail.stream.cli", *map(str, args)],
            cwd=NODE_CWD,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            preexec_fn=terminal_signals,
        )
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.lines.append(line.rstrip("\n"))

    @property
    def output(self) -> str:
        return "\n".join(self.lines)

    def wait_for(self, text: str, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while not any(text in line for line in self.lines):
            if self.p.poll() is not None:
                self._t.join(2)
                if any(text in line for line in self.lines):
                    return
                raise AssertionError(f"process exited ({self.p.returncode}):\n{self.output}")
            if time.monotonic() > deadline:
                raise AssertionError(f"no {text!r} after {timeout} s:\n{self.output}")
            time.sleep(0.02)

    def stop(self, timeout: float = 15.0, sig: int = signal.SIGTERM) -> int:
        """``sig`` (SIGTERM or SIGINT), then wait for a clean exit (SIGKILL after ``timeout``)."""
        if self.p.poll() is None:
            self.p.send_signal(sig)
        try:
            rc = self.p.wait(timeout)
        except subprocess.TimeoutExpired:
            self.p.kill()
            self.p.wait(5)
            raise AssertionError(f"no clean exit after SIGTERM:\n{self.output}") from None
        self._t.join(5)
        return rc

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(5)

    def stats(self) -> dict[str, Any]:
        line = next(s for s in reversed(self.lines) if s.startswith("stats "))
        return json.loads(line[len("stats ") :])


@contextmanager
def running(*procs_args: Sequence[str]) -> Iterator[list[Proc]]:
    procs: list[Proc] = []
    try:
        for a in procs_args:
            procs.append(Proc(a))
        yield procs
    finally:
        for p in procs:
            p.kill()


class Collector:
    """A test session (connected to ``port``) that stores every sample of some keys."""

    def __init__(self, port: int, keys: Sequence[str]) -> None:
        self.session = zenoh.open(make_config("peer", connect=[loopback(port)]))
        self.samples: dict[str, list[bytes]] = defaultdict(list)
        self._lock = threading.Lock()
        self._subs = [self.session.declare_subscriber(k, self._cb) for k in keys]

    def _cb(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.samples[str(sample.key_expr)].append(sample.payload.to_bytes())

    def wait(self, key: str, n: int, timeout: float = 20.0) -> list[bytes]:
        deadline = time.monotonic() + timeout
        while len(self.samples[key]) < n:
            if time.monotonic() > deadline:
                raise AssertionError(f"{key}: {len(self.samples[key])} of {n} samples")
            time.sleep(0.01)
        with self._lock:
            return list(self.samples[key])

    def wait_until(
        self, key: str, done: Callable[[list[bytes]], bool], timeout: float = 20.0
    ) -> list[bytes]:
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                got = list(self.samples[key])
            if done(got):
                return got
            if time.monotonic() > deadline:
                raise AssertionError(f"{key}: condition not met with {len(got)} samples")
            time.sleep(0.02)

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()


def localize_replayed(
    node_args: Sequence[str | Path],
    recording: Path,
    port: int,
    n_poses: int,
    *,
    replay_timeout: float = 30.0,
    timeout: float = 20.0,
    sig: int = signal.SIGTERM,
) -> tuple[list[bytes], Proc]:
    """Run a ``stream localize`` node (``node_args``, listening on ``port``), replay the
    detections bag ``recording`` into it, collect ``n_poses`` ``tag_only_pose`` messages, stop
    the node with ``sig`` (asserting a clean exit) and return the poses and the stopped node."""
    with running([str(a) for a in node_args]) as (node,):
        node.wait_for("localize: ready")
        sub = Collector(port, ["tag_only_pose"])
        try:
            with running(
                [
                    "replay",
                    str(recording),
                    "--topics",
                    "/camera_info",
                    "/detections",
                    "--connect",
                    loopback(port),
                    "--rate",
                    "2",
                ]
            ) as (rep,):
                assert rep.p.wait(replay_timeout) == 0, rep.output
            poses = sub.wait("tag_only_pose", n_poses, timeout=timeout)
        finally:
            sub.close()
        assert node.stop(sig=sig) == 0, node.output
    return poses, node


def router(port: int) -> zenoh.Session:
    """A zenoh router on 127.0.0.1:``port`` only (no scouting): the bridge's stand-in."""
    return listening(port, "router")


def listening(port: int, mode: str) -> zenoh.Session:
    """A zenoh session in ``mode`` (router, peer) listening on 127.0.0.1:``port`` only, with
    scouting off and no endpoint to connect to: the others connect to it."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps([loopback(port)]))
    cfg.insert_json5("connect/endpoints", "[]")
    return zenoh.open(cfg)
