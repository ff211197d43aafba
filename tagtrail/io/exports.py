"""SPEC output files written from a dataset's artifacts (called by the runner after a run).

Each exporter takes ``get(stage, output)`` (artifact or None), the dataset's output folder and
its name; it writes what its artifacts allow and returns whether it wrote anything.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from tagtrail.io import layouts

Getter = Callable[[str, str], Any]


def trajectories(get: Getter, folder: Path, dataset: str) -> bool:
    wrote = False
    smooth = get("smooth", "trajectory")
    if smooth is not None:
        layouts.write_trajectory_csv(folder / "trajectory.csv", smooth)
        layouts.write_trajectory_tum(folder / "trajectory.tum", smooth)
        wrote = True
    raw = get("trajectory", "trajectory")
    if raw is not None:
        layouts.write_trajectory_csv(folder / "trajectory_raw.csv", raw)
        wrote = True
    return wrote


def tag_map(get: Getter, folder: Path, dataset: str) -> bool:
    tags = get("optimize", "tag_map")
    report = get("optimize", "report")
    if tags is None or report is None:
        return False
    layouts.write_tag_map(folder, tags, int(report["anchor_id"]))
    return True


EXPORTERS: list[Callable[[Getter, Path, str], bool]] = [trajectories, tag_map]
