"""Fixtures of the simulator tests: small simulated recordings, shared by the session."""

from __future__ import annotations

from pathlib import Path

import pytest

from tagtrail.sim import simulate
from tests.sim.helpers import SMALL


@pytest.fixture(scope="session")
def room_mcap(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The room scenario, raw rgb8 images, MCAP, 48-frame loop, 4-frame queries."""
    return simulate("room", tmp_path_factory.mktemp("room_mcap"), **SMALL)


@pytest.fixture(scope="session")
def room_detections(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The room scenario as /detections + /camera_info, sqlite3, more frames (cheap)."""
    out = tmp_path_factory.mktemp("room_det")
    return simulate(
        "room", out, frames=300, query_frames=10, detections=True, storage="sqlite3", seed=5
    )
