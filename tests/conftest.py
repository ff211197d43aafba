"""Shared fixtures. Real third-party data lives in ../shared/realdata beside the repo: tests that
need it skip when it is absent (a user's clone), except under CI=true, where absence fails."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

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
def room_bags(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The `room` recordings (reference + parked queries) as sqlite3 detection bags, simulated
    once per session and shared: tests read them and never write into the folder."""
    return detection_bags(tmp_path_factory.mktemp("room_bags"))
