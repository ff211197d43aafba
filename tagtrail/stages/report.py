"""Stage ``report``: distance and heading of the (aligned) query against the reference (§3.2.1).

``trajectory`` mode: every query pose is associated with its nearest reference sample (Eq. 3.12)
and gets D (Eq. 3.13) and phi (Eq. 3.15, reference heading by Eq. 3.14). ``point`` mode (a robot
parked at a test pose): the query is reduced to its median position and circular-mean heading,
D is the distance to the nearest point of the reference polyline and the reference heading is
that segment's. ``auto`` picks ``point`` when the query's 95th-percentile radius about its
centroid is at most ``static_threshold_m``. Outputs follow SPEC ``relocalization.csv`` (with
``t_ns``) and ``summary.json``.

Point mode follows the original tool exactly (segment heading; at a vertex shared by two segments
the earlier segment), which reproduces its published LIMO results (PAPER Table 4.3) to < 0.1 mm
and 0.01° from the smoothed trajectories (tests/test_relocalize.py).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from pydantic import Field

from tagtrail.errors import DataError
from tagtrail.geometry.reference_path import (
    PathMatch,
    ReferencePath,
    capture_radius_p95,
    reduce_to_point,
    reference_plane,
)
from tagtrail.schemas.artifacts import columns, poses
from tagtrail.schemas.documents import AlignmentBlock, Summary
from tagtrail.stages.base import StageParams

INPUTS = {
    "trajectory": "align.trajectory",
    "ref_trajectory": "reference:smooth.trajectory",
    "alignment": "align.alignment",
}
OUTPUTS = ("relocalization", "summary")
SCOPE = "query"
RELOC_COLS = columns("report.relocalization")


class Params(StageParams):
    """``mode``: auto | trajectory | point; ``plane``: auto | xz | xy | yz (SPEC Conventions)."""

    mode: Literal["auto", "trajectory", "point"] = "auto"
    plane: Literal["auto", "xz", "xy", "yz"] = "auto"
    static_threshold_m: float = Field(0.20, gt=0)


def stats(x: ArrayLike) -> dict[str, float | None]:
    """``mean, median, p90, p95, max, rmse`` of a series (None when it is empty)."""
    a = np.asarray(x, dtype=np.float64)
    if a.size == 0:
        return dict.fromkeys(("mean", "median", "p90", "p95", "max", "rmse"))
    return {
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
        "p95": float(np.percentile(a, 95)),
        "max": float(a.max()),
        "rmse": float(np.sqrt(np.mean(a**2))),
    }


def relocalization_frame(t_ns: ArrayLike, t0_ns: int, m: PathMatch) -> pd.DataFrame:
    """SPEC relocalization columns (``t_ns`` int64, ``t_rel_s`` from ``t0_ns``, angles in deg)."""
    t = np.asarray(t_ns, dtype=np.int64)
    return pd.DataFrame(
        {
            "t_ns": t,
            "t_rel_s": (t - np.int64(t0_ns)).astype(np.float64) * 1e-9,
            "nearest_ref_idx": m.ref_idx.astype(np.int64),
            "distance_m": m.distance_m,
            "heading_error_deg": np.degrees(m.phi_rad),
            "query_heading_deg": np.degrees(m.query_heading_rad),
            "ref_heading_deg": np.degrees(m.ref_heading_rad),
            "query_u": m.query_uv[:, 0],
            "query_v": m.query_uv[:, 1],
            "ref_u": m.ref_uv[:, 0],
            "ref_v": m.ref_uv[:, 1],
        },
        columns=RELOC_COLS,
    )


def choose_mode(mode: str, query_uv: ArrayLike, static_threshold_m: float) -> str:
    """``point`` or ``trajectory``; ``auto`` = point when the capture's p95 radius ≤ threshold."""
    if mode != "auto":
        return mode
    return "point" if capture_radius_p95(query_uv) <= static_threshold_m else "trajectory"


def run(
    trajectory: pd.DataFrame,
    ref_trajectory: pd.DataFrame,
    alignment: AlignmentBlock,
    params: Params,
) -> dict[str, Any]:
    """D and phi of the query ``trajectory`` (already in the reference world) (Eqs. 3.11–3.16).

    Returns ``relocalization`` (one row per query pose, or one row in point mode) and
    ``summary`` (SPEC summary.json: mode, plane, n, distance_m and abs_heading_error_deg
    statistics, and the ``alignment`` block).
    """
    if len(trajectory) == 0:
        raise DataError("the query trajectory is empty: nothing to relocalize")
    if len(ref_trajectory) < 2:
        raise DataError("the reference trajectory needs at least 2 poses")
    ref_P, ref_R = poses(ref_trajectory)
    path = ReferencePath(ref_P, reference_plane(params.plane, ref_P, ref_R))
    uv, heading = path.planar(*poses(trajectory))
    t_ns = trajectory["t_ns"].to_numpy(np.int64)
    mode = choose_mode(params.mode, uv, params.static_threshold_m)
    if mode == "point":
        p, h, i = reduce_to_point(uv, heading)
        match = path.query_polyline(p[None], [h])
        t_rows = t_ns[[i]]
    else:
        match = path.query_uv(uv, heading)
        t_rows = t_ns
    reloc = relocalization_frame(t_rows, int(t_ns[0]), match)
    summary = {
        "mode": mode,
        "plane": params.plane,
        "n": len(reloc),
        "distance_m": stats(reloc["distance_m"]),
        "abs_heading_error_deg": stats(np.abs(reloc["heading_error_deg"])),
        "alignment": alignment,
    }
    return {"relocalization": reloc, "summary": Summary.model_validate(summary)}
