"""Fixtures of the streaming tests: a zenoh router standing in for the robot's bridge, and a
simulated detections recording that several modules replay (read, never written)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from tagtrail.sim.simulate import simulate
from tests.stream.helpers import free_port, router


@pytest.fixture()
def bridge() -> Iterator[tuple[zenoh.Session, int]]:
    """A zenoh router on 127.0.0.1 (zenoh-bridge-ros2dds is one by default) and its port."""
    port = free_port()
    session = router(port)
    try:
        yield session, port
    finally:
        session.close()  # type: ignore[no-untyped-call]


@pytest.fixture(scope="session")
def detections(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 s of the `circle` scenario as /detections + /camera_info at 30 Hz (240 messages)."""
    return simulate("circle", tmp_path_factory.mktemp("circle_det"), frames=240, detections=True)[
        "circle"
    ]
