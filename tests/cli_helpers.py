"""Shared by the CLI tests: a small simulated detections recording, the one-error-line check,
``tagtrail`` as a subprocess, and what a killed or interrupted command may leave behind."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tagtrail.commands.demo import template
from tagtrail.sim import simulate

REPO = Path(__file__).resolve().parents[1]
TEMP = re.compile(r"^\..+\.[a-z0-9_]{8}$")  # mkstemp's names: a killed atomic write's leftovers

# The `room` recordings under bags/ (a test copies them there): the reference, and query_1 parked
# and localized against the reference's map.
ROOM_QUERY_PIPELINE = """datasets:
  reference: {source: bags/reference}
  query_1:
    source: bags/query_1
    inputs:
      trajectory.tag_map: reference:optimize.tag_map
      trajectory.map_report: reference:optimize.report
      align.tag_map: reference:optimize.tag_map
stages:
  pnp: {tag_size: 0.16}
"""


def detection_bags(root: Path) -> Path:
    """The `room` recordings (reference + parked queries) as sqlite3 detection bags in ``root``."""
    simulate("room", root, frames=40, query_frames=5, detections=True, storage="sqlite3")
    return root


def demo_project(folder: Path, data: Path) -> Path:
    """``folder`` with the demo's pipeline.yaml (a reference and three parked queries) reading
    the `room` recordings in ``data``."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "pipeline.yaml").write_text(template().replace("source: data/", f"source: {data}/"))
    return folder


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    """The single ``error: …`` line a failed command printed on stderr."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def terminal_signals() -> None:
    """A child's ``preexec_fn``: SIGINT, SIGTERM and SIGHUP at their defaults, as under a
    terminal, also when the tests run where they are ignored (a background job, ``nohup``):
    tagtrail keeps an ignored signal ignored, so a signal test would see it do nothing."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)


def cli_env(fault: str | None = None) -> dict[str, str]:
    """The environment of a ``tagtrail`` subprocess: this checkout first on PYTHONPATH, and
    ``TAGTRAIL_FAULT`` (``tagtrail/faults.py``) set to ``fault`` alone."""
    env = {k: v for k, v in os.environ.items() if k != "TAGTRAIL_FAULT"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    if fault:
        env["TAGTRAIL_FAULT"] = fault
    return env


def tagtrail(
    cwd: Path, *args: str, fault: str | None = None, timeout: float = 300
) -> subprocess.CompletedProcess[str]:
    """``tagtrail ARGS`` run in ``cwd`` by a fresh interpreter (the console script's entry)."""
    return subprocess.run(
        [sys.executable, "-m", "tagtrail.cli", *args],
        cwd=cwd,
        env=cli_env(fault),
        capture_output=True,
        text=True,
        timeout=timeout,
        preexec_fn=terminal_signals,
    )


def files(root: Path) -> dict[str, bytes]:
    """Every file below ``root`` with its bytes."""
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def stray(project: Path) -> list[str]:
    """Temporary files and folders a killed or failed write may leave behind."""
    left = [str(p.relative_to(project)) for p in project.rglob("*") if TEMP.match(p.name)]
    tmp = project / "artifacts" / "tmp"
    return left + ([str(p) for p in tmp.iterdir()] if tmp.is_dir() else [])


def children(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux ``/proc``)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*/children"):
        try:
            out += [int(c) for c in task.read_text().split()]
        except OSError:  # the thread ended meanwhile
            continue
    return out


def alive(pid: int) -> bool:
    """``pid`` runs (a zombie, ended but not yet reaped, does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"
