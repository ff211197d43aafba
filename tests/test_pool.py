"""WorkerPool: subprocess workers, results before exit, errors re-raised, deaths reported."""

from __future__ import annotations

import pytest

from tagtrail.errors import SourceError
from tagtrail.pool import WorkerPool, shared_pool


def test_results_complete_and_workers_stop() -> None:
    with WorkerPool("tests.pool_funcs:square", 2) as pool:
        got = sorted(pool.imap_unordered((x,) for x in range(25)))
        procs = pool.procs
    assert got == [(x, x * x) for x in range(25)]
    assert all(p.poll() is not None for p in procs)  # exited; status not inspected


def test_worker_exception_is_reraised() -> None:
    with (
        pytest.raises(SourceError, match="bad frame"),
        WorkerPool("tests.pool_funcs:fail", 1) as pool,
    ):
        list(pool.imap_unordered((x,) for x in range(3)))


def test_worker_death_mid_task_is_an_error() -> None:
    with pytest.raises(RuntimeError, match=r"died while working on a task \(exit status 3\)"):
        with WorkerPool("tests.pool_funcs:die", 2) as pool:
            list(pool.imap_unordered((x,) for x in range(4)))


def test_shared_pool_is_reused_unless_it_failed() -> None:
    with shared_pool("tests.pool_funcs:square", 2) as pool:
        assert sorted(pool.imap_unordered([(1,), (2,)])) == [(1, 1), (2, 4)]
        pids = [p.pid for p in pool.procs]
    with shared_pool("tests.pool_funcs:square", 2) as again:
        assert [p.pid for p in again.procs] == pids  # no new start-up
        with shared_pool("tests.pool_funcs:square", 2) as other:  # busy: a private one
            assert [p.pid for p in other.procs] != pids
            assert list(other.imap_unordered([(3,)])) == [(3, 9)]
    with pytest.raises(SourceError), shared_pool("tests.pool_funcs:fail", 1) as bad:
        list(bad.imap_unordered([(1,)]))
    assert all(p.poll() is not None for p in bad.procs)  # closed, not kept
