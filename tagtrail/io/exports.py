"""SPEC output files written from a dataset's artifacts (called by the runner after a run).

Each exporter takes ``get(stage, output, reference=False)`` (the dataset's — or the reference
dataset's — up-to-date artifact, or None), the dataset's output folder and its name; it writes
what its artifacts allow (atomically) and returns whether it wrote anything.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tagtrail.io import layouts

Getter = Callable[..., Any]
# Modules whose code shapes the files (with this one): a change re-exports.
DEPENDS = ("tagtrail.io.layouts", "tagtrail.io.reloc_files", "tagtrail.relocalize")


def trajectories(get: Getter, folder: Path, dataset: str) -> bool:
    """``trajectory.csv``, ``trajectory.tum`` (smoothed) and ``trajectory_raw.csv``."""
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
    """``tag_map.yaml`` and ``tag_map.csv``."""
    tags, report = get("optimize", "tag_map"), get("optimize", "report")
    if tags is None or report is None:
        return False
    layouts.write_tag_map(folder, tags, int(report["anchor_id"]))
    return True


def diagnostics(get: Getter, folder: Path, dataset: str) -> bool:
    """``diagnostics.csv`` (metric,value), a superset of the original ``diagnostico_erros.csv``."""
    frames, dets = get("extract", "frames"), get("extract", "detections")
    obs, graph = get("pnp", "observations"), get("edges", "graph")
    edges, tags = get("edges", "edges"), get("optimize", "tag_map")
    report = get("optimize", "report")
    traj = get("smooth", "trajectory")
    if frames is None or obs is None:
        return False
    rows: list[tuple[str, Any]] = [
        ("frames_total", len(frames) if len(frames) else obs["frame_idx"].nunique()),
        ("frames_with_detections", int(obs["frame_idx"].nunique())),
        ("frames_with_pose", len(traj) if traj is not None else ""),
        ("detections", len(dets) if dets is not None and len(dets) else len(obs)),
        ("tags_detected", int(obs["tag_id"].nunique())),
        ("tags_mapped", len(tags) if tags is not None else ""),
        ("tags_dropped", len(graph["dropped"]) if graph is not None else ""),
        ("anchor_tag", f"tag36h11:{report['anchor_id']}" if report is not None else ""),
        ("pairwise_edges", len(edges) if edges is not None else ""),
        ("map_residual_rms_t_m", report.get("rms_t_m", "") if report is not None else ""),
        ("map_residual_rms_r_deg", report.get("rms_r_deg", "") if report is not None else ""),
    ]
    text = "metric,value\n" + "".join(f"{k},{v}\n" for k, v in rows)
    layouts.atomic_write_text(folder / "diagnostics.csv", text)
    return True


def recording_map(get: Getter, folder: Path, dataset: str) -> bool:
    """``map.png`` of a recording: its tags and trajectory seen from above (plane auto)."""
    from tagtrail.io import reloc_files
    from tagtrail.stages import align, report

    traj, tags = get("smooth", "trajectory"), get("optimize", "tag_map")
    if traj is None or tags is None or len(traj) < 2 or get("report", "summary") is not None:
        return False
    plane = align.reference_plane("auto", traj)
    P, R = align.poses(traj)
    flip_v = bool(plane.n @ R[:, :, 1].mean(axis=0) > 0)
    empty = pd.DataFrame({c: np.zeros(0) for c in report.RELOC_COLS})
    reloc_files.write_map_png(
        folder / "map.png", plane.to_uv(P), np.zeros((0, 2)), empty,
        plane.to_uv(tags[["x_m", "y_m", "z_m"]].to_numpy()), tags["tag_id"].astype(int).tolist(),
        ("u", "v"), flip_v, f"{dataset}: trajectory and tag map (plane auto, seen from above)",
    )  # fmt: skip
    return True


def evaluation(get: Getter, folder: Path, dataset: str) -> bool:
    """``evaluation.json``: errors vs ground truth (datasets that have it)."""
    from tagtrail.runner.cache import pretty_json

    ev = get("eval", "evaluation")
    if ev is None:
        return False
    layouts.atomic_write_text(folder / "evaluation.json", pretty_json(ev))
    return True


def relocalization(get: Getter, folder: Path, dataset: str) -> bool:
    """``relocalization.csv``, ``summary.json``, ``relocalization.png``, ``map.png`` (queries)."""
    from tagtrail.relocalize import write_outputs

    reloc, summary = get("report", "relocalization"), get("report", "summary")
    q_traj, ref_traj = get("align", "trajectory"), get("smooth", "trajectory", reference=True)
    if reloc is None or summary is None or q_traj is None or ref_traj is None:
        return False
    ref_tags = get("optimize", "tag_map", reference=True)
    write_outputs(folder, reloc, summary, q_traj, ref_traj, ref_tags, summary["plane"])
    return True


EXPORTERS: list[Callable[[Getter, Path, str], bool]] = [
    trajectories, tag_map, diagnostics, recording_map, evaluation, relocalization,
]
