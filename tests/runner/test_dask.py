"""The dask executor on a simulated recording: a 2-worker LocalCluster (processes) gives outputs
byte-identical to the local executor's; workers killed mid-run leave a store the rerun completes
from; without dask the command says in one line what to install. Addresses: 127.0.0.1 only."""

from __future__ import annotations

import importlib.util
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tagtrail.cli import main
from tagtrail.errors import SpecError
from tagtrail.runner import executors
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.sim import simulate
from tagtrail.stages import REGISTRY
from tests.cli_helpers import demo_project, one_error_line
from tests.runner.project import ALL, executed, write_project
from tests.runner.toy import copy_stages, load_registry

pytestmark = pytest.mark.slow  # Dask clusters (make test-all)

needs_dask = pytest.mark.skipif(
    importlib.util.find_spec("distributed") is None and os.environ.get("CI") != "true",
    reason="dask.distributed not installed (pip install -e '.[test]')",
)


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Rendered (compressed image) recordings: extract fans detection out to `tagtrail.pool`
    processes, here from inside dask's daemonic worker processes."""
    root = tmp_path_factory.mktemp("room")
    simulate("room", root, compressed=True, frames=60, query_frames=5)
    return root


def project(folder: Path, data: Path) -> Path:
    folder.mkdir()  # a new one
    return demo_project(folder, data)


def tagtrail(cwd: Path, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """The CLI in a fresh interpreter (`main_entry`: single-threaded BLAS, as users run it)."""
    return subprocess.run(
        [sys.executable, "-m", "tagtrail.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, **env},
    )


def files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def entries(folder: Path) -> set[str]:
    """The store's entries as ``stage/key``."""
    objects = folder / "artifacts" / "objects"
    return {f"{p.parent.name}/{p.name}" for p in objects.glob("*/*") if p.is_dir()}


def errors(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("error:")]


@pytest.fixture(scope="module")
def local(tmp_path_factory: pytest.TempPathFactory, data: Path) -> Path:
    """The project run by the local executor: what every dask run must reproduce."""
    folder = project(tmp_path_factory.mktemp("local") / "p", data)
    res = tagtrail(folder, "run", "-j", "2")
    assert res.returncode == 0, res.stderr
    return folder


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    """An existing 2-worker cluster on 127.0.0.1, as `dask scheduler` + `dask worker` give."""
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    with LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    ) as c:
        yield c


@needs_dask
def test_a_2_worker_local_cluster_matches_the_local_executor_byte_for_byte(
    tmp_path: Path, data: Path, local: Path
) -> None:
    b = project(tmp_path / "b", data)
    t0 = time.perf_counter()
    res = tagtrail(b, "run", "--executor", "dask", "-j", "2")
    took = time.perf_counter() - t0
    assert res.returncode == 0, res.stderr
    first = res.stdout.splitlines()[0]
    assert first.startswith(
        "dask: a local cluster of 2 worker processes, dashboard http://127.0.0.1:"
    ), first
    assert "warning" not in res.stdout  # single-threaded BLAS in the workers
    assert files(b / "outputs") == files(local / "outputs")
    assert entries(b) == entries(local) and len(entries(b)) == 34
    again = tagtrail(b, "run")  # the local executor accepts what the workers wrote
    assert again.returncode == 0 and "0 ran" in again.stdout, again.stdout
    print(f"dask (2-worker LocalCluster, cluster start included) {took:.1f}s")


@needs_dask
def test_a_worker_killed_mid_write_leaves_a_store_the_rerun_completes(
    tmp_path: Path, data: Path, local: Path, cluster: Any
) -> None:
    c = project(tmp_path / "c", data)
    res = tagtrail(
        c,
        "run",
        "--executor",
        "dask",
        "-j",
        "2",
        TAGTRAIL_FAULT="kill@store:optimize",  # SIGKILL half-way into the entry
        # fail at the first death, and only the task that was running there
        DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES="0",
        DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION="1.0",
    )
    assert res.returncode == 1, res.stderr
    (line,) = errors(res.stderr)
    assert line.startswith("error: stage optimize [") and "WorkerDied: the dask worker" in line
    assert any((c / "artifacts" / "tmp").iterdir())  # the half-written entries
    assert not any(e.startswith("optimize/") for e in entries(c))

    rerun = tagtrail(c, "run", "--scheduler", cluster.scheduler_address)  # a warm cluster
    assert rerun.returncode == 0, rerun.stderr
    assert "extract [reference]" in rerun.stdout and "cached" in rerun.stdout
    assert files(c / "outputs") == files(local / "outputs")
    assert entries(c) == entries(local)
    assert not any((c / "artifacts" / "tmp").iterdir())


def _kill_a_busy_worker(client: Any, done: threading.Event, killed: list[int]) -> None:
    """SIGKILL the first worker seen running a task (its nanny restarts it)."""
    deadline = time.time() + 120
    while not done.is_set() and time.time() < deadline:
        busy = [w for w, keys in client.processing().items() if keys]
        if busy:
            pid = client.run(os.getpid, workers=busy[:1])[busy[0]]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            return
        time.sleep(0.01)


@needs_dask
def test_a_worker_killed_by_a_signal_is_replaced_and_the_run_matches(
    tmp_path: Path, data: Path, local: Path, cluster: Any
) -> None:
    d = project(tmp_path / "d", data)
    lines: list[str] = []
    with executors.dask_session(cluster.scheduler_address, echo=lines.append) as session:
        runner = Runner(
            load_pipeline(d / "pipeline.yaml", REGISTRY),
            jobs=2,
            executor="dask",
            scheduler=cluster.scheduler_address,
        )
        done, killed = threading.Event(), []
        killer = threading.Thread(target=_kill_a_busy_worker, args=(session.client, done, killed))
        killer.start()
        try:
            states = runner.run()
        finally:
            done.set()
            killer.join()
    assert killed, "no worker was busy"
    assert all(s.status == "ran" for s in states) and len(states) == 34
    assert lines[0].startswith(f"dask: {cluster.scheduler_address} (2 workers), dashboard ")
    exported = tagtrail(d, "run")  # export (and a no-op run) in a CLI process
    assert exported.returncode == 0 and "0 ran" in exported.stdout, exported.stderr
    assert files(d / "outputs") == files(local / "outputs")


@needs_dask
def test_a_recordings_frame_chunks_are_tasks_of_the_cluster(
    tmp_path: Path, data: Path, local: Path, cluster: Any
) -> None:
    """extract's chunks of frames run as tasks of their own (``detect-chunk-*``) wherever the
    cluster puts them, not only in the worker that runs the node; the outputs do not change."""
    from distributed import Client, get_task_stream

    f = project(tmp_path / "f", data)
    with Client(cluster.scheduler_address) as client, get_task_stream(client) as stream:
        runner = Runner(
            load_pipeline(f / "pipeline.yaml", REGISTRY, overrides=["extract.chunk_size=8"]),
            jobs=2,
            executor="dask",
            scheduler=cluster.scheduler_address,
        )
        assert all(s.status == "ran" for s in runner.run())
    chunks = [t for t in stream.data if t["key"].startswith("detect-chunk-")]
    assert len(chunks) == -(-60 // 8) + 3  # reference: 60 frames; each query: 5
    exported = tagtrail(f, "run")
    assert exported.returncode == 0 and "0 ran" in exported.stdout, exported.stderr
    assert files(f / "outputs") == files(local / "outputs")


@needs_dask
def test_an_existing_scheduler_from_the_command_line(
    tmp_path: Path, data: Path, local: Path, cluster: Any
) -> None:
    e = project(tmp_path / "e", data)
    res = tagtrail(e, "run", "--scheduler", cluster.scheduler_address)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith(f"dask: {cluster.scheduler_address} (2 workers), dashboard")
    assert files(e / "outputs") == files(local / "outputs")


@needs_dask
def test_toy_stages_loaded_from_files_run_on_the_workers(tmp_path: Path, cluster: Any) -> None:
    """Stage modules a worker cannot import by name (a registry built from files) are loaded
    from their file; the entries equal a local run's."""
    stages = copy_stages(tmp_path / "stages")
    pipes = [write_project(tmp_path / name) for name in ("local", "dask")]
    local = Runner(load_pipeline(pipes[0], load_registry(stages)), jobs=2)
    remote = Runner(
        load_pipeline(pipes[1], load_registry(stages)),
        jobs=2,
        executor="dask",
        scheduler=cluster.scheduler_address,
    )
    assert executed(local.run()) == ALL
    assert executed(remote.run()) == ALL
    assert entries(tmp_path / "local") == entries(tmp_path / "dask")


def test_without_dask_the_command_says_what_to_install(
    tmp_path: Path,
    data: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    f = project(tmp_path / "f", data)
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails
    code = main(["run", "-p", str(f / "pipeline.yaml"), "--executor", "dask"])
    assert code == 2
    assert one_error_line(capsys) == (
        "error: --executor dask needs dask.distributed: pip install 'tagtrail[dask]'"
    )
    assert not (f / "artifacts" / "objects").exists()


def test_a_scheduler_needs_the_dask_executor(
    tmp_path: Path, data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    g = project(tmp_path / "g", data)
    code = main(
        [
            "run",
            "-p",
            str(g / "pipeline.yaml"),
            "--executor",
            "local",
            "--scheduler",
            "tcp://127.0.0.1:8786",
        ]
    )
    assert code == 2
    assert one_error_line(capsys) == "error: --scheduler needs --executor dask"


@needs_dask
def test_an_unreachable_scheduler_is_one_line(
    tmp_path: Path,
    data: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    h = project(tmp_path / "h", data)
    monkeypatch.setattr(executors, "CONNECT_TIMEOUT_S", 2.0)
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(["run", "-p", str(h / "pipeline.yaml"), "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert code == 2
    line = one_error_line(capsys)
    assert line.startswith(f"error: cannot reach the dask scheduler at tcp://127.0.0.1:{port}")


def test_a_worker_running_other_stage_code_refuses(tmp_path: Path) -> None:
    """The worker checks the runner's code fingerprint before running a node."""
    pipe = write_project(tmp_path / "proj")
    runner = Runner(load_pipeline(pipe, load_registry(copy_stages(tmp_path / "stages"))))
    node = next(n for n in runner.graph.order if n.stage == "load")
    record = runner.record_for(node, {})
    assert record is not None
    task = runner._task(node, "k" * 64, {**record, "code": "0" * 64}, {})
    del sys.modules[task.module]  # as in a fresh worker: found through its file
    with pytest.raises(SpecError, match="runs other code for stage load"):
        executors.run_remote(task)
    assert task.module in sys.modules
