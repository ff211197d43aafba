"""The README's shell blocks, taken from the file so tests run exactly what it says."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def section(title: str) -> str:
    """The README's ``## title`` section, up to the next ``## `` heading."""
    text = (REPO / "README.md").read_text()
    start = text.index(f"## {title}")
    end = text.find("\n## ", start + 3)
    return text[start : end if end >= 0 else None]


def shell_blocks(text: str) -> list[str]:
    return re.findall(r"^```sh\n(.*?)^```", text, re.S | re.M)


def run_script(script: str, cwd: Path, timeout: float = 900) -> str:
    """Run ``script`` with bash (``set -e``), ``tagtrail`` on the PATH; returns its output."""
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
        "PYTHONUNBUFFERED": "1",
    }
    done = subprocess.run(
        ["bash", "-c", "set -e\n" + script],
        cwd=cwd,
        env=env,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        timeout=timeout,
    )
    assert done.returncode == 0, f"{script}\n---\n{done.stdout[-6000:]}"
    assert "error:" not in done.stdout, done.stdout[-6000:]
    return done.stdout
