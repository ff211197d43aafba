"""Shared fixtures. Real third-party data lives in ../shared/realdata beside the repo: tests that
need it skip when it is absent (a user's clone), except under CI=true, where absence fails."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from tagtrail.sim import simulate
from tests.cli_helpers import detection_bags

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata"


@pytest.fixture(scope="session")
def realdata() -> Path:
    if not REALDATA.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"real data folder {REALDATA} is missing (required under CI=true)")
        pytest.skip(f"real data folder {REALDATA} not present")
    return REALDATA


@pytest.fixture(scope="session")
def room_images(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The `room` recordings rendered as compressed images (reference 90 frames, parked queries
    8), simulated once per session: read, never written (the crash tests' input)."""
    root = tmp_path_factory.mktemp("room_images")
    simulate("room", root, compressed=True, frames=90, query_frames=8)
    return root


def _listing(root: Path) -> dict[str, tuple[int, int]]:
    return {
        str(p.relative_to(root)): (p.lstat().st_size, p.lstat().st_mtime_ns)
        for p in root.rglob("*")
    }


@pytest.fixture(scope="session")
def room_bags(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The `room` recordings (reference + parked queries) as sqlite3 detection bags, simulated
    once per session and shared: tests read them or copy them (``shutil.copytree``, 3 ms) and
    never write into the folder, which the session's end checks."""
    root = detection_bags(tmp_path_factory.mktemp("room_bags"))
    before = _listing(root)
    yield root
    assert _listing(root) == before, f"a test wrote into the shared {root}: copy it first"
