"""Where the runner's nodes execute: anything with the ``concurrent.futures.Executor`` interface.

``serial`` runs each node in the calling thread when it is submitted (deterministic order, plain
tracebacks); ``local`` runs up to ``jobs`` nodes at once in threads of this process (the stages
release the GIL in numpy/scipy/OpenCV and fan detection out to worker processes themselves).
A distributed executor attaches here: ``dask.distributed.Client.get_executor()`` has the same
interface.
"""

from __future__ import annotations

import concurrent.futures as cf
from collections.abc import Callable
from typing import Any, TypeVar

from tagtrail.errors import SpecError

T = TypeVar("T")
KINDS = ("serial", "local")


class SerialExecutor(cf.Executor):
    """Runs each submitted call at once, in the caller's thread; returns a finished future."""

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> cf.Future[T]:
        fut: cf.Future[T] = cf.Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as err:  # noqa: BLE001 - handed to the caller through the future
            fut.set_exception(err)
        return fut


def make_executor(kind: str = "local", jobs: int = 1) -> cf.Executor:
    """``serial``, or ``local`` with ``jobs`` threads (``jobs`` 1 is serial)."""
    if kind not in KINDS:
        raise SpecError(f"unknown executor {kind!r} (choose from {', '.join(KINDS)})")
    if kind == "serial" or jobs <= 1:
        return SerialExecutor()
    return cf.ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="tagtrail-node")
