"""The node's work after a sample's outputs are out (:attr:`tagtrail.stream.node.Node.after`:
the live smoother hands its window's re-solve to its background process then), and that
process (:class:`tagtrail.stream.background.Background`)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zenoh

from tagtrail.stream.background import Background
from tagtrail.stream.node import AFTER_MAX_S, Node
from tagtrail.stream.session import make_config
from tagtrail.stream.stats import Stats
from tests.stream.helpers import free_port, loopback


def test_after_runs_once_the_outputs_are_out_and_the_node_was_idle_after_s() -> None:
    port = free_port()
    a = zenoh.open(make_config("peer", listen=[loopback(port)]))
    b = zenoh.open(make_config("peer", connect=[loopback(port)]))
    node = Node(a, Stats("t"))
    got: list[bytes] = []
    sub = b.declare_subscriber("out", lambda s: got.append(s.payload.to_bytes()))
    # (thread, outputs handed to zenoh, lock held, seconds since the last output)
    seen: list[tuple[str, int, bool, float]] = []
    published: list[float] = []
    publish = node.publish

    def counting(outputs: object, background: bool = False) -> None:
        for key, payload in outputs:  # type: ignore[attr-defined]
            publish([(key, payload)], background)
            published.append(time.monotonic())

    node.publish = counting  # type: ignore[method-assign]

    def handler(data: bytes) -> list[tuple[str, bytes]]:
        if data == b"\x02":
            raise ValueError("a bad sample")  # after runs all the same (nothing to hand over)
        return [("out", data)]

    def after() -> None:
        since = time.monotonic() - published[-1]
        seen.append((threading.current_thread().name, len(published), node._lock.locked(), since))
        if len(seen) == 4:
            raise RuntimeError("after failed")  # counted, the node goes on

    node.after.append(after)
    node.subscribe("in", handler)
    try:
        time.sleep(0.3)
        pub = b.declare_publisher("in")
        for i in range(5):
            pub.put(bytes([i]))
            time.sleep(0.05)
        deadline = time.monotonic() + 3.0
        while len(got) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        node.close()
        sub.undeclare()  # type: ignore[no-untyped-call]
        b.close()  # type: ignore[no-untyped-call]
    assert len(got) == 4 and len(seen) == 5
    assert [n for _, n, _, _ in seen] == [1, 2, 2, 3, 4]  # each after its sample's outputs
    assert all(locked for _, _, locked, _ in seen)  # no other sample is handled meanwhile
    assert {name for name, _, _, _ in seen} == {"handle"}  # the node's worker, not zenoh's
    assert all(since >= node.after_s for _, n, _, since in seen if n)  # the downstream's turn
    assert node.stats.dropped == {"error": 2}


def test_in_a_flood_the_after_work_still_runs_once_overdue() -> None:
    port = free_port()
    a = zenoh.open(make_config("peer", listen=[loopback(port)]))
    b = zenoh.open(make_config("peer", connect=[loopback(port)]))
    c = zenoh.open(make_config("peer", connect=[loopback(port)]))  # the flood's link
    node = Node(a, Stats("t"))
    handled: list[int] = []
    afters: list[int] = []  # samples handled when it ran

    def handler(data: bytes) -> list[tuple[str, bytes]]:
        time.sleep(0.3 if data == b"\xff" else 0.001)
        handled.append(data[0])
        return []

    node.after.append(lambda: afters.append(len(handled)))
    node.subscribe("in", handler)
    try:
        time.sleep(0.3)
        slow, flood = b.declare_publisher("in"), c.declare_publisher("in")
        time.sleep(0.3)
        slow.put(b"\xff")  # while it is handled, the flood queues up
        time.sleep(0.05)
        for i in range(200):
            flood.put(bytes([i]))
        deadline = time.monotonic() + 5.0
        while len(handled) < 201 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)
    finally:
        node.close()
        for s in (b, c):
            s.close()  # type: ignore[no-untyped-call]
    assert len(handled) == 201 and handled[1:] == list(range(200))
    assert afters[-1] == 201  # the last sample's, once idle
    # handled back to back from the queue (never idle): the after-work is overdue 2 ms on
    gaps = np.diff([0, *afters])
    assert len(afters) > 20 and gaps[1:].max() <= 2 * node.after_s / 0.001 + 2


def test_a_message_soon_after_another_puts_the_after_work_off_until_after_its_outputs() -> None:
    """``camera_info`` then its frame, as a camera driver sends them: the frame's handling ends
    past the after-work the first asked for. It still waits ``after_s`` after the frame's
    outputs (the downstream's turn) instead of running at once after them; and a stream that
    never leaves the node idle ``after_s`` (no backlog either) has it run every
    ``AFTER_MAX_S`` or so."""
    port = free_port()
    a = zenoh.open(make_config("peer", listen=[loopback(port)]))
    b = zenoh.open(make_config("peer", connect=[loopback(port)]))
    node = Node(a, Stats("t"))
    out: list[float] = []  # when each sample's output left
    afters: list[tuple[float, int]] = []  # (seconds since the last output, outputs so far)

    def handler(data: bytes) -> list[tuple[str, bytes]]:
        if data == b"frame":
            time.sleep(2 * node.after_s)  # ends past the after-work camera_info asked for
        elif data == b"tick":
            _spin(node.after_s)  # busy whenever the after-work falls due
        out.append(time.monotonic())  # (this handler's output is what the node publishes)
        return []

    node.after.append(lambda: afters.append((time.monotonic() - out[-1], len(out))))
    node.subscribe("in", handler)
    try:
        time.sleep(0.3)
        pub = b.declare_publisher("in")
        time.sleep(0.3)
        for _ in range(5):
            pub.put(b"camera_info")
            pub.put(b"frame")
            time.sleep(0.05)
        _until(lambda: len(afters) >= 5, 5.0)
        pairs = list(afters)
        afters.clear()
        t0 = time.monotonic()
        for i in range(80):  # a sample every 1.15 after_s: the node is never idle after_s
            pub.put(b"tick")
            _spin(t0 + (i + 1) * 1.15 * node.after_s - time.monotonic())
        _until(lambda: len(out) >= 90, 5.0)  # all handled (a slow machine lags behind)
        during = [n for _, n in afters if n <= 90]
    finally:
        node.close()
        b.close()  # type: ignore[no-untyped-call]
    assert len(pairs) == 5 and [n for _, n in pairs] == [2, 4, 6, 8, 10]  # after each frame
    assert all(since >= node.after_s for since, _ in pairs)  # not at once after its outputs
    # ~185 ms: every 4 ticks (~9 ms) past AFTER_MAX_S (19-21 seen); without the bound 1-2
    assert AFTER_MAX_S <= 0.01 and len(during) >= 8


def test_an_after_hook_that_waits_for_something_is_asked_again_without_a_message() -> None:
    """A hook that returns True (the smoother's re-solve still in the background) runs again
    ``after_s`` later with no message in between, until it returns False."""
    port = free_port()
    a = zenoh.open(make_config("peer", listen=[loopback(port)]))
    b = zenoh.open(make_config("peer", connect=[loopback(port)]))
    node = Node(a, Stats("t"))
    runs: list[float] = []

    def hook() -> bool:
        runs.append(time.monotonic())
        return len(runs) < 4

    node.after.append(hook)
    node.subscribe("in", lambda data: [])
    try:
        time.sleep(0.3)
        pub = b.declare_publisher("in")
        time.sleep(0.3)
        pub.put(b"x")
        _until(lambda: len(runs) >= 4, 5.0)
        time.sleep(0.05)
    finally:
        node.close()
        b.close()  # type: ignore[no-untyped-call]
    assert len(runs) == 4 and node.stats.received == 1  # one message, four runs, then none
    assert all(gap >= node.after_s for gap in np.diff(runs))


def _spin(seconds: float) -> None:
    """Busy for ``seconds`` (a sleep overshoots by ~0.1 ms)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


def _run(job: tuple[str, object]) -> object:
    """The test's jobs, by name (a worker runs one function)."""
    what, arg = job
    if what == "square":
        return arg * arg  # type: ignore[operator]
    if what == "policy":
        return os.getpid(), os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, 0)
    if what == "slow":
        time.sleep(arg)  # type: ignore[arg-type]
        return arg
    raise ValueError("no")


JOBS = "tests.stream.test_node_after:_run"


def _until(ok: object, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not ok() and time.monotonic() < deadline:  # type: ignore[operator]
        time.sleep(0.005)
    assert ok(), "timed out"  # type: ignore[operator]


def _wait(bg: Background, seq: int | None, timeout_s: float = 20.0) -> object:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ok, value = bg.result(seq)
        if ok:
            return value
        time.sleep(0.005)
    raise AssertionError("no result")


@pytest.mark.skipif(sys.platform != "linux", reason="SCHED_IDLE is Linux's")
def test_background_computes_in_a_process_of_the_lowest_priority() -> None:
    bg = Background(JOBS, "t")
    try:
        seq = bg.submit(("square", 7))
        assert seq is not None and _wait(bg, seq) == 49
        assert bg.result(seq) == (False, None)  # taken once
        pid, policy, nice = _wait(bg, bg.submit(("policy", None)))  # type: ignore[misc]
        assert pid != os.getpid() and (policy == os.SCHED_IDLE or nice == 19)
        slow = bg.submit(("slow", 0.3))
        assert bg.submit(("square", 2)) is None  # busy: refused (its owner computes it)
        assert bg.result(slow) == (False, None)  # not back yet: never waited for
        assert not bg.ready(slow)
        _until(lambda: bg.ready(slow))
        assert bg.ready(slow) and not bg.ready(None)  # asking takes nothing
        assert _wait(bg, slow) == 0.3
        failed = bg.submit(("fail", None))
        _until(bg.idle)
        assert bg.result(failed) == (False, None) and bg.counts["failed"] == 1
        assert _wait(bg, bg.submit(("square", 3))) == 9  # it goes on after a failure
        assert bg.counts["refused"] == 1 and bg.counts["used"] == 4
    finally:
        proc = bg._proc
        bg.close()
    assert proc is not None and proc.poll() is not None  # ended
    assert bg.submit(("square", 2)) is None  # nothing after close


def test_background_starts_before_its_first_job_and_sums_up_at_close(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """:meth:`Background.start` spawns the worker at once (its imports over before the first
    frame); closing says what the background did."""
    bg = Background(JOBS, "t")
    try:
        assert bg.start() and bg._proc is not None and bg._proc.poll() is None
        proc = bg._proc
        assert bg.start() and bg._proc is proc  # once
        assert _wait(bg, bg.submit(("square", 4))) == 16
    finally:
        with caplog.at_level("INFO", logger="tagtrail.stream"):
            bg.close()
    assert not bg.start()  # nothing after close
    assert "t: 1 jobs computed in the background, 1 of them back in time" in caplog.text


def test_background_child_leaves_with_its_parent() -> None:
    """The child's input is the parent's pipe: when the parent goes (its end closed, as by
    the parent's exit), the child leaves on its own."""
    bg = Background(JOBS, "t")
    assert _wait(bg, bg.submit(("square", 3))) == 9
    proc = bg._proc
    assert proc is not None and proc.stdin is not None and proc.stdout is not None
    proc.stdin.close()  # the parent's ends of both pipes, as at its exit
    proc.stdout.close()
    proc.wait(5.0)
    bg.close()


def test_background_close_does_not_raise_when_the_worker_is_slow_to_go(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """On a machine busy with other work a ``SCHED_IDLE`` worker gets no CPU, not even to die
    of the kill: the node's shutdown goes on (one line) instead of a traceback. Here the
    worker's waits time out as they did under two CPU-bound processes on 2 cores."""
    bg = Background(JOBS, "t")
    assert bg.start()
    proc = bg._proc
    assert proc is not None
    real_wait, calls = proc.wait, []

    def slow_wait(timeout: float | None = None) -> int:
        calls.append(timeout)
        raise subprocess.TimeoutExpired(proc.args, timeout or 0.0)

    proc.wait = slow_wait  # type: ignore[method-assign]
    with caplog.at_level("INFO", logger="tagtrail.stream"):
        bg.close()  # killed, then given up on: no exception
    assert len(calls) == 2 and "left to the system" in caplog.text
    assert real_wait(10.0) is not None  # the kill did its work
