"""The zenoh driver shared by the live nodes: subscribe → handle → publish, safely.

A handler is a plain function ``handler(payload: bytes) -> [(key, payload), ...]`` that knows
nothing of zenoh (so the same code runs on bag messages and in tests). :class:`Node` calls it
from the subscriber's callback under a lock (messages are handled one at a time, in arrival
order), publishes what it returns, and turns every failure into a counted, rate-limited drop:
:class:`~tagtrail.stream.stats.DropError` for bad input, anything else as ``error``. The main
thread only waits (for SIGINT/SIGTERM, ``--duration``, ``--count``), runs periodic tasks and logs
a stats line; on the way out every entity is undeclared and the session closed.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from tagtrail.stream.session import close_all
from tagtrail.stream.stats import DropError, Stats

log = logging.getLogger("tagtrail.stream")
Handler = Callable[[bytes], Iterable[tuple[str, bytes]]]
Payload = bytes | zenoh.ZBytes
CONGESTION = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}


class Node:
    """Publishers, subscribers, queryables and periodic tasks of one live node (see module doc)."""

    def __init__(self, session: zenoh.Session, stats: Stats, congestion: str = "block",
                 express: bool = False) -> None:  # fmt: skip
        self.session = session
        self.stats = stats
        self.stop = threading.Event()
        self.count: int | None = None
        self._cc = CONGESTION[congestion]
        self._express = express
        self._entities: list[Any] = []
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._bg: dict[str, zenoh.Publisher] = {}
        self._periodic: list[list[Any]] = []  # [period_s, fn, next_due]
        self._lock = threading.Lock()
        self._closed = False

    def publisher(self, key: str, background: bool = False) -> zenoh.Publisher:
        """The publisher of ``key`` (declared once); ``background``: a second, low-priority one
        for bulk data (the reference path) so that it never delays the per-pose outputs."""
        pubs = self._bg if background else self._pubs
        if key not in pubs:
            # a periodic republish may be dropped (the next one follows); it must never block
            cc = zenoh.CongestionControl.DROP if background else self._cc
            pub = self.session.declare_publisher(
                key, congestion_control=cc, express=self._express and not background,
                priority=zenoh.Priority.DATA_LOW if background else zenoh.Priority.DATA,
            )  # fmt: skip
            self._entities.append(pub)
            pubs[key] = pub
        return pubs[key]

    def publish(self, outputs: Iterable[tuple[str, Payload]], background: bool = False) -> None:
        pubs = self._bg if background else self._pubs
        for key, payload in outputs:
            pub = pubs.get(key) or self.publisher(key, background)
            pub.put(payload)

    def subscribe(self, key: str, handler: Handler, latest_only: bool = False) -> None:
        """Handle every sample of ``key`` with ``handler`` and publish its outputs.

        ``latest_only`` (slow handlers, e.g. image detection): samples are handled on a worker
        thread, and a sample still waiting when a newer one arrives is skipped (counted as
        ``skipped``), so latency never builds up.
        """
        if not latest_only:

            def callback(sample: zenoh.Sample) -> None:
                self._handle(key, handler, sample, time.perf_counter_ns())

            self._entities.append(self.session.declare_subscriber(key, callback))
            return
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
        self._entities.append(self.session.declare_subscriber(key, enqueue))

    def _handle(self, key: str, handler: Handler, sample: zenoh.Sample, t_recv: int) -> None:
        stats = self.stats
        with self._lock:
            if self._closed:
                return
            stats.received += 1
            try:
                if sample.kind != zenoh.SampleKind.PUT:
                    raise DropError("delete", f"{key}: a DELETE sample")
                self.publish(handler(sample.payload.to_bytes()))
                stats.done(t_recv)
            except DropError as err:
                stats.drop(err.reason, f"{key}: {err}")
            except Exception as err:  # noqa: BLE001 - a bad message must never stop the node
                stats.drop("error", f"{key}: {type(err).__name__}: {err}")
            if self.count is not None and stats.received >= self.count:
                self.stop.set()

    def queryable(self, key: str, payload: Callable[[], Payload]) -> None:
        """Answer ``get`` on ``key`` with ``payload()`` (late joiners fetch the reference path)."""

        def on_query(query: zenoh.Query) -> None:
            try:
                query.reply(key, payload())
            except Exception as err:  # noqa: BLE001
                log.warning("query on %s: %s", key, err)

        self._entities.append(self.session.declare_queryable(key, on_query))

    def every(self, period_s: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` now and then every ``period_s`` from the main loop (0: only now)."""
        fn()
        if period_s > 0:
            self._periodic.append([period_s, fn, time.monotonic() + period_s])

    def run(self, duration_s: float | None = None, stats_period_s: float = 10.0,
            stop: threading.Event | None = None) -> dict[str, Any]:  # fmt: skip
        """Serve until ``stop``/``self.stop`` is set or ``duration_s`` passes; then close.

        Returns the stats summary (also printed on stdout as one ``stats {json}`` line).
        """
        t_end = None if duration_s is None else time.monotonic() + duration_s
        t_stats = time.monotonic() + stats_period_s
        try:
            print(f"{self.stats.name}: ready", flush=True)
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
                self.stop.wait(0.05)
        finally:
            self.close()
        summary = self.stats.summary()
        print("stats " + json.dumps(summary), flush=True)
        return summary

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        # wait for a callback half-way through its publishing, but not for ever: a put blocked
        # by a congested link (congestion "block") must not keep the node from stopping
        locked = self._lock.acquire(timeout=2.0)
        try:
            self._closed = True
            close_all(self.session, self._entities)
            self._entities = []
        finally:
            if locked:
                self._lock.release()
