"""Counters of a live node: rate, processing latency, drops by reason, with rate-limited logs."""

from __future__ import annotations

import logging
import time
from collections import Counter, deque

import numpy as np

log = logging.getLogger("tagtrail.stream")


class DropError(Exception):
    """A message the node drops: ``reason`` is a short counter name (malformed, non_finite, …)."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(detail or reason)
        self.reason = reason


class Stats:
    """What a node did: messages received/processed, drops by reason, latency of the last ones.

    ``drop()`` logs the first drop of each reason at once and then at most one line per reason
    every ``log_every_s`` (with the count since), so a flood of bad input cannot flood the log.
    """

    def __init__(self, name: str, log_every_s: float = 5.0, window: int = 10_000) -> None:
        self.name = name
        self.received = 0
        self.processed = 0
        self.out_of_order = 0
        self.dropped: Counter[str] = Counter()
        self.proc_ns: deque[int] = deque(maxlen=window)
        self.age_ns: deque[int] = deque(maxlen=window)
        self._log_every = log_every_s
        self._last_log: dict[str, float] = {}
        self._since: Counter[str] = Counter()
        self._t0 = self._t_last = time.monotonic()
        self._n_last = 0
        self._last_stamp = (-(2**62), 0)

    def stamp(self, sec: int, nanosec: int) -> None:
        """Note a message stamp; one older than the newest so far counts as out of order (it is
        processed all the same). Stamps within a minute of this machine's clock also give the
        message's age (end-to-end latency when the clocks are synchronised)."""
        age = time.time_ns() - (sec * 1_000_000_000 + nanosec)
        if 0 <= age < 60_000_000_000:
            self.age_ns.append(age)
        if (sec, nanosec) < self._last_stamp:
            self.out_of_order += 1
        else:
            self._last_stamp = (sec, nanosec)

    def drop(self, reason: str, detail: str = "") -> None:
        self.dropped[reason] += 1
        self._since[reason] += 1
        now = time.monotonic()
        if now - self._last_log.get(reason, -1e18) >= self._log_every:
            n = self._since.pop(reason)
            log.warning("%s: dropped %d message(s) (%s)%s", self.name, n, reason,
                        f": {detail}" if detail else "")  # fmt: skip
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
        p = (f"proc p50 {np.percentile(lat, 50):.0f} us p99 {np.percentile(lat, 99):.0f} us"
             if lat.size else "proc -")  # fmt: skip
        if self.age_ns:
            age = np.asarray(self.age_ns, dtype=np.float64) / 1e6
            p += f", age p50 {np.percentile(age, 50):.1f} ms p99 {np.percentile(age, 99):.1f} ms"
        drops = sum(self.dropped.values())
        why = ", ".join(f"{k} {v}" for k, v in sorted(self.dropped.items()))
        why = f" ({why})" if why else ""
        return (f"{self.name}: {rate:.1f} msg/s, {p}, received {self.received}, processed "
                f"{self.processed}, dropped {drops}{why}, out of order {self.out_of_order}")

    def summary(self) -> dict[str, object]:
        """Machine-readable totals (printed as JSON by the nodes when they stop)."""
        lat = np.asarray(self.proc_ns, dtype=np.float64) / 1e3
        return {
            "node": self.name,
            "received": self.received,
            "processed": self.processed,
            "dropped": dict(self.dropped),
            "out_of_order": self.out_of_order,
            "elapsed_s": round(time.monotonic() - self._t0, 3),
            "proc_p50_us": float(np.percentile(lat, 50)) if lat.size else None,
            "proc_p99_us": float(np.percentile(lat, 99)) if lat.size else None,
        }
