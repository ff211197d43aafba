"""Counters of a live node: rate, processing latency, drops by reason, with rate-limited logs."""

from __future__ import annotations

import logging
import sys
import time
from collections import Counter, deque
from typing import Any

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger("tagtrail.stream")
OUTLIER_NS = 10 * 1_000_000_000  # a stamp this far from both neighbours, which agree: an outlier


class StampOrder:
    """Out-of-order and outlier stamps of one stream, judged against the neighbours.

    A stamp earlier than the one before it is out of order (counted once; the next is compared
    with it, not with the largest stamp ever seen). A lone stamp more than :data:`OUTLIER_NS`
    from both its neighbours while they agree (far future, far past, zero) is an outlier:
    counted once as such, and left out, so it poisons neither the out-of-order count nor the
    stamps after it. The judgement of a stamp waits for the next one (``pending``); the last
    stamp of a stream is judged on its predecessor alone.
    """

    def __init__(self) -> None:
        self.outliers = 0
        self._out_of_order = 0
        self._prev: list[int] = []  # the last two stamps kept; the newest not judged yet
        self._first = True  # the first stamp has no predecessor: judged on its two successors

    def note(self, t_ns: int) -> None:
        prev = self._prev
        if len(prev) == 2:
            a, b = prev
            if self._first and _far(a, b) and _far(a, t_ns) and not _far(b, t_ns):
                self.outliers += 1  # the very first stamp was the lone one
                prev[:] = [b]
            elif _far(b, a) and _far(b, t_ns) and not _far(a, t_ns):
                self.outliers += 1
                prev[:] = [a]
            else:
                self._out_of_order += b < a
                prev[:] = [b]
            self._first = False
        prev.append(int(t_ns))

    @property
    def out_of_order(self) -> int:
        """Stamps earlier than the one before (the newest judged on its predecessor alone)."""
        p = self._prev
        return self._out_of_order + (len(p) == 2 and p[1] < p[0])


def _far(a: int, b: int) -> bool:
    return abs(a - b) > OUTLIER_NS


def lone_outliers(t_ns: NDArray[np.int64]) -> NDArray[np.bool_]:
    """:class:`StampOrder`'s outliers of a whole sequence ``t_ns (N,)`` at once: stamps more
    than :data:`OUTLIER_NS` from both neighbours while these agree (the first and the last
    stamp: from the two next to them)."""
    t = np.asarray(t_ns, dtype=np.float64)  # int64 differences of such stamps overflow
    n = len(t)
    out = np.zeros(n, dtype=bool)
    if n < 3:
        return out

    def far(i: Any, j: Any) -> Any:
        return np.abs(t[i] - t[j]) > OUTLIER_NS

    i = np.arange(1, n - 1)
    out[1:-1] = far(i, i - 1) & far(i, i + 1) & ~far(i - 1, i + 1)
    out[0] = far(0, 1) and far(0, 2) and not far(1, 2)
    out[-1] = far(n - 1, n - 2) and far(n - 1, n - 3) and not far(n - 2, n - 3)
    return out


class DropError(Exception):
    """A message the node drops: ``reason`` is a short counter name (malformed, non_finite, …)."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(detail or reason)
        self.reason = reason


class Deferred(Exception):
    """A message kept to be handled later (e.g. a detection waiting for the first CameraInfo):
    received, neither processed nor dropped yet; its handler counts it when it is."""


class Stats:
    """What a node did: messages received/processed, drops by reason, latency of the last ones.

    ``drop()`` logs the first drop of each reason at once and then at most one line per reason
    every ``log_every_s`` (with the count since), so a flood of bad input cannot flood the log.
    """

    def __init__(self, name: str, log_every_s: float = 5.0, window: int = 10_000) -> None:
        self.name = name
        self.received = 0
        self.processed = 0
        self.order = StampOrder()
        self.dropped: Counter[str] = Counter()
        self.proc_ns: deque[int] = deque(maxlen=window)
        self.age_ns: deque[int] = deque(maxlen=window)
        self._log_every = log_every_s
        self._last_log: dict[str, float] = {}
        self._since: Counter[str] = Counter()
        self._t0 = self._t_last = time.monotonic()
        self._n_last = 0

    @property
    def out_of_order(self) -> int:
        return self.order.out_of_order

    def stamp(self, sec: int, nanosec: int) -> None:
        """Note a message stamp (:class:`StampOrder`: out of order, outliers; the message is
        processed all the same). Stamps within a minute of this machine's clock also give the
        message's age (end-to-end latency when the clocks are synchronised)."""
        t_ns = sec * 1_000_000_000 + nanosec
        age = time.time_ns() - t_ns
        if 0 <= age < 60_000_000_000:
            self.age_ns.append(age)
        self.order.note(t_ns)

    def drop(self, reason: str, detail: str = "") -> None:
        self.dropped[reason] += 1
        self._since[reason] += 1
        now = time.monotonic()
        if now - self._last_log.get(reason, -1e18) >= self._log_every:
            n = self._since.pop(reason)
            log.warning(
                "%s: dropped %d message(s) (%s)%s",
                self.name,
                n,
                reason,
                f": {detail}" if detail else "",
            )
            self._last_log[reason] = now

    def done(self, t_recv_ns: int) -> None:
        """One message processed; ``t_recv_ns`` = its ``perf_counter_ns`` at reception."""
        self.processed += 1
        self.proc_ns.append(time.perf_counter_ns() - t_recv_ns)

    def line(self) -> str:
        """``name: 2003.1 msg/s, proc p50 41 µs p99 97 µs, processed N, dropped K (…)``."""
        now = time.monotonic()
        rate = (self.processed - self._n_last) / max(now - self._t_last, 1e-9)
        self._t_last, self._n_last = now, self.processed
        lat = np.asarray(self.proc_ns, dtype=np.float64) / 1e3
        p = (
            f"proc p50 {np.percentile(lat, 50):.0f} us p99 {np.percentile(lat, 99):.0f} us"
            if lat.size
            else "proc -"
        )
        if self.age_ns:
            age = np.asarray(self.age_ns, dtype=np.float64) / 1e6
            p += f", age p50 {np.percentile(age, 50):.1f} ms p99 {np.percentile(age, 99):.1f} ms"
        drops = sum(self.dropped.values())
        why = ", ".join(f"{k} {v}" for k, v in sorted(self.dropped.items()))
        why = f" ({why})" if why else ""
        return (
            f"{self.name}: {rate:.1f} msg/s, {p}, received {self.received}, processed "
            f"{self.processed}, dropped {drops}{why}, out of order {self.out_of_order}"
            + (f", stamp outliers {self.order.outliers}" if self.order.outliers else "")
        )

    def summary(self) -> dict[str, object]:
        """Machine-readable totals (printed as JSON by the nodes when they stop)."""
        lat = np.asarray(self.proc_ns, dtype=np.float64) / 1e3
        return {
            "node": self.name,
            "received": self.received,
            "processed": self.processed,
            "dropped": dict(self.dropped),
            "out_of_order": self.out_of_order,
            "stamp_outliers": self.order.outliers,
            "elapsed_s": round(time.monotonic() - self._t0, 3),
            "proc_p50_us": float(np.percentile(lat, 50)) if lat.size else None,
            "proc_p99_us": float(np.percentile(lat, 99)) if lat.size else None,
        }


def say(line: str) -> None:
    """Print one line to stdout in one write: ``print`` writes the text and its newline apart
    when stdout is unbuffered (``PYTHONUNBUFFERED``), and nodes started together in one
    terminal (``&``) then run each other's lines together ("relocalize: readyrelocalization/
    state: ...")."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()
