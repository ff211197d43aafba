"""Garbage collected between messages (:func:`tagtrail.stream.node.collections_between_messages`,
:func:`~tagtrail.stream.node.collect_due`): while a node serves, no collection starts in the
middle of a message's handling, and the garbage is still collected, after the outputs."""

from __future__ import annotations

import gc
import threading
import time
import weakref

import zenoh

from tagtrail.stream.node import Node, collect_due, collections_between_messages
from tagtrail.stream.session import make_config
from tagtrail.stream.stats import Stats
from tests.stream.helpers import free_port, loopback


class _Cycle:
    """An object in a reference cycle: only the collector frees it."""

    def __init__(self) -> None:
        self.me = self


def _cycles(n: int) -> list[weakref.ref[_Cycle]]:
    """``n`` unreachable cycles, watched."""
    out = []
    for _ in range(n):
        c = _Cycle()
        out.append(weakref.ref(c))
    return out


def test_collections_wait_for_collect_due_and_come_back_after() -> None:
    assert gc.isenabled()
    with collections_between_messages():
        assert not gc.isenabled() and gc.get_freeze_count() > 0  # the start-up, frozen
        with collections_between_messages():  # nested (nodes in one process)
            assert not gc.isenabled()
        assert not gc.isenabled()  # the outer one still holds
        limit = gc.get_threshold()[0]
        collect_due()  # nothing due yet: the cycles stay
        watched = _cycles(2 * limit)  # > the threshold: no automatic collection frees them
        assert any(w() is not None for w in watched)
        collect_due(slack=1000)  # not due at that slack
        assert any(w() is not None for w in watched)
        collect_due()
        assert all(w() is None for w in watched)
    assert gc.isenabled() and gc.get_freeze_count() == 0


def test_a_serving_node_collects_its_garbage_after_the_outputs() -> None:
    port = free_port()
    a = zenoh.open(make_config("peer", listen=[loopback(port)]))
    b = zenoh.open(make_config("peer", connect=[loopback(port)]))
    node = Node(a, Stats("t"))
    watched: list[weakref.ref[_Cycle]] = []
    enabled: list[bool] = []
    got: list[bytes] = []

    def handler(data: bytes) -> list[tuple[str, bytes]]:
        enabled.append(gc.isenabled())
        watched.extend(_cycles(gc.get_threshold()[0] + 10))  # due after this message
        return [("out", data)]

    node.subscribe("in", handler)
    sub = b.declare_subscriber("out", lambda s: got.append(s.payload.to_bytes()))
    runner = threading.Thread(target=node.run, kwargs={"stats_period_s": 0})
    runner.start()
    try:
        time.sleep(0.3)
        pub = b.declare_publisher("in")
        for i in range(3):
            pub.put(bytes([i]))
            time.sleep(0.05)
        deadline = time.monotonic() + 3.0
        while len(got) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(got) == 3
        assert enabled == [False] * 3  # no automatic collection inside a handler
        while any(w() is not None for w in watched) and time.monotonic() < deadline:
            time.sleep(0.01)  # (the last message's: once its output is out)
        assert all(w() is None for w in watched)  # collected between the messages
    finally:
        node.stop.set()
        runner.join(5.0)
        sub.undeclare()  # type: ignore[no-untyped-call]
        b.close()  # type: ignore[no-untyped-call]
    assert gc.isenabled()
