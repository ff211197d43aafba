"""Ctrl-C under ``tagtrail run --executor dask``: the command ends with its one ``interrupted``
line and nothing after it — no worker tracebacks (the workers of the local cluster were in the
terminal's foreground process group and died of the SIGINT), no shutdown chatter, no warning of
leaked semaphores — and leaves no worker process behind.

A real ``tagtrail`` process in a session of its own gets SIGINT on its whole process group, as a
terminal's Ctrl-C does, while its 2-worker LocalCluster (127.0.0.1) runs the stages of a rendered
recording."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tagtrail.commands.demo import template
from tagtrail.sim import simulate
from tests.cli_helpers import REPO, alive, children, terminal_signals

pytestmark = [
    pytest.mark.slow,  # a Dask cluster (make test-all)
    pytest.mark.skipif(
        importlib.util.find_spec("distributed") is None and os.environ.get("CI") != "true",
        reason="dask.distributed not installed (pip install -e '.[test]')",
    ),
]


def descendants(pid: int) -> set[int]:
    out: set[int] = set()
    for kid in children(pid):
        out |= {kid, *descendants(kid)}
    return out


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("dask_interrupt")
    simulate("room", root / "data", compressed=True, frames=60, query_frames=5)
    (root / "pipeline.yaml").write_text(template())
    return root


@pytest.mark.parametrize("after", ["dask:", "extract ["])
def test_ctrl_c_under_dask_ends_with_one_line_and_no_worker_output(
    project: Path, after: str
) -> None:
    """SIGINT once the cluster is up (``dask: …`` printed), and once the first node finished."""
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "tagtrail.cli", "run", "--executor", "dask", "-j", "2", "--force"],
        cwd=project,
        env={**os.environ, "PYTHONPATH": path},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=terminal_signals,
    )
    assert proc.stdout is not None
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if line.startswith(after):
            break
    workers = descendants(proc.pid)
    assert workers, "the local cluster started no worker process"
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert any(line.startswith(after) for line in seen), "".join(seen) + out
    lines = [ln for ln in err.splitlines() if not ln.startswith(("INFO ", "WARNING "))]
    assert proc.returncode == 130, err
    assert lines[-1:] == ["interrupted"] and lines.count("interrupted") == 1, err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert "leaked" not in err and "error:" not in err, err
    deadline = time.monotonic() + 5
    while any(alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [w for w in workers if alive(w)], "worker processes outlived the command"
