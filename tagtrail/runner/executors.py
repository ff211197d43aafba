"""Where the runner's nodes execute: anything with the ``concurrent.futures.Executor`` interface.

``serial`` runs each node in the calling thread when it is submitted (deterministic order, plain
tracebacks); ``local`` runs up to ``jobs`` nodes at once in threads of this process (the stages
release the GIL in numpy/scipy/OpenCV and fan detection out to worker processes themselves);
``dask`` runs them on a ``dask.distributed`` cluster — a ``LocalCluster`` of ``jobs`` worker
processes on 127.0.0.1, or the workers of an existing scheduler (``--scheduler tcp://host:8786``).

The runner alone decides what runs (it plans, looks up the cache, holds the store's lock); a
node goes out as a :class:`NodeTask` (plain picklable data: the stage's module name, params,
dataset config, upstream keys, the store's path) to :func:`run_remote`, which rebuilds the stage
in the worker, checks that the worker runs the same stage code as the runner (the code
fingerprint), reads its inputs from the store, runs the stage and writes the entry through the
store's own atomic protocol (temp folder, then rename); the row count comes back. The local
executors call the same :func:`run_node` in-process: one implementation, two drivers.

What the store's file system must provide when workers run on other hosts:

- the same path on every host (the project's ``artifacts/`` and the datasets' sources);
- atomic ``rename(2)`` of a directory within one file system, and close-to-open consistency
  (a file closed on one host reads whole on another) — NFS, CephFS, Lustre, GPFS/Spectrum Scale,
  BeeGFS do;
- for the store's lock (``flock(2)`` on ``artifacts/.lock``, taken by the runner for the whole
  run, so two runs never share the store): locks that hold across hosts. Linux's NFS client
  sends ``flock`` to the server as a POSIX lock: NFSv4, or NFSv3 with ``lockd``/``rpc.statd``
  running, and no ``nolock`` or ``local_lock=flock|all`` mount option; Lustre needs the
  ``flock`` mount option (``localflock`` is host-local); SMB/CIFS mounts and most FUSE file
  systems (sshfs, object-store mounts) keep the lock on one host or ignore it;
- the host running ``tagtrail run`` should see new entries at once: on NFS mount the store with
  ``lookupcache=positive`` (the default also caches "no such file", so an entry a worker just
  renamed into place can look missing for up to ``acdirmax`` seconds and the run fails).

Without a lock that holds across hosts, two runs started on different hosts against one store
can overlap. The store still never holds a damaged entry it would accept (each entry is renamed
into place whole, and every file is checked against its manifest's sha256 before use): the
worst case is a node failing (a temp folder removed under it by the other run's clean-up, or a
rename refused because the entry appeared meanwhile), which a rerun repairs. A worker killed
mid-run (``kill -9``, out of memory) leaves at most a temp folder, removed by the next run;
dask reschedules its task on another worker up to ``distributed.scheduler.allowed-failures``
times, then the node fails with one line.

Outputs are byte-identical to the local executor's when the workers run single-threaded BLAS
(the last bit of a float can depend on the thread count): dask's nanny sets
``OPENBLAS_NUM_THREADS``/``OMP_NUM_THREADS``/``MKL_NUM_THREADS`` to 1 by default
(``distributed.nanny.pre-spawn-environ``); the runner warns when a worker does not.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import contextvars
import importlib
import importlib.util
import logging
import multiprocessing.util
import os
import pickle
import signal
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar

from tagtrail import faults, pool
from tagtrail.errors import SpecError
from tagtrail.runner.cache import Store
from tagtrail.runner.inputs import resolve
from tagtrail.runner.stage import StageSpec, stage_spec
from tagtrail.schemas.pipeline import DatasetConfig
from tagtrail.schemas.stage import StageParams

T = TypeVar("T")
KINDS = ("serial", "local", "dask")
DASK_MISSING = "--executor dask needs dask.distributed: pip install 'tagtrail[dask]'"
BLAS_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
DASHBOARD_PORT = 8787
WAIT_FOR_WORKERS_S = 60.0
CONNECT_TIMEOUT_S = 10.0


class SerialExecutor(cf.Executor):
    """Runs each submitted call at once, in the caller's thread; returns a finished future.
    Ctrl-C (``KeyboardInterrupt``) is not a result of the call: it leaves ``submit`` at once."""

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> cf.Future[T]:
        fut: cf.Future[T] = cf.Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except Exception as err:  # noqa: BLE001 - handed to the caller through the future
            fut.set_exception(err)
        return fut


def timed_call(fn: Callable[..., T], /, *args: Any) -> tuple[T, float]:
    """``(fn(*args), seconds it took)``, measured where it runs: a node's compute time, not
    its wait in a queue nor, under the serial executor (which runs it inside ``submit``), the
    runner's bookkeeping around it."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def make_executor(kind: str = "local", jobs: int = 1) -> cf.Executor:
    """``serial``, or ``local`` with ``jobs`` threads (``jobs`` 1 is serial); ``dask`` needs a
    cluster: use :func:`open_executor`."""
    if kind not in KINDS or kind == "dask":
        choices = ", ".join(k for k in KINDS if k != "dask")
        raise SpecError(f"unknown executor {kind!r} (choose from {choices})")
    if kind == "serial" or jobs <= 1:
        return SerialExecutor()
    return cf.ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="tagtrail-node")


# --- one node, wherever it runs ---------------------------------------------------------------


@dataclass(frozen=True)
class NodeTask:
    """Everything needed to run one node, as plain picklable data (no runner, no open file)."""

    stage: str
    dataset: str
    module: str  # the stage module's import name …
    module_file: str | None  # … and its file, for stage modules not importable by name
    params: StageParams
    config: DatasetConfig
    key: str
    record: dict[str, Any]
    specials: dict[str, str]  # run() argument → special input (source, ground_truth, dataset)
    upstream: dict[str, tuple[str, str, str]]  # run() argument → (stage, key, output)
    artifacts: Path
    log_level: int = logging.INFO

    @property
    def label(self) -> str:
        return f"{self.stage} [{self.dataset}]"

    # ``params`` is an instance of the stage module's own class: pickled on its own and
    # unpickled once that module is loaded (by name, or from its file for a registry built
    # from files, whose modules a worker cannot import by name).
    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["params"] = pickle.dumps(self.params, protocol=pickle.HIGHEST_PROTOCOL)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        _stage_module(state["module"], state["module_file"])
        state["params"] = pickle.loads(state["params"])
        self.__dict__.update(state)


def run_node(task: NodeTask, spec: StageSpec, store: Store) -> int | None:
    """Run one node's stage on its inputs and write its entry; the number of rows written."""
    kwargs: dict[str, Any] = {}
    with ExitStack() as stack:
        for arg, special in task.specials.items():
            kwargs[arg] = resolve(special, task.config, task.label, stack)
        for arg, (stage, key, output) in task.upstream.items():
            kwargs[arg] = store.load(stage, key, output)
        outputs = spec.run(task.params, **kwargs)
    faults.point(f"stage:{task.stage}")
    if not isinstance(outputs, dict) or set(outputs) != set(spec.outputs):
        got = sorted(outputs) if isinstance(outputs, dict) else type(outputs).__name__
        raise TypeError(f"run() returned {got}, expected outputs {list(spec.outputs)}")
    manifest = store.write(task.stage, task.key, outputs, task.record)
    store.save_record(task.dataset, task.stage, task.record)
    rows = [o["rows"] for o in manifest["outputs"].values() if o["rows"] is not None]
    return sum(rows) if rows else None


_SPECS: dict[tuple[str, str], StageSpec] = {}


def _stage_module(name: str, file: str | None) -> ModuleType:
    if name in sys.modules:
        return sys.modules[name]
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError:
        if file is None:
            raise
    spec = importlib.util.spec_from_file_location(name, file)
    if spec is None or spec.loader is None:
        raise ModuleNotFoundError(f"stage module {name} cannot be loaded from {file}")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def run_remote(task: NodeTask) -> int | None:
    """The task a worker process runs: rebuild the stage, check its code, run the node."""
    logging.getLogger("tagtrail").setLevel(task.log_level)  # records are forwarded to the runner
    spec = _SPECS.get((task.stage, task.module))
    if spec is None:  # once per worker, when it loads the stage: the fingerprint describes the
        # code in memory, so a worker left running across a code update refuses to run it
        spec = stage_spec(task.stage, _stage_module(task.module, task.module_file))
        _SPECS[(task.stage, task.module)] = spec
    if spec.code_fingerprint != task.record["code"]:
        raise SpecError(
            f"the dask worker on {socket.gethostname()} runs other code for stage "
            f"{task.stage} ({task.module}) than `tagtrail run` does; install the same tagtrail "
            "on every worker and restart the workers"
        )
    with pool.task_mapper(_cluster_tasks):  # extract's frame chunks: tasks of the cluster
        return run_node(task, spec, Store(task.artifacts))


def _cluster_tasks(func: str, tasks: Iterable[tuple[Any, ...]]) -> Iterator[Any]:
    """``pool.run_one(func, args)`` for each of ``tasks`` as a task of the cluster this worker
    belongs to (so one long recording's chunks spread over every worker), at most two per worker
    thread in flight; results as they complete. Each chunk goes from this worker to the one that
    runs it directly (scattered), not through the scheduler."""
    distributed: Any = importlib.import_module("distributed")
    name = func.rsplit(":", 1)[-1].replace("_", "-")
    here = distributed.get_worker().address
    with distributed.worker_client(separate_thread=True) as client:
        limit = 2 * max(1, sum(client.nthreads().values()))
        pending = iter(tasks)
        running = distributed.as_completed()

        def submit() -> bool:
            args = next(pending, None)
            if args is None:
                return False
            [data] = client.scatter([args], hash=False, workers=[here])  # lost only with us
            running.add(
                client.submit(
                    pool.run_one, func, data, pure=False, key=f"{name}-{uuid.uuid4().hex}"
                )
            )
            return True

        for _ in range(limit):
            if not submit():
                break
        for future in running:
            result = future.result()
            future.release()
            yield result
            submit()


# --- dask -------------------------------------------------------------------------------------


class WorkerDied(RuntimeError):
    """The dask workers that ran a node died (killed, out of memory) as many times as allowed."""


def _blas_env() -> dict[str, str | None]:
    return {v: os.environ.get(v) for v in BLAS_VARS}


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def dask_setup(worker: Any) -> None:
    """Run by each worker process of the local cluster as it starts (dask's ``preload``): it
    ignores SIGINT. Ctrl-C at a terminal signals the whole foreground process group; the
    command handles it and ends the cluster (:meth:`DaskSession.kill_workers`), where a worker
    of its own would die of it printing a traceback after the command's ``interrupted``."""
    del worker
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from tqdm import tqdm

    # tqdm's default lock holds a multiprocessing semaphore, which a killed worker would leave
    # to multiprocessing's resource tracker (a warning); its bars are this process's alone
    tqdm.set_lock(threading.RLock())


_LOCAL: list[DaskSession] = []  # the sessions whose LocalCluster is running


def kill_local_workers() -> None:
    """At the exit of an interrupted command (``os._exit``, :mod:`tagtrail.signals`; the CLI
    registers it): the local clusters' workers are killed and the semaphores of their nannies'
    queues released, as multiprocessing's exit handler would (else its resource tracker warns
    of them)."""
    for session in list(_LOCAL):
        session.kill_workers()
    finalizers: Callable[[int], None] | None = getattr(
        multiprocessing.util, "_run_finalizers", None
    )
    if finalizers is not None:
        finalizers(0)  # priority >= 0: what multiprocessing runs first at exit (its locks)


class DaskSession:
    """A ``dask.distributed`` client: to ``scheduler``, or to a ``LocalCluster`` of ``workers``
    processes on 127.0.0.1 it starts (and stops). Prints one line with the dashboard link."""

    def __init__(
        self,
        scheduler: str | None = None,
        workers: int = 2,
        echo: Callable[[str], None] | None = None,
    ) -> None:
        self.scheduler = scheduler
        self.workers = max(1, workers)
        self.echo = echo or (lambda s: None)
        self.client: Any = None
        self._cluster: Any = None
        self._stack = ExitStack()

    def __enter__(self) -> DaskSession:
        try:
            distributed: Any = importlib.import_module("distributed")  # optional: tagtrail[dask]
        except ImportError as err:
            raise SpecError(DASK_MISSING) from err
        with ExitStack() as stack:
            quiet = logging.getLogger("distributed")  # its INFO chatter; warnings still show
            stack.callback(quiet.setLevel, quiet.level)
            quiet.setLevel(max(quiet.getEffectiveLevel(), logging.WARNING))
            if self.scheduler is None:
                port = DASHBOARD_PORT if _port_free(DASHBOARD_PORT) else 0
                cluster = stack.enter_context(
                    distributed.LocalCluster(
                        n_workers=self.workers,
                        threads_per_worker=1,
                        processes=True,
                        host="127.0.0.1",
                        dashboard_address=f"127.0.0.1:{port}",
                        silence_logs=logging.CRITICAL,
                        env=dict.fromkeys(BLAS_VARS, "1"),
                        preload=[__name__],  # dask_setup: Ctrl-C is for this process
                    )
                )
                self._cluster = cluster
                _LOCAL.append(self)
                stack.callback(_LOCAL.remove, self)
                client = stack.enter_context(distributed.Client(cluster))
                where = f"a local cluster of {self.workers} worker processes"
            else:
                try:
                    client = stack.enter_context(
                        distributed.Client(self.scheduler, timeout=CONNECT_TIMEOUT_S)
                    )
                except (OSError, TimeoutError, ValueError) as err:
                    raise SpecError(
                        f"cannot reach the dask scheduler at {self.scheduler} ({err}); start "
                        "one with `dask scheduler` and workers with `dask worker ADDRESS`, or "
                        "leave out --scheduler for a local cluster"
                    ) from err
                n = len(client.scheduler_info(n_workers=-1).get("workers", {}))
                if n == 0:
                    self.echo(f"dask: waiting for workers to connect to {self.scheduler}…")
                    try:
                        client.wait_for_workers(1, timeout=WAIT_FOR_WORKERS_S)
                    except TimeoutError as err:
                        raise SpecError(
                            f"no dask worker connected to {self.scheduler} within "
                            f"{WAIT_FOR_WORKERS_S:.0f} s; start some with `dask worker "
                            f"{self.scheduler}`"
                        ) from err
                    n = len(client.scheduler_info(n_workers=-1).get("workers", {}))
                where = f"{self.scheduler} ({n} workers)"
            client.forward_logging("tagtrail")
            self.client = client
            self._stack = stack.pop_all()
        self.echo(f"dask: {where}, dashboard {client.dashboard_link}")
        self._check_blas()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *rest: object) -> None:
        if exc_type is not None and issubclass(exc_type, KeyboardInterrupt):
            self.kill_workers()  # not the cluster's orderly close: seconds, and its workers'
        self.client = None  # shutdown chatter (tracebacks, warnings) after `interrupted`
        self._stack.close()

    def kill_workers(self) -> None:
        """SIGKILL the worker processes of the local cluster (Ctrl-C): their task is abandoned,
        as the local executor abandons its threads; the store keeps no partial entry. Each
        nanny is marked failed first (the status in which it neither restarts its worker nor
        waits to close): a running one restarts a worker that dies, and the new process, still
        starting when the command exits, printed a traceback (EOFError) after ``interrupted``."""
        failed = importlib.import_module("distributed.core").Status.failed
        for nanny in getattr(self._cluster, "workers", {}).values():
            with contextlib.suppress(AttributeError, TypeError):
                nanny.status = failed
            pid = getattr(getattr(nanny, "process", None), "pid", None)
            if pid:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)

    def _check_blas(self) -> None:
        envs: dict[str, dict[str, str | None]] = self.client.run(_blas_env)
        multi = sorted(w for w, env in envs.items() if any(v != "1" for v in env.values()))
        if multi:
            self.echo(
                f"warning: {len(multi)} of {len(envs)} dask workers may run a "
                "multi-threaded BLAS (start them with OPENBLAS_NUM_THREADS=1 "
                "OMP_NUM_THREADS=1 MKL_NUM_THREADS=1): outputs can differ from a local "
                "run in the last bit"
            )

    def check_shared(self, path: Path) -> None:
        """Refuse to run when a worker does not see ``path`` (the artifact store)."""
        seen: dict[str, bool] = self.client.run(os.path.isdir, str(path))
        blind = sorted(w for w, ok in seen.items() if not ok)
        if blind:
            raise SpecError(
                f"dask worker(s) {', '.join(blind)} do not see the artifact store {path}: put "
                "the project on a file system every worker mounts at the same path"
            )


class DaskExecutor(cf.Executor):
    """Submits to a dask client; a task whose workers all died fails with :class:`WorkerDied`.
    Leaving the ``with`` block on an exception (Ctrl-C) cancels what is still queued."""

    remote = True

    def __init__(self, client: Any) -> None:
        self._inner: cf.Executor = client.get_executor(pure=False)

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> cf.Future[T]:
        outer: cf.Future[T] = cf.Future()

        def done(inner: cf.Future[T]) -> None:
            if inner.cancelled():
                outer.cancel()
                outer.set_running_or_notify_cancel()
                return
            err = inner.exception()
            if err is None:
                outer.set_result(inner.result())
            elif type(err).__name__ == "KilledWorker":
                died = WorkerDied(
                    "the dask worker running it died each time it was tried "
                    "(killed or out of memory: see the worker's log); nothing "
                    "partial was kept, rerun to retry"
                )
                died.__cause__ = err
                outer.set_exception(died)
            else:
                outer.set_exception(err)

        self._inner.submit(fn, *args, **kwargs).add_done_callback(done)
        return outer

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._inner.shutdown(wait=wait and not cancel_futures)

    def __exit__(self, exc_type: Any, *rest: Any) -> None:
        self.shutdown(wait=exc_type is None)


_SESSION: contextvars.ContextVar[DaskSession | None] = contextvars.ContextVar(
    "tagtrail_dask_session", default=None
)


@contextlib.contextmanager
def dask_session(
    scheduler: str | None = None,
    workers: int = 2,
    echo: Callable[[str], None] | None = None,
) -> Iterator[DaskSession]:
    """One dask client for several runs (a sweep): runners with ``executor="dask"`` inside the
    block use it instead of starting a cluster each."""
    with DaskSession(scheduler, workers, echo) as session:
        token = _SESSION.set(session)
        try:
            yield session
        finally:
            _SESSION.reset(token)


@contextlib.contextmanager
def open_executor(
    kind: str = "local",
    jobs: int = 1,
    scheduler: str | None = None,
    echo: Callable[[str], None] | None = None,
    store: Path | None = None,
) -> Iterator[cf.Executor]:
    """The executor of one run. ``dask``: the active :func:`dask_session` when it matches
    ``scheduler``, else a session for this run (``jobs`` local workers without a scheduler);
    ``store`` is checked to be visible from every worker."""
    if kind != "dask":
        if scheduler is not None:
            raise SpecError("--scheduler needs --executor dask")
        pool = make_executor(kind, jobs)
        try:
            yield pool
        except KeyboardInterrupt:  # Ctrl-C: drop the queue, do not wait for the running nodes
            pool.shutdown(wait=False, cancel_futures=True)  # (the process ends without them:
            raise  # tagtrail.signals)
        except BaseException:
            pool.shutdown(wait=True)
            raise
        pool.shutdown(wait=True)
        return
    with ExitStack() as stack:
        session = _SESSION.get()
        if session is None or scheduler not in (None, session.scheduler):
            session = stack.enter_context(DaskSession(scheduler, jobs, echo))
        if store is not None:
            session.check_shared(store)
        yield stack.enter_context(DaskExecutor(session.client))
