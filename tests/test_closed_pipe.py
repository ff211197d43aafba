"""A closed stdout pipe (``tagtrail show optimize | head -1``) ends a command quietly, with the
exit code of a process SIGPIPE ended (141, as ``git`` or ``yes`` under a shell), not with
``error: unexpected BrokenPipeError`` or Python's ``Exception ignored … BrokenPipeError``.

Each command runs as a real ``tagtrail`` process whose stdout is a real pipe: read up to one
line, as ``head -1`` does, then closed, or closed before the command starts, so that its first
write finds no reader whatever it prints (the pipe's buffer cannot hide the case)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

import tagtrail.cli

REPO = Path(__file__).resolve().parents[1]
SIGPIPE_EXIT = 141  # 128 + SIGPIPE: what a shell reports for a process a closed pipe ended


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory, room_bags: Path) -> Path:
    """The `room` detection recordings mapped (reference + a parked query), run in-process."""
    root = tmp_path_factory.mktemp("pipe")
    doc = {
        "datasets": {
            "reference": {"source": str(room_bags / "reference")},
            "query_1": {"source": str(room_bags / "query_1")},
        },
        "stages": {"pnp": {"tag_size": 0.16}},
    }
    (root / "pipeline.yaml").write_text(yaml.safe_dump(doc))
    assert tagtrail.cli.main(["run", "-p", str(root / "pipeline.yaml")]) == 0
    return root


def start(cwd: Path, argv: list[str], read_first_line: bool) -> tuple[subprocess.Popen[str], int]:
    """``tagtrail ARGV`` with stdout a pipe (closed at once unless ``read_first_line``); the
    process and the pipe's reading end (-1 when closed)."""
    exe = shutil.which("tagtrail", path=str(Path(sys.executable).parent))
    cmd = [exe] if exe else [sys.executable, "-m", "tagtrail.cli"]
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    read_end, write_end = os.pipe()
    if not read_first_line:
        os.close(read_end)  # no reader from the start: the first write fails
        read_end = -1
    try:
        proc = subprocess.Popen(
            [*cmd, *argv],
            cwd=cwd,
            env={**os.environ, "PYTHONPATH": path},
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
        )
    finally:
        os.close(write_end)
    return proc, read_end


# (argv, exit code): the commands write to stdout; argparse prints help itself, ignores the
# failed write and exits 0; a user error keeps its one line on stderr and exit 2
CASES = [
    (["show", "optimize"], SIGPIPE_EXIT),
    (["run"], SIGPIPE_EXIT),
    (["--help"], 0),
    (["show", "optimise"], 2),
]


def test_a_reader_gone_before_the_first_write_ends_each_command_quietly(project: Path) -> None:
    procs = [(argv, rc, start(project, argv, False)[0]) for argv, rc in CASES]  # in parallel
    for argv, rc, proc in procs:
        _, err = proc.communicate(timeout=120)
        if rc == 2:
            lines = err.strip().splitlines()
            assert proc.returncode == 2 and len(lines) == 1, (argv, proc.returncode, err)
            assert lines[0].startswith("error: ") and "did you mean" in lines[0], (argv, err)
        else:
            assert (proc.returncode, err) == (rc, ""), argv


def test_head_1_ends_the_command_quietly(project: Path) -> None:
    """As ``tagtrail show optimize | head -1``: one line read, then the pipe closed; the rest of
    the output finds no reader (141) or was written before it left (0), quietly either way."""
    proc, read_end = start(project, ["show", "optimize"], True)
    with os.fdopen(read_end, "rb") as reader:  # head -1
        first = reader.readline()
    _, err = proc.communicate(timeout=120)
    assert first.strip(), "the command printed nothing on stdout"
    assert err == "" and proc.returncode in (0, SIGPIPE_EXIT), (proc.returncode, err)
