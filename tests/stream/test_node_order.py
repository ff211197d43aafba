"""The node's ordered subscriptions: a sample that finds the node idle is handled at once on the
thread zenoh delivered it on (no hand-over to a worker: ~60 us a hop at p50, up to ~2 ms at p99
on a busy machine); samples that arrive while one is handled wait, and are handled one at a
time in their order of arrival across keys."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh

from tagtrail.stream.node import Node
from tagtrail.stream.session import make_config
from tagtrail.stream.stats import Stats
from tests.stream.helpers import free_port, loopback


def test_an_idle_node_handles_on_the_delivering_thread_and_a_busy_one_keeps_the_order() -> None:
    port = free_port()
    a = zenoh.open(make_config("peer", listen=[loopback(port)]))
    b = zenoh.open(make_config("peer", connect=[loopback(port)]))
    c = zenoh.open(make_config("peer", connect=[loopback(port)]))  # a second link
    node = Node(a, Stats("t"))
    handled: list[tuple[str, int]] = []  # (thread name, sample)
    running = [0, 0]  # handlers running now, most at once

    def handler(data: bytes) -> list[tuple[str, bytes]]:
        running[0] += 1
        running[1] = max(running)
        if data[0] == 0:
            time.sleep(0.3)  # the second link's samples arrive meanwhile
        handled.append((threading.current_thread().name, data[0]))
        running[0] -= 1
        return []

    def wait_for(n: int) -> None:
        deadline = time.monotonic() + 5.0
        while len(handled) < n and time.monotonic() < deadline:
            time.sleep(0.01)

    for key in ("x", "y"):
        node.subscribe(key, handler)
    try:
        time.sleep(0.3)
        pb = b.declare_publisher("x")
        pc = {k: c.declare_publisher(k) for k in ("x", "y")}
        time.sleep(0.3)
        pb.put(bytes([0]))  # handled at once, 0.3 s long
        time.sleep(0.1)
        for i in range(1, 11):  # arrive while 0 is handled, on another link, across keys
            pc["x" if i % 2 else "y"].put(bytes([i]))
        wait_for(11)
        time.sleep(0.2)
        pb.put(bytes([11]))  # the node is idle again
        wait_for(12)
    finally:
        node.close()
        for s in (b, c):
            s.close()  # type: ignore[no-untyped-call]
    assert [i for _, i in handled] == list(range(12))  # arrival order, across keys
    assert running[1] == 1  # one at a time
    threads = [name for name, _ in handled]
    assert threads[0] != "handle" and threads[11] != "handle"  # zenoh's thread: no hand-over
    assert set(threads[1:11]) == {"handle"}  # those that waited: the node's worker, in order
    assert node.stats.received == 12 and not node.stats.dropped


@pytest.mark.parametrize(("listener", "connector"), [(True, True), (True, False), (False, True)])
def test_a_low_latency_link_delivers_every_sample_in_order(listener: bool, connector: bool) -> None:
    """``--low-latency`` on one end or both (zenoh uses the low-latency transport only when both
    ask for it): a node's samples, the small ones of a controller's chain, all arrive in order."""
    port = free_port()
    a = zenoh.open(make_config("peer", listen=[loopback(port)], low_latency=listener))
    b = zenoh.open(make_config("peer", connect=[loopback(port)], low_latency=connector))
    got: list[bytes] = []
    sub = a.declare_subscriber("x", lambda s: got.append(bytes(s.payload.to_bytes())))
    try:
        time.sleep(0.3)
        pub = b.declare_publisher("x", express=True)
        time.sleep(0.3)
        sent = [i.to_bytes(2, "little") * 100 for i in range(200)]  # 200-byte samples
        for payload in sent:
            pub.put(payload)
        deadline = time.monotonic() + 5.0
        while len(got) < len(sent) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert got == sent
    finally:
        sub.undeclare()  # type: ignore[no-untyped-call]
        for s in (b, a):
            s.close()  # type: ignore[no-untyped-call]
