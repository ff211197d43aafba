"""A small pool of subprocess workers mapping one function over pickled tasks.

Why not :mod:`multiprocessing`: ``fork`` is unsafe from the runner's threads (a lock held by
another thread stays locked in the child), and ``forkserver``/``spawn`` re-import the caller's
``__main__`` in every worker (an unguarded user script would run again; the CLI entry point
would import the whole package). Workers here are plain ``python -m tagtrail.pool
MODULE:FUNC`` processes that import only the module they need and exchange pickles over their
stdin/stdout pipes.

:func:`shared_pool` keeps idle pools for reuse within the process (a pipeline extracts several
datasets; a sweep re-runs extract): worker start-up (~0.3 s of imports) is paid once.

Each result is read before its worker is told to stop, and a worker's exit status is not
trusted: workers leave through ``os._exit(0)`` (no interpreter teardown), so a library that
crashes in its finalizers (pupil-apriltags, upstream pupil-labs/apriltags#46) can never fail a
run. A worker that dies *while* holding a task is an error.
"""

from __future__ import annotations

import atexit
import contextvars
import importlib
import os
import pickle
import queue
import signal
import subprocess
import sys
import threading
import weakref
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO

import tagtrail

try:
    import fcntl
except ImportError:  # not POSIX
    pass

_POLL_S = 0.05
DEPTH = 2  # tasks in flight per worker
_PIPE_BYTES = 1 << 20


def spawn_worker(func: str) -> subprocess.Popen[bytes]:
    """One worker process running ``func`` (``"package.module:function"``) on the tasks
    pickled to its stdin (a tuple of arguments each; ``None``: the end of a batch, echoed),
    each answered on its stdout by a pickled ``(ok, result or exception)``; it leaves at EOF."""
    env = dict(os.environ)
    root = str(Path(tagtrail.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    proc = subprocess.Popen(
        [sys.executable, "-m", "tagtrail.pool", func],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env=env,
        process_group=0,  # Ctrl-C at a terminal signals its foreground group: the parent
    )  # alone, which stops the workers (a worker has no partial result to keep)
    for f in (proc.stdin, proc.stdout):  # fewer context switches for MB-sized raw images, and
        try:  # a result written whole (Linux)
            fcntl.fcntl(f.fileno(), fcntl.F_SETPIPE_SZ, _PIPE_BYTES)  # type: ignore
        except (AttributeError, OSError, NameError):
            pass
    return proc


class WorkerPool:
    """``workers`` processes running ``func`` (``"package.module:function"``) on tasks.

    Use as a context manager; :meth:`imap_unordered` takes tuples of arguments and yields the
    function's results as they complete. Worker exceptions are re-raised in the caller.
    """

    def __init__(self, func: str, workers: int) -> None:
        self.procs = [spawn_worker(func) for _ in range(max(1, workers))]
        self._threads: list[threading.Thread] = []
        self._closing = threading.Event()
        self._clean = True  # no task in flight: safe to reuse
        _LIVE.add(self)

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close(kill=exc[0] is not None)

    def close(self, kill: bool = False) -> None:
        """Stop the workers (EOF on their stdin, or SIGKILL), ignoring their exit status."""
        self._closing.set()
        for p in self.procs:
            if kill:
                p.kill()
            try:
                if p.stdin is not None:
                    p.stdin.close()
            except OSError:
                pass
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for t in self._threads:  # their worker is gone: they return at EOF
            t.join()
        for p in self.procs:
            if p.stdout is not None:
                p.stdout.close()

    def alive(self) -> bool:
        """Every worker running and no result left unread."""
        return self._clean and all(p.poll() is None for p in self.procs)

    def imap_unordered(self, tasks: Iterable[tuple[Any, ...]]) -> Iterator[Any]:
        """Results of ``func(*task)`` in completion order.

        Each worker has up to ``DEPTH`` tasks in flight (the next one is already in its pipe
        when it finishes one), fed by a writer thread; a reader thread collects its results.
        """
        todo: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=len(self.procs))
        results: queue.Queue[tuple[bool, Any]] = queue.Queue()
        fed_all = threading.Event()
        threads = []
        for p in self.procs:
            slots = threading.Semaphore(DEPTH)
            threads += [
                threading.Thread(
                    target=_write, args=(p, todo, slots, fed_all, self._closing), daemon=True
                ),
                threading.Thread(target=_read, args=(p, results, slots), daemon=True),
            ]
        self._threads = [t for t in self._threads if t.is_alive()] + threads
        self._clean = False
        for t in threads:
            t.start()
        pending = 0
        try:
            for task in tasks:
                while True:
                    try:
                        todo.put(task, timeout=_POLL_S)
                        pending += 1
                        break
                    except queue.Full:
                        while not results.empty():
                            pending -= 1
                            yield _unwrap(results.get())
                while not results.empty():
                    pending -= 1
                    yield _unwrap(results.get())
            fed_all.set()
            while pending:
                pending -= 1
                yield _unwrap(results.get())
            for t in threads:
                t.join()
            self._clean = True
        finally:
            fed_all.set()


_IDLE: dict[tuple[str, int], WorkerPool] = {}
_IDLE_LOCK = threading.Lock()
_LIVE: weakref.WeakSet[WorkerPool] = weakref.WeakSet()  # every open pool, for kill_workers


def kill_workers() -> None:
    """SIGKILL every worker of every pool of this process: how an interrupted command ends them
    at once (``tagtrail.signals``; a worker holds no partial result worth keeping)."""
    for pool in list(_LIVE):
        for p in pool.procs:
            try:
                p.kill()
            except OSError:
                pass


@contextmanager
def shared_pool(func: str, workers: int) -> Iterator[WorkerPool]:
    """A pool for exclusive use, reused from an earlier call when one is idle; returned for
    reuse afterwards (closed instead after an error). Idle pools are closed at exit."""
    key = (func, workers)
    with _IDLE_LOCK:
        pool = _IDLE.pop(key, None)
    if pool is not None and not pool.alive():
        pool.close(kill=True)
        pool = None
    pool = pool or WorkerPool(func, workers)
    ok = False
    try:
        yield pool
        ok = True
    finally:
        if ok and pool.alive():
            with _IDLE_LOCK:
                keep = key not in _IDLE
                if keep:
                    _IDLE[key] = pool
            if not keep:
                pool.close()
        else:
            pool.close(kill=True)


Mapper = Callable[[str, Iterable[tuple[Any, ...]]], Iterator[Any]]
_MAPPER: contextvars.ContextVar[Mapper | None] = contextvars.ContextVar(
    "tagtrail_mapper", default=None
)


@contextmanager
def task_mapper(mapper: Mapper) -> Iterator[None]:
    """Within the block (this thread), :func:`map_tasks` hands its tasks to ``mapper`` instead
    of a local pool: an executor's, e.g. the dask one, which runs each as a task of the cluster."""
    token = _MAPPER.set(mapper)
    try:
        yield
    finally:
        _MAPPER.reset(token)


def map_tasks(func: str, tasks: Iterable[tuple[Any, ...]], workers: int) -> Iterator[Any]:
    """``func`` (``"package.module:function"``) over ``tasks``, results in any order: through the
    :func:`task_mapper` in effect, else in a :func:`shared_pool` of ``workers`` processes."""
    mapper = _MAPPER.get()
    if mapper is not None:
        yield from mapper(func, tasks)
        return
    with shared_pool(func, workers) as pool:
        yield from pool.imap_unordered(tasks)


def run_one(func: str, args: tuple[Any, ...]) -> Any:
    """``func(*args)`` in a worker process of this process (a pool of one, kept for reuse): how
    a task handed out by a :func:`task_mapper` runs where it lands."""
    with shared_pool(func, 1) as pool:
        return next(iter(pool.imap_unordered([args])))


@atexit.register
def _close_idle() -> None:
    with _IDLE_LOCK:
        pools = list(_IDLE.values())
        _IDLE.clear()
    for pool in pools:
        pool.close()


def _unwrap(item: tuple[bool, Any]) -> Any:
    ok, value = item
    if not ok:
        raise value
    return value


def _write(
    proc: subprocess.Popen[bytes],
    todo: queue.Queue[tuple[Any, ...]],
    slots: threading.Semaphore,
    fed_all: threading.Event,
    closing: threading.Event,
) -> None:
    """Send tasks to one worker while it has a free slot; then the end marker (a thread)."""
    assert proc.stdin is not None
    try:
        while not closing.is_set():
            if not slots.acquire(timeout=_POLL_S):
                continue
            while True:
                try:
                    task: tuple[Any, ...] | None = todo.get(timeout=_POLL_S)
                    break
                except queue.Empty:
                    if fed_all.is_set() or closing.is_set():
                        task = None
                        break
            pickle.dump(task, proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            proc.stdin.flush()
            if task is None:
                return
    except (OSError, ValueError):
        return  # the reader reports the dead worker


def _read(
    proc: subprocess.Popen[bytes],
    results: queue.Queue[tuple[bool, Any]],
    slots: threading.Semaphore,
) -> None:
    """Collect one worker's results until its end marker (runs in a thread)."""
    assert proc.stdout is not None
    while True:
        try:
            ok, value = pickle.load(proc.stdout)
        except (EOFError, OSError, ValueError, pickle.UnpicklingError) as err:
            try:
                code: int | None = proc.wait(timeout=1)
            except subprocess.TimeoutExpired:
                code = None
            results.put(
                (
                    False,
                    RuntimeError(
                        f"worker process {proc.pid} died while working on a task "
                        f"(exit status {code}): {type(err).__name__}: {err}"
                    ),
                )
            )
            return
        if ok is None:  # end marker
            return
        results.put((ok, value))
        slots.release()


def _worker_main(func_spec: str) -> None:
    """Worker loop: read a pickled task tuple, call the function, write ``(ok, result)``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and closes pipes
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # (a closed terminal: the parent stops)
    out: BinaryIO = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # stray prints (Python or C) go to stderr, not into the result stream
    mod, _, name = func_spec.partition(":")
    func = getattr(importlib.import_module(mod), name)
    inp = sys.stdin.buffer
    while True:
        try:
            task = pickle.load(inp)
        except (EOFError, OSError, pickle.UnpicklingError):  # the parent closed the pipe (or
            break  # died writing a task): no more work
        if task is None:  # end of a batch: echo the marker, stay alive for the next one
            try:
                out.write(pickle.dumps((None, None)))
                out.flush()
            except OSError:
                os._exit(0)
            continue
        try:
            reply: tuple[bool, Any] = (True, func(*task))
        except Exception as err:  # noqa: BLE001 - sent back and re-raised in the parent
            reply = (False, err)
        try:
            data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as err:  # noqa: BLE001 - an unpicklable exception
            data = pickle.dumps((False, RuntimeError(f"{type(reply[1]).__name__}: {err}")))
        try:
            out.write(data)
            out.flush()
        except OSError:  # the parent is gone (interrupted, killed): nobody wants the result
            os._exit(0)
    try:
        out.close()
    except OSError:
        pass
    os._exit(0)  # skip interpreter teardown (library finalizers that may crash)


if __name__ == "__main__":
    _worker_main(sys.argv[1])
