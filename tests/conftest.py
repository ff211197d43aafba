"""Shared fixtures. Real third-party data lives in ../shared/realdata beside the repo: tests that
need it skip when it is absent (a user's clone), except under CI=true, where absence fails."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata"


@pytest.fixture(scope="session")
def realdata() -> Path:
    if not REALDATA.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"real data folder {REALDATA} is missing (required under CI=true)")
        pytest.skip(f"real data folder {REALDATA} not present")
    return REALDATA
