"""The node's work after a sample's outputs are out (:attr:`tagtrail.stream.node.Node.after`:
the live smoother's window re-solve): it runs after the outputs are published, on a thread of
lower priority, never beside a handler."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest
import zenoh

from tagtrail.stream.node import Node
from tagtrail.stream.session import make_config
from tagtrail.stream.stats import Stats
from tests.stream.helpers import free_port, loopback


def _nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


@pytest.mark.skipif(sys.platform != "linux", reason="per-thread priorities are Linux's")
def test_after_runs_once_the_outputs_are_out_at_a_lower_priority() -> None:
    port = free_port()
    a = zenoh.open(make_config("peer", listen=[loopback(port)]))
    b = zenoh.open(make_config("peer", connect=[loopback(port)]))
    node = Node(a, Stats("t"))
    got: list[bytes] = []
    sub = b.declare_subscriber("out", lambda s: got.append(s.payload.to_bytes()))
    busy = threading.Event()  # a handler is running
    seen: list[tuple[int, int, int, bool]] = []  # (outputs out, after's nice, handler's, overlap)
    handler_nice: list[int] = []

    def handler(data: bytes) -> list[tuple[str, bytes]]:
        busy.set()
        handler_nice.append(_nice())
        time.sleep(0.002)
        busy.clear()
        return [("out", data)]

    def after() -> None:
        time.sleep(0.01)  # got's sample has arrived by then if it was published first
        seen.append((len(got), _nice(), handler_nice[-1], busy.is_set()))

    node.after.append(after)
    node.subscribe("in", handler)
    try:
        time.sleep(0.3)
        pub = b.declare_publisher("in")
        for i in range(5):
            pub.put(bytes([i]))
            time.sleep(0.05)
        deadline = time.monotonic() + 3.0
        while len(seen) < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        node.close()
        sub.undeclare()  # type: ignore[no-untyped-call]
        b.close()  # type: ignore[no-untyped-call]
    assert len(seen) == 5 and len(got) == 5
    for k, (n_out, nice, h_nice, overlap) in enumerate(seen):
        assert n_out == k + 1  # this sample's output went out before
        assert nice > h_nice  # lowered
        assert not overlap
