"""Shared by the CLI tests: a small simulated detections recording, the one-error-line check."""

from __future__ import annotations

from pathlib import Path

import pytest

from tagtrail.sim import simulate


def detection_bags(root: Path) -> Path:
    """The `room` recordings (reference + parked queries) as sqlite3 detection bags in ``root``."""
    simulate("room", root, frames=40, query_frames=5, detections=True, storage="sqlite3")
    return root


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    """The single ``error: …`` line a failed command printed on stderr."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]
