"""A worker process that computes a node's background work at the lowest priority.

The live smoother answers each frame with the filter's step and re-solves its window after
the pose is out (~10 ms of CPU). On a thread of the node that work would share the GIL with
the handlers — a handler waits up to the interpreter's switch interval (5 ms) for it, or for
as long as the scheduler leaves a low-priority GIL holder off the CPU — and Linux's EEVDF
scheduler lets a niced thread finish its slice before the downstream nodes run (2-4 ms of
delay measured, bench/FOLLOW.md). A process of its own under ``SCHED_IDLE`` (preempted at once
by any other task that wakes) shares neither, and nothing it holds can hold a handler up: a
handler that needs a result not yet back computes it itself (:class:`Background` is only ever
asked, never waited for).

The process is :func:`tagtrail.pool.spawn_worker`'s (``python -m tagtrail.pool MODULE:FUNC``:
pickles over its stdin and stdout, no fork beside zenoh's threads, never a re-import of the
parent's main script), started with the first job; one job at a time (a job submitted while
one runs is refused: its owner computes it when needed). Its pipes hold 1 MiB, so a job (a
window: up to ~100 kB) and its result (~30 kB) are written whole, never waiting for the other
side. It ends when :meth:`Background.close` is called or its parent goes (its stdin closes).
"""

from __future__ import annotations

import logging
import os
import pickle
import select
import subprocess
import threading
from typing import Any

from tagtrail.pool import spawn_worker

log = logging.getLogger("tagtrail.stream")


def lowest_priority(pid: int = 0) -> str:
    """Put process (Linux: thread) ``pid`` (0: the caller) at the lowest scheduling priority:
    ``SCHED_IDLE``, which any other task that wakes up preempts at once; where that is refused,
    nice 19. Returns the one applied ("" none)."""
    try:
        os.sched_setscheduler(pid, os.SCHED_IDLE, os.sched_param(0))
        return "idle"
    except (AttributeError, OSError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, pid or threading.get_native_id(), 19)
        return "nice"
    except (AttributeError, OSError):
        return ""


class Background:
    """The parent's side (module docstring) for ``func`` (``"package.module:function"`` of one
    picklable argument): :meth:`submit` a job, :meth:`result` when it is wanted. Not
    thread-safe: one node's handling thread uses it."""

    def __init__(self, func: str, name: str = "background") -> None:
        self.func, self.name = func, name
        self._proc: subprocess.Popen[bytes] | None = None
        self._seq = 0
        self._busy: int | None = None  # the job the worker is computing
        self._done: tuple[int, Any] | None = None  # the last result back
        self.dead = False
        self.counts = {"submitted": 0, "used": 0, "refused": 0, "failed": 0}

    def start(self) -> bool:
        """Start the worker now (else the first :meth:`submit` does): its start-up, ~0.5 s of
        imports, is then over before the first job. Whether there is a worker."""
        if self.dead:
            return False
        if self._proc is None:
            try:
                self._proc = spawn_worker(self.func)
            except Exception as err:  # noqa: BLE001 - no worker: the owner computes
                self._fail(f"cannot start: {err}")
                return False
            lowest_priority(self._proc.pid)
        return True

    def submit(self, arg: Any) -> int | None:
        """Hand ``func(arg)`` to the worker; its number, or None when the worker is busy (or
        gone): then the owner computes it itself when it needs it."""
        if not self.start():
            return None
        self._drain()
        if self._busy is not None:
            self.counts["refused"] += 1
            return None
        self._seq += 1
        proc = self._proc
        assert proc is not None and proc.stdin is not None
        try:
            proc.stdin.write(pickle.dumps((arg,), protocol=pickle.HIGHEST_PROTOCOL))
            proc.stdin.flush()
        except (OSError, ValueError) as err:
            self._fail(f"cannot send: {err}")
            return None
        self._busy = self._seq
        self.counts["submitted"] += 1
        return self._seq

    def result(self, seq: int | None) -> tuple[bool, Any]:
        """``(True, value)`` when job ``seq``'s result is back, else ``(False, None)``."""
        if seq is None:
            return False, None
        self._drain()
        if self._done is not None and self._done[0] == seq:
            value = self._done[1]
            self._done = None
            self.counts["used"] += 1
            return True, value
        return False, None

    def ready(self, seq: int | None) -> bool:
        """Whether job ``seq``'s result is back (:meth:`result` then returns it at once)."""
        self._drain()
        return seq is not None and self._done is not None and self._done[0] == seq

    def idle(self) -> bool:
        """Whether no job is being computed (a new one would be taken)."""
        self._drain()
        return self._busy is None

    def _drain(self) -> None:
        """Take the running job's answer if it is there (the worker writes it whole)."""
        proc = self._proc
        if proc is None or self._busy is None or proc.stdout is None:
            return
        try:
            if not select.select([proc.stdout], [], [], 0)[0]:
                return
            ok, value = pickle.load(proc.stdout)
        except (EOFError, OSError, ValueError, pickle.UnpicklingError) as err:
            self._fail(f"the process went: {type(err).__name__}: {err}")
            return
        seq, self._busy = self._busy, None
        if ok:
            self._done = (seq, value)
        else:
            self.counts["failed"] += 1
            log.warning("%s: job %d failed: %s: %s", self.name, seq, type(value).__name__, value)

    def _fail(self, why: str) -> None:
        if not self.dead:  # (not after close)
            log.warning("%s: %s; its work is done in the foreground from now on", self.name, why)
        self.close()

    def close(self, timeout_s: float = 0.5) -> None:
        """End the worker (its stdin closed: it leaves; killed if it has not within
        ``timeout_s``); no job is taken after. Idempotent, and it does not raise: on a machine
        busy with other work a ``SCHED_IDLE`` process gets no CPU, not even to die of the kill,
        and the parent goes on without waiting for it (the kernel reaps it later)."""
        was, self.dead = self.dead, True
        proc, self._proc = self._proc, None
        if not was and self.counts["submitted"] + self.counts["refused"]:
            c = self.counts
            log.info(
                "%s: %d jobs computed in the background, %d of them back in time; %d refused "
                "while it was busy, %d failed (the rest done in the foreground)",
                self.name,
                c["submitted"],
                c["used"],
                c["refused"],
                c["failed"],
            )
        if proc is None:
            return
        for f in (proc.stdin, proc.stdout):
            try:
                if f is not None:
                    f.close()
            except OSError:
                pass
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log.info("%s: killed, not yet gone (no CPU for it): left to the system", self.name)
