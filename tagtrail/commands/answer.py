"""The answer ``tagtrail run`` ends with: one short block per dataset, read from its outputs.

Read from the files the run exported into ``outputs/<dataset>/`` (``diagnostics.csv``,
``evaluation.json``, ``summary.json``, ``relocalization.csv``), never from the stages: what is
printed is what a user finds in the folder. A reference: tags mapped, frames posed, the corner
RMS (px) and, with ground truth, the trajectory's and the map's position errors. A query: D and
phi (the parked values in point mode, mean / max in trajectory mode) and which reference
heading phi compares with (``summary.json``'s ``ref_heading``: the nearest segment's in point
mode, the matched sample's in trajectory mode, with the association that matched it).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

HEADING = {  # summary.json's ref_heading
    "segment": "phi vs the heading of the nearest reference segment",
    "sample": "phi vs the reference heading at the matched sample",
}


def _diagnostics(folder: Path) -> dict[str, str]:
    try:
        with open(folder / "diagnostics.csv", newline="") as f:
            return {r["metric"]: r["value"] for r in csv.DictReader(f)}
    except (OSError, KeyError):
        return {}


def _json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _num(text: str | None) -> float | None:
    try:
        return float(text) if text not in (None, "") else None
    except ValueError:
        return None


def _mm(block: dict[str, Any]) -> str:
    """``rmse X mm, max Y mm`` of an error block in metres."""
    return f"rmse {1000 * block['rmse']:.1f} mm, max {1000 * block['max']:.1f} mm"


def _truth(folder: Path) -> list[str]:
    """Errors against ground truth (``evaluation.json``), when the dataset has it."""
    ev = _json(folder / "evaluation.json")
    if not isinstance(ev, dict):
        return []
    parts = []
    for what, label in (("trajectory", "trajectory"), ("tags", "tags")):
        block = ev.get(what) or {}
        pos = block.get("position_m") or {}
        if pos.get("rmse") is not None and pos.get("max") is not None:
            parts.append(f"{label} {_mm(pos)}")
    return [f"  vs ground truth: {'; '.join(parts)}"] if parts else []


def reference_block(dataset: str, folder: Path) -> list[str]:
    """Tags mapped, frames posed, corner RMS, errors vs ground truth."""
    diag = _diagnostics(folder)
    if not diag:
        return []
    rms = _num(diag.get("joint_corner_rms_px"))
    if rms is None:
        rms = _num(diag.get("frame_reproj_px_median"))
    rms_text = "" if rms is None else f", corner RMS {rms:.2f} px"
    posed, total = diag.get("frames_with_pose") or "?", diag.get("frames_total") or "?"
    head = (
        f"{dataset}: {diag.get('tags_mapped') or '?'} tags mapped, {posed}/{total} frames "
        f"posed{rms_text}"
    )
    return [head, *_truth(folder)]


def _parked(folder: Path) -> tuple[float, float] | None:
    """D (m) and signed phi (deg) of the single row of a point-mode ``relocalization.csv``."""
    try:
        with open(folder / "relocalization.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        if len(rows) != 1:
            return None
        return float(rows[0]["distance_m"]), float(rows[0]["heading_error_deg"])
    except (OSError, KeyError, ValueError):
        return None


def query_block(dataset: str, folder: Path) -> list[str]:
    """D and phi of a query, and which heading phi compares with."""
    summary = _json(folder / "summary.json")
    if not isinstance(summary, dict) or "distance_m" not in summary:
        return []
    mode = str(summary.get("mode", ""))
    d, phi = summary["distance_m"], summary["abs_heading_error_deg"]
    parked = _parked(folder) if mode == "point" else None
    if parked is not None:
        text = f"{dataset}: parked (point mode): D = {parked[0]:.4f} m, phi = {parked[1]:+.2f} deg"
    else:
        text = (
            f"{dataset}: {mode} mode, {summary.get('n', '?')} poses: D mean {d['mean']:.4f} m, "
            f"max {d['max']:.4f} m; |phi| mean {phi['mean']:.2f} deg, max {phi['max']:.2f} deg"
        )
    ref = summary.get("ref_heading") or ("segment" if mode == "point" else "sample")
    how = (
        f"{summary['association']} association, "
        if ref == "sample" and summary.get("association")
        else ""
    )
    return [
        text,
        f"  {HEADING.get(ref, 'phi vs the reference heading')} "
        f"({how}plane {summary.get('plane', '?')})",
    ]


def answer_text(written: dict[str, Path], reference: str) -> str:
    """The closing block of ``tagtrail run``: the reference first, then each query."""
    order = sorted(written, key=lambda ds: ds != reference)
    lines: list[str] = []
    for ds in order:
        block = (
            reference_block(ds, written[ds]) if ds == reference else query_block(ds, written[ds])
        )
        lines += block
    return "\n".join(["== answer", *lines]) if lines else ""
