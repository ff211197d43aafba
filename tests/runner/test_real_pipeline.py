"""The runner on the real stages and a simulated recording: kill -9, rerun, identical outputs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.cli_helpers import demo_project, files


@pytest.fixture(scope="module")
def data(room_images: Path) -> Path:
    return room_images


def project(folder: Path, data: Path) -> Path:
    return demo_project(folder, data)


def tagtrail(cwd: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "tagtrail.cli", *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.slow
def test_kill_9_then_rerun_gives_byte_identical_outputs(tmp_path: Path, data: Path) -> None:
    a = project(tmp_path / "a", data)
    out, err = tagtrail(a, "run").communicate(timeout=300)
    assert "error" not in err.lower(), err

    b = project(tmp_path / "b", data)
    proc = tagtrail(b, "run", "-j", "2")
    marker = b / "artifacts" / "runs" / "reference" / "extract.json"
    deadline = time.time() + 120
    while not marker.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    time.sleep(0.15)  # into pnp/edges of the reference and the queries' extract
    assert proc.poll() is None, "the run finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    rerun = tagtrail(b, "run")
    out, err = rerun.communicate(timeout=300)
    assert rerun.returncode == 0, err
    assert "cached" in out  # what finished before the kill is reused
    assert files(a / "outputs") == files(b / "outputs")
    assert not any((b / "artifacts" / "tmp").iterdir())
    second = tagtrail(b, "run")
    out, _ = second.communicate(timeout=120)
    assert " ran " not in out and "0 ran" in out
