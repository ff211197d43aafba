"""The zenoh driver shared by the live nodes: subscribe → handle → publish, safely.

A handler is a plain function ``handler(payload: bytes) -> [(key, payload), ...]`` that knows
nothing of zenoh (so the same code runs on bag messages and in tests). :class:`Node` calls it
under a lock (messages are handled one at a time, in arrival order across keys: on the thread
zenoh delivers a sample on when the node is idle, else on the node's worker once the samples
before it are done), publishes what it returns, and turns every failure into a counted,
rate-limited drop:
:class:`~tagtrail.stream.stats.DropError` for bad input, anything else as ``error``. The main
thread only waits (for SIGINT/SIGTERM, ``--duration``, ``--count``), runs periodic tasks and logs
a stats line; on the way out every entity is undeclared and the session closed, within a
bounded time (:meth:`Node.close`) even under a flood or a congested link.

Keys are ROS topic names without the leading ``/``; the node's
:class:`~tagtrail.stream.wire.Wire` (``bridge`` unless given) turns each into its zenoh key,
with the message type of ``Node.types[key]`` (rmw_zenoh keys, attachments and tokens need it).
"""

from __future__ import annotations

import gc
import json
import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any

import zenoh

from tagtrail.stream.session import close_all
from tagtrail.stream.stats import Deferred, DropError, Stats, say
from tagtrail.stream.wire import RmwPublisher, Wire

log = logging.getLogger("tagtrail.stream")
Handler = Callable[[bytes], Iterable[tuple[str, bytes]]]
Payload = bytes | zenoh.ZBytes
QUEUE_MAX = 1000  # samples waiting for the ordered worker; more: the receiving thread waits
AFTER_S = 0.002
"""The after-work (:attr:`Node.after`, the garbage) waits this long after a message's outputs
for the downstream's turn: in the closed loop (bench/FOLLOW.md) relocalize and follow answered
a pose in ~0.8 ms at p50 and 1.4 ms at p90. Run at once, localize's hand-over of its window's
re-solve (~0.5 ms) and a node's collection (~1 ms) took their CPU on 2 cores: detections ->
Twist with --smooth, p99 median 7.9 ms against 7.0 deferred (6 runs each, alternated)."""
AFTER_MAX_S = 0.006
"""A pending after-work is put off at most this long by messages still being handled when it
falls due: a message that ends later runs it at once, as does one with others queued behind it
(a flood). Before this bound a message that came within ``after_s`` of the last (the
simulator's ``camera_info``, then its frame) ran it at once after its outputs, on nearly every
frame."""
CONGESTION = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}


def peak_rss_mb() -> float | None:
    """This process's peak resident memory (MiB; None where it cannot be read): Linux's
    ``VmHWM``, the high-water mark of this process's own memory. Not ``ru_maxrss``: Linux
    carries the parent's peak across fork and exec into it, so a node started by a large
    process (a test runner) would report that process's memory."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024, 1)  # kB
    except (OSError, ValueError):
        pass
    try:
        import resource
    except ImportError:
        return None
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return round(kib / (1 << 20 if sys.platform == "darwin" else 1024), 1)


_gc_lock = threading.Lock()
_gc_holders = 0


@contextmanager
def collections_between_messages() -> Iterator[None]:
    """Python's automatic garbage collection off while a node serves; :func:`collect_due`
    runs what it would have run, between messages. Automatic, a collection starts at whichever
    allocation crosses a threshold, often in the middle of a message's handling: a young
    generation's took ~1 ms (~25 times in 30 s of a closed loop, in each node), the whole
    heap's 40-65 ms. What the start-up built (imports, the map, the message types) is frozen
    first (``gc.freeze``: never scanned again), so the collections left are small. Nests
    (nodes in one process, as in tests): the last to leave turns it back on."""
    global _gc_holders
    with _gc_lock:
        if _gc_holders == 0:
            gc.collect()
            gc.freeze()
            gc.disable()
        _gc_holders += 1
    try:
        yield
    finally:
        with _gc_lock:
            _gc_holders -= 1
            if _gc_holders == 0:
                gc.unfreeze()
                gc.enable()


def collect_due(slack: int = 1) -> None:
    """The collection Python's own thresholds call for now, if any, while
    :func:`collections_between_messages` holds them off: once the allocations exceed ``slack``
    times the youngest generation's threshold, the oldest generation whose count exceeds its
    threshold (as the interpreter's own ``gc_collect_generations``)."""
    if gc.isenabled():
        return
    counts, limits = gc.get_count(), gc.get_threshold()
    if limits[0] <= 0 or counts[0] <= limits[0] * slack:
        return  # (a threshold of 0: collection turned off by the user)
    gen = next(g for g in (2, 1, 0) if g == 0 or counts[g] > limits[g])
    gc.collect(gen)


class Node:
    """Publishers, subscribers, queryables and periodic tasks of one live node (see module doc)."""

    def __init__(
        self,
        session: zenoh.Session,
        stats: Stats,
        congestion: str = "block",
        express: bool = False,
        wire: Wire | None = None,
    ) -> None:
        self.session = session
        self.stats = stats
        self.wire = wire if wire is not None else Wire(session)
        self.types: dict[str, str] = {}  # key → ROS message type (or "json")
        self.stop = threading.Event()
        self.count: int | None = None
        self._cc = CONGESTION[congestion]
        self._express = express
        self._entities: list[Any] = []
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._bg: dict[str, zenoh.Publisher] = {}
        self._periodic: list[list[Any]] = []  # [period_s, fn, next_due]
        self._lock = threading.Lock()
        self._queue: deque[tuple[str, Handler, zenoh.Sample, int]] = deque()
        self._ready = threading.Condition()
        self._busy = False  # a sample of the ordered subscriptions is being handled
        self._worker: threading.Thread | None = None
        self._closed = False
        # the after-work: run under the handling lock after_s after a sample's outputs when
        # the node is idle then, else after_s after the outputs of the sample it is handling
        # (in a flood, or AFTER_MAX_S after it was asked for: at once after that sample): the
        # live smoother hands its window's re-solve to its background process then, after
        # the pose has left and the downstream nodes have had their turn
        self.after: list[Callable[[], bool | None]] = []
        self.after_s = AFTER_S
        self._due: float | None = None  # when the pending after-work runs (None: none)
        self._by = 0.0  # when a pending after-work no longer waits for an idle node
        self.clean = True  # False once a shutdown left a blocked put or an unclosed session

    def publisher(self, key: str, background: bool = False) -> zenoh.Publisher:
        """The publisher of ``key`` (declared once); ``background``: a second, low-priority one
        for bulk data (the reference path) so that it never delays the per-pose outputs."""
        pubs = self._bg if background else self._pubs
        if key not in pubs:
            # a periodic republish may be dropped (the next one follows); it must never block
            cc = zenoh.CongestionControl.DROP if background else self._cc
            pub = self.wire.declare_publisher(
                key,
                self.types.get(key),
                congestion_control=cc,
                express=self._express and not background,
                priority=zenoh.Priority.DATA_LOW if background else zenoh.Priority.DATA,
            )
            self._entities.append(pub)
            pubs[key] = pub
        return pubs[key]

    def publish(self, outputs: Iterable[tuple[str, Payload]], background: bool = False) -> None:
        pubs = self._bg if background else self._pubs
        for key, payload in outputs:
            if self._closed:  # shutting down: the rest of a result is not worth a blocked put
                return
            pub = pubs.get(key) or self.publisher(key, background)
            pub.put(payload)

    def subscribe(
        self, key: str, handler: Handler, latest_only: bool = False, msgtype: str | None = None
    ) -> None:
        """Handle every sample of ``key`` (of ``msgtype``, default ``types[key]``) with
        ``handler`` and publish its outputs.

        Samples of every key subscribed this way are handled one at a time, in their order of
        arrival across keys (a CameraInfo published before a detection is handled before it,
        as on the wire; zenoh-python's own per-subscriber threads would not keep that order:
        under a flood, many detections were handled before the first CameraInfo). A sample
        that finds the node idle is handled at once on zenoh's delivering thread: a hand-over
        to the worker cost each hop of a closed loop ~60 us at p50 and up to 2 ms at p99 (a
        thread to wake on a busy machine). Those that arrive while one is handled queue for
        the worker thread.

        ``latest_only`` (slow handlers, e.g. image detection): samples are handled on a worker
        thread of their own, and a sample still waiting when a newer one arrives is skipped
        (counted as ``skipped``), so latency never builds up.
        """
        msgtype = msgtype or self.types.get(key)
        if not latest_only:

            def callback(sample: zenoh.Sample) -> None:
                t_recv = time.perf_counter_ns()
                with self._ready:
                    here = not self._queue and not self._busy
                    if here:  # nothing waits or runs: handled on this (zenoh's) thread
                        self._busy = True
                    else:
                        while len(self._queue) >= QUEUE_MAX and not self._closed:
                            self._ready.wait(0.05)  # backpressure: the sender's link slows
                        self._queue.append((key, handler, sample, t_recv))
                        self._ready.notify_all()
                if here:
                    self._then_free(self._handle, key, handler, sample, t_recv)

            self._start_worker()
            self._entities.append(self.wire.declare_subscriber(key, msgtype, callback, True))
            return
        self._start_worker()  # (the after-work's)
        slot: list[Any] = []
        ready = threading.Condition()

        def enqueue(sample: zenoh.Sample) -> None:
            with ready:
                if slot:
                    self.stats.received += 1
                    self.stats.drop("skipped", f"{key}: busy, a newer sample replaces it")
                slot[:] = [sample, time.perf_counter_ns()]
                ready.notify()

        def worker() -> None:
            while not self._closed:
                with ready:
                    if not slot and not ready.wait(0.1):
                        continue
                    sample, t_recv = slot
                    slot.clear()
                self._handle(key, handler, sample, t_recv)

        threading.Thread(target=worker, name=f"handle {key}", daemon=True).start()
        self._entities.append(self.wire.declare_subscriber(key, msgtype, enqueue, True))

    def _start_worker(self) -> None:
        if self._worker is None:
            self._worker = threading.Thread(target=self._work, name="handle", daemon=True)
            self._worker.start()

    def _work(self) -> None:
        """The worker of the ordered subscriptions: the samples that arrived while another
        was handled, oldest first; and the after-work, once due with nothing to handle."""
        while not self._closed:
            with self._ready:
                item = None
                if self._queue and not self._busy:
                    item = self._queue.popleft()
                    self._busy = True
                    self._ready.notify_all()
                else:
                    due, now = self._due, time.monotonic()
                    if due is None or self._busy or self._queue or now < due:
                        wait = 0.1 if due is None or self._busy else min(0.1, due - now)
                        self._ready.wait(max(wait, 0.0))
                        continue
                    self._busy = True
            if item is None:
                self._then_free(self._after_work_locked)
            else:
                self._then_free(self._handle, *item)

    def _then_free(self, fn: Callable[..., None], *args: Any) -> None:
        """``fn(*args)`` by the thread that marked the node busy; then it is free again."""
        try:
            fn(*args)
        finally:
            with self._ready:
                self._busy = False
                self._ready.notify_all()

    def _after_work_locked(self) -> None:
        with self._lock:
            if not self._closed:
                self._after_work()

    def _after_work(self) -> None:
        """The after-hooks, then the garbage due (:func:`collect_due`); under the lock. A hook
        that returns True waits for something (the background's re-solve): the after-work
        runs again ``after_s`` later, message or not."""
        self._due = None
        again = False
        for fn in self.after:
            try:
                again = bool(fn()) or again
            except Exception as err:  # noqa: BLE001 - must never stop the node
                self.stats.drop("error", f"after: {type(err).__name__}: {err}")
        collect_due()  # the outputs are out: the messages' garbage, when due
        if again and not self._closed:
            self._ask_after(time.monotonic())

    def _ask_after(self, now: float) -> None:
        """Have the after-work run ``after_s`` from ``now`` (put off by at most AFTER_MAX_S)."""
        self._due, self._by = now + self.after_s, now + AFTER_MAX_S

    def _handle(self, key: str, handler: Handler, sample: zenoh.Sample, t_recv: int) -> None:
        stats = self.stats
        if self._closed:  # never queue up behind the lock while the node shuts down
            return
        with self._lock:
            if self._closed:
                return
            stats.received += 1
            try:
                if sample.kind != zenoh.SampleKind.PUT:
                    raise DropError("delete", f"{key}: a DELETE sample")
                self.publish(handler(sample.payload.to_bytes()))
                stats.done(t_recv)
            except Deferred:
                pass  # kept by the handler, counted when it is handled
            except DropError as err:
                stats.drop(err.reason, f"{key}: {err}")
            except Exception as err:  # noqa: BLE001 - a bad message must never stop the node
                if not self._closed:  # a put on a publisher undeclared by close() is no error
                    stats.drop("error", f"{key}: {type(err).__name__}: {err}")
            now = time.monotonic()
            if self._due is None:
                self._ask_after(now)
                with self._ready:
                    self._ready.notify_all()  # the ordered worker runs it
            elif now >= self._due:
                if self._queue or now >= self._by:
                    self._after_work()  # a flood: the after-work is never put off for long
                else:  # (one message after another: camera_info, then the frame)
                    self._due = now + self.after_s  # the downstream's turn after this one's
            if self.count is not None and stats.received >= self.count:
                self.stop.set()

    def queryable(self, key: str, payload: Callable[[], Payload]) -> None:
        """Answer ``get`` on ``key`` with ``payload()`` (late joiners fetch the reference path)."""

        def on_query(query: zenoh.Query) -> None:
            try:
                query.reply(zkey, payload())
            except Exception as err:  # noqa: BLE001
                log.warning("query on %s: %s", key, err)

        zkey = self.wire.key(key, self.types.get(key))
        self._entities.append(self.session.declare_queryable(zkey, on_query))

    def every(self, period_s: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` now and then every ``period_s`` from the main loop (0: only now)."""
        fn()
        if period_s > 0:
            self._periodic.append([period_s, fn, time.monotonic() + period_s])

    def run(
        self,
        duration_s: float | None = None,
        stats_period_s: float = 10.0,
        stop: threading.Event | None = None,
    ) -> dict[str, Any]:
        """Serve until ``stop``/``self.stop`` is set or ``duration_s`` passes; then close.

        Returns the stats summary (also printed on stdout as one ``stats {json}`` line) with
        ``shutdown_s`` (time to close), ``shutdown_clean`` (:meth:`close`) and ``peak_rss_mb``.
        """
        t_end = None if duration_s is None else time.monotonic() + duration_s
        try:
            with collections_between_messages():
                self._serve(t_end, stats_period_s, stop)
        finally:
            t_close = time.monotonic()
            self.close()
        summary = {
            **self.stats.summary(),
            **self.wire.summary(),
            "shutdown_s": round(time.monotonic() - t_close, 3),
            "shutdown_clean": self.clean,
            "peak_rss_mb": peak_rss_mb(),
        }
        say("stats " + json.dumps(summary))
        return summary

    def _serve(
        self, t_end: float | None, stats_period_s: float, stop: threading.Event | None
    ) -> None:
        """The main thread's loop of :meth:`run`: periodic tasks, stats lines, and the
        garbage of a node that runs timers without messages (:func:`collect_due`, at 4 times
        its threshold: the handler's collections come first)."""
        t_stats = time.monotonic() + stats_period_s
        say(f"{self.stats.name}: ready")
        while not self.stop.is_set() and not (stop is not None and stop.is_set()):
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                break
            for task in self._periodic:
                if now >= task[2]:
                    task[2] = now + task[0]
                    try:
                        task[1]()
                    except Exception as err:  # noqa: BLE001
                        log.warning("%s: periodic task failed: %s", self.stats.name, err)
            if stats_period_s > 0 and now >= t_stats:
                t_stats = now + stats_period_s
                log.info("%s", self.stats.line())
            collect_due(slack=4)
            self.stop.wait(0.05)

    def close(self, wait_s: float = 0.3) -> bool:
        """Stop and close, bounded (idempotent); True if nothing was left hanging.

        No new sample is handled; subscribers and queryables are undeclared first; a handler
        half-way through publishing gets ``wait_s`` to finish; then the publishers are undeclared
        and the session closed (:func:`close_all`, bounded too). The lock is never held across
        ``session.close()``: zenoh waits there for a callback that may be waiting for the lock
        (a 10 s stall under a flood).
        """
        self._closed = True
        outs = (zenoh.Publisher, RmwPublisher)
        inputs = [e for e in self._entities if not isinstance(e, outs)]
        close_all(None, inputs)
        idle = self._lock.acquire(timeout=wait_s)  # False: a put blocked by a congested link
        if idle:
            self._lock.release()
        outputs = [e for e in self._entities if isinstance(e, outs)]
        self._entities = []
        self.wire.close()
        closed = close_all(self.session, outputs, timeout_s=0.5 if idle else 0.1)
        self.clean = self.clean and idle and closed
        return self.clean
