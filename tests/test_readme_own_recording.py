"""The README's "Your own recording" block, run as written on a fresh copy of real photos.

The block's ``photos`` folder is the swatbotics loop (72 hand-held photos of 20 wall tags,
0.127 m, its ``camera.yaml`` inside), copied from ``../shared/realdata``; the files the
README's "What you get" table names for a reference recording must then exist.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest

from tests.readme import REPO, run_script, section, shell_blocks

PHOTOS = REPO.parent / "shared" / "realdata" / "swatbotics_mapping_feb_2014" / "images"
# What a reference without ground truth gets (the table also lists the query and eval files).
REFERENCE_FILES = {
    "trajectory.csv",
    "trajectory.tum",
    "trajectory_raw.csv",
    "trajectory_std.csv",
    "trajectory_evidence.csv",
    "tag_map.yaml",
    "tag_map.csv",
    "map.png",
    "diagnostics.csv",
}


def table_files() -> set[str]:
    """File names in the first column of the "What you get" table."""
    names: set[str] = set()
    for row in re.findall(r"^\| (`[^|]+`) \|", section("What you get"), re.M):
        names.update(re.findall(r"`([^`]+)`", row))
    return names


@pytest.mark.slow  # the README's commands on a real photo set (~7 s): make test-all
def test_own_recording_block_runs_on_real_photos(tmp_path: Path) -> None:
    if not PHOTOS.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"{PHOTOS} is missing")
        pytest.skip("../shared/realdata is not here")
    blocks = shell_blocks(section("Your own recording"))
    assert len(blocks) == 1
    script = blocks[0]
    assert "tagtrail init --reference photos --tag-size 0.127" in script
    shutil.copytree(PHOTOS, tmp_path / "photos")
    out = run_script(script, tmp_path)
    assert REFERENCE_FILES <= table_files()
    folder = tmp_path / "outputs" / "reference"
    missing = {f for f in REFERENCE_FILES if not (folder / f).is_file()}
    assert not missing, (missing, out[-3000:])
    assert "up to date" in out  # status after run
    assert "optimize.tag_map" in out  # show optimize
    rows = (folder / "tag_map.csv").read_text().splitlines()
    assert len(rows) == 21  # the loop's 20 tags
