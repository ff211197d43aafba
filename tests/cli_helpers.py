"""Shared by the CLI tests: a small simulated detections recording, the one-error-line check."""

from __future__ import annotations

from pathlib import Path

import pytest

from tagtrail.sim import simulate

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


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    """The single ``error: …`` line a failed command printed on stderr."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]
