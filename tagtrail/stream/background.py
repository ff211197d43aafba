"""A child process that computes a node's background work at the lowest priority.

The live smoother answers each frame with the filter's step and re-solves its window after
the pose is out (~10 ms of CPU). On a thread of the node that work would share the GIL with
the handlers — a handler waits up to the interpreter's switch interval (5 ms) for it, or for
as long as the scheduler leaves a low-priority GIL holder off the CPU — and Linux's EEVDF
scheduler lets a niced thread finish its slice before the downstream nodes run (2-4 ms of
delay measured, bench/FOLLOW.md). A process of its own under ``SCHED_IDLE`` (preempted at once
by any other task that wakes) shares neither, and nothing it holds can hold a handler up: a
handler that needs a result not yet back computes it itself (:class:`Background` is only ever
asked, never waited for).

Work is ``fn(arg)`` with a module-level ``fn`` and a picklable ``arg``; one job at a time (a
job submitted while one runs is refused: its owner computes it when needed). The process starts
with the first job — a fresh interpreter (``python -m tagtrail.stream.background``, pickles over
its stdin and stdout: no fork beside zenoh's threads, and unlike multiprocessing's spawn it
never re-imports the parent's main script) — and ends when :meth:`Background.close` is called
or its parent goes (its stdin closes).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

log = logging.getLogger("tagtrail.stream")


def lowest_priority(tid: int = 0) -> str:
    """Put thread ``tid`` (0: the caller's process or thread; Linux sets it per thread) at the
    lowest scheduling priority: ``SCHED_IDLE``, which any other task that wakes up preempts at
    once; where that is refused, nice 19. Returns the one applied ("" none)."""
    try:
        os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        return "idle"
    except (AttributeError, OSError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, tid, 19)
        return "nice"
    except (AttributeError, OSError):
        return ""


def _serve(conn: _Pipes) -> None:
    """The child: ``(seq, fn, arg)`` in, ``(seq, ok, fn(arg) or the error's text)`` out."""
    while True:
        try:
            seq, fn, arg = conn.recv()
        except (EOFError, OSError):
            return  # the parent closed the pipe, or went
        try:
            out: tuple[int, bool, Any] = (seq, True, fn(arg))
        except Exception as err:  # noqa: BLE001 - reported to the parent, which computes it
            out = (seq, False, f"{type(err).__name__}: {err}")
        try:
            conn.send(out)
        except (OSError, ValueError):
            return


class Background:
    """The parent's side (module docstring): :meth:`submit` a job, :meth:`result` when it is
    wanted. Not thread-safe: one node's handling thread uses it."""

    def __init__(self, name: str = "background") -> None:
        self.name = name
        self._conn: _Pipes | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._seq = 0
        self._busy: int | None = None  # the job the child is computing
        self._done: tuple[int, Any] | None = None  # the last result back
        self.dead = False
        self.counts = {"submitted": 0, "used": 0, "refused": 0, "failed": 0}

    def _start(self) -> None:
        root = str(Path(__file__).resolve().parents[2])  # where this tagtrail is imported from
        path = os.environ.get("PYTHONPATH")
        env = {**os.environ, "PYTHONPATH": root + (os.pathsep + path if path else "")}
        proc = subprocess.Popen(
            [sys.executable, "-m", "tagtrail.stream.background"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        assert proc.stdin is not None and proc.stdout is not None
        # one duplex Connection over the two pipes: it frames the pickles
        self._conn = _Pipes(proc.stdin.fileno(), proc.stdout.fileno())
        self._proc = proc

    def submit(self, fn: Callable[[Any], Any], arg: Any) -> int | None:
        """Hand ``fn(arg)`` to the child; its number, or None when the child is busy (or
        gone): then the owner computes it itself when it needs it."""
        if self.dead:
            return None
        if self._conn is None:
            try:
                self._start()
            except Exception as err:  # noqa: BLE001 - no child: the owner computes
                self._fail(f"cannot start: {err}")
                return None
        self._drain()
        if self._busy is not None:
            self.counts["refused"] += 1
            return None
        self._seq += 1
        assert self._conn is not None
        try:
            self._conn.send((self._seq, fn, arg))
        except (OSError, ValueError) as err:
            self._fail(f"cannot send: {err}")
            return None
        self._busy = self._seq
        self.counts["submitted"] += 1
        return self._seq

    def result(self, seq: int | None) -> tuple[bool, Any]:
        """``(True, value)`` when job ``seq``'s result is back, else ``(False, None)``."""
        if seq is None or self._conn is None:
            return False, None
        self._drain()
        if self._done is not None and self._done[0] == seq:
            value = self._done[1]
            self._done = None
            self.counts["used"] += 1
            return True, value
        return False, None

    def idle(self) -> bool:
        """Whether no job is being computed (a new one would be taken)."""
        self._drain()
        return self._busy is None

    def _drain(self) -> None:
        conn = self._conn
        try:
            while conn is not None and conn.poll():
                seq, ok, value = conn.recv()
                if seq == self._busy:
                    self._busy = None
                if ok:
                    self._done = (seq, value)
                else:
                    self.counts["failed"] += 1
                    log.warning("%s: job %d failed: %s", self.name, seq, value)
        except (EOFError, OSError) as err:
            self._fail(f"the process went: {err}")

    def _fail(self, why: str) -> None:
        if not self.dead:  # (not after close)
            log.warning("%s: %s; its work is done in the foreground from now on", self.name, why)
        self.dead = True
        self.close()

    def close(self, timeout_s: float = 0.5) -> None:
        """End the child (its pipe closed: it leaves; killed if it has not within
        ``timeout_s``); no job is taken after. Idempotent."""
        self.dead = True
        conn, self._conn = self._conn, None
        if conn is not None:
            conn.close()
        proc, self._proc = self._proc, None
        if proc is not None:
            for f in (proc.stdin, proc.stdout):
                if f is not None:
                    f.close()
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout_s)


class _Pipes:
    """``send``/``recv``/``poll``/``close`` of :class:`multiprocessing.connection.Connection`
    over a child's stdin (out) and stdout (in)."""

    def __init__(self, out_fd: int, in_fd: int) -> None:
        self._out = Connection(os.dup(out_fd), readable=False)
        self._in = Connection(os.dup(in_fd), writable=False)

    def send(self, obj: Any) -> None:
        self._out.send(obj)

    def recv(self) -> Any:
        return self._in.recv()

    def poll(self) -> bool:
        return self._in.poll()

    def close(self) -> None:
        self._out.close()
        self._in.close()


def main() -> None:
    """The child's entry: serve the parent over stdin/stdout at the lowest priority; its
    Ctrl-C is the parent's to handle (the parent ends it)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    lowest_priority()
    conn = _Pipes(1, 0)  # (duplicates of the two pipes' ends)
    os.dup2(2, 1)  # nothing else may write into the pipe: stdout is stderr from now on
    os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
    _serve(conn)


if __name__ == "__main__":
    main()
