"""Stage ``report``: distance and heading of the (aligned) query against the reference (§3.2.1).

``trajectory`` mode: every query pose is associated with its nearest reference sample (Eq. 3.12)
and gets D (Eq. 3.13) and phi (Eq. 3.15, reference heading by Eq. 3.14). ``point`` mode (a robot
parked at a test pose): the query is reduced to its median position and circular-mean heading,
D is the distance to the nearest point of the reference polyline and the reference heading is
that segment's. ``auto`` picks ``point`` when the query's 95th-percentile radius about its
centroid is at most ``static_threshold_m``. Outputs follow SPEC ``relocalization.csv`` (with
``t_ns``) and ``summary.json``.

Beside D and phi, each row carries what a path tracker steers on (signed cross-track error,
progress along the path, curvature, a lookahead point, a ``lost`` flag:
:mod:`tagtrail.geometry.association`). ``association`` chooses k* in trajectory mode:
``progress`` (default: the nearest sample near the previous match, so that a path crossing itself
does not make k* jump branch) or ``nearest`` (Eq. 3.12 exactly, the paper's). Point mode has one
pose and no previous match: it always takes the nearest point of the polyline.

Point mode follows the original tool exactly (segment heading; at a vertex shared by two segments
the earlier segment), which reproduces its published LIMO results (PAPER Table 4.3) to < 0.1 mm
and 0.01° from the smoothed trajectories (tests/test_relocalize.py).
"""

from __future__ import annotations

import json
from typing import Any, Literal

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike
from pydantic import Field

from tagtrail.errors import DataError
from tagtrail.geometry.association import PathTracker, Track, TrackParams
from tagtrail.geometry.reference_path import (
    PathMatch,
    ReferencePath,
    capture_radius_p95,
    reduce_to_point,
    reference_plane,
)
from tagtrail.schemas.artifacts import columns, poses
from tagtrail.schemas.documents import AlignmentBlock, Summary
from tagtrail.stages.base import Export, ExportFiles, Metric, StageParams

INPUTS = {
    "trajectory": "align.trajectory",
    "ref_trajectory": "reference:smooth.trajectory",
    "alignment": "align.alignment",
}
OUTPUTS = ("relocalization", "summary")
SCOPE = "query"
RELOC_COLS = columns("report.relocalization")
RELOC_STATS = ("mean", "median", "p90", "p95", "max", "rmse")
METRICS = (
    *(
        m
        for stat in RELOC_STATS
        for m in (
            Metric(
                f"D.{stat}_m",
                "summary",
                ("distance_m", stat),
                "m",
                datasets="all",
                default=3 if stat == "mean" else 0,
            ),
            Metric(
                f"abs_phi.{stat}_deg",
                "summary",
                ("abs_heading_error_deg", stat),
                "deg",
                datasets="all",
                default=4 if stat == "mean" else 0,
            ),
        )
    ),
    Metric("alignment.rms_m", "summary", ("alignment", "rms_m"), "m", datasets="all"),
)
METRICS_HELP = (
    f"D.STAT_m and abs_phi.STAT_deg (relocalization; STAT: {', '.join(RELOC_STATS)}),"
    " alignment.rms_m"
)


class Params(StageParams):
    """``mode``: auto | trajectory | point; ``plane``: auto | xz | xy | yz (SPEC Conventions);
    ``association`` (trajectory mode): progress | nearest (Eq. 3.12); the tracker's lengths (m):
    ``lookahead_m`` (the lookahead point's distance ahead along the path), ``search_back_m`` /
    ``search_ahead_m`` (progress's window about the previous match), ``reacquire_m`` / ``lost_m``
    (re-acquire over the whole path when the window's match is this much farther than another /
    farther than ``lost_m``; ``lost`` beyond ``lost_m``), ``curvature_window_m``."""

    mode: Literal["auto", "trajectory", "point"] = "auto"
    """``trajectory``: D and phi per query pose against the nearest reference sample; ``point``: a
    parked robot, its median pose against the nearest reference segment; ``auto``: ``point``
    when the query stays within ``static_threshold_m``."""
    plane: Literal["auto", "xz", "xy", "yz"] = "auto"
    """Plane of D and phi (SPEC Conventions; ``auto``: fitted to the reference cameras; ``xy`` in
    a z-up world)."""
    static_threshold_m: float = Field(0.20, gt=0, le=100.0)
    """``auto`` picks ``point`` mode when the query's 95th-percentile radius about its centroid is
    at most this (m)."""
    association: Literal["progress", "nearest"] = "progress"
    """Trajectory mode: which reference sample a query pose is matched to: ``progress`` (the
    nearest within a window about the previous match, so a path that crosses itself is
    followed) or ``nearest`` (the nearest sample, Eq. 3.12)."""
    lookahead_m: float = Field(0.3, ge=0, le=100.0)
    """Distance (m) ahead along the path of the lookahead point."""
    search_back_m: float = Field(0.2, ge=0, le=1000.0)
    """``progress``: the window reaches this far (m) back along the path from the previous
    match."""
    search_ahead_m: float = Field(1.0, gt=0, le=1000.0)
    """``progress``: the window reaches this far (m) ahead along the path from the previous
    match."""
    reacquire_m: float = Field(0.25, gt=0, le=1000.0)
    """``progress``: search the whole path again when the window's match is this much (m) farther
    than another point of the path."""
    lost_m: float = Field(0.5, gt=0, le=1000.0)
    """``progress``: search the whole path again when the window's match is farther than this (m);
    a pose farther than this from the path is marked ``lost``."""
    curvature_window_m: float = Field(0.1, gt=0, le=100.0)
    """Length (m) of path over which the curvature is measured."""


def track_params(params: Params) -> TrackParams:
    """The tracker settings of the report's parameters (also the live node's)."""
    return TrackParams(
        params.association,
        params.lookahead_m,
        params.search_back_m,
        params.search_ahead_m,
        params.reacquire_m,
        params.lost_m,
        params.curvature_window_m,
    )


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


def relocalization_frame(
    t_ns: ArrayLike, t0_ns: int, m: PathMatch, tracks: list[Track]
) -> pd.DataFrame:
    """SPEC relocalization columns (``t_ns`` int64, ``t_rel_s`` from ``t0_ns``, angles in deg),
    then the tracker's (``cross_track_m … lost``) from ``tracks`` (one per row)."""
    t = np.asarray(t_ns, dtype=np.int64)
    tr = np.array([tk[4:9] for tk in tracks], dtype=np.float64).reshape(-1, 5)
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
            "cross_track_m": tr[:, 0],
            "progress_m": tr[:, 1],
            "curvature_1pm": tr[:, 2],
            "lookahead_u": tr[:, 3],
            "lookahead_v": tr[:, 4],
            "lost": np.array([tk.lost for tk in tracks], dtype=bool),
        },
        columns=RELOC_COLS,
    )


def track_trajectory(
    path: ReferencePath, uv: ArrayLike, heading: ArrayLike, params: Params
) -> tuple[PathMatch, list[Track]]:
    """Trajectory mode: every pose ``uv (M, 2)``, ``heading (M,)`` against the reference.

    ``nearest``: k* of the batch query (Eq. 3.12, as ever); ``progress``: the poses in time
    order through one :class:`PathTracker` (the live node's per-pose call)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    hq = np.asarray(heading, dtype=np.float64).reshape(-1)
    tracker = PathTracker(path, track_params(params))
    if params.association == "nearest":
        m = path.query_uv(uv, hq)
        tracks = [
            tracker.track(u, v, h, k)
            for (u, v), h, k in zip(uv.tolist(), hq.tolist(), m.ref_idx.tolist(), strict=True)
        ]
        return m, tracks
    tracks = [tracker.track(u, v, h) for (u, v), h in zip(uv.tolist(), hq.tolist(), strict=True)]
    k = np.array([tk.ref_idx for tk in tracks], dtype=np.int64)
    href = path.heading_rad[k]
    m = PathMatch(
        k,
        np.array([tk.distance_m for tk in tracks], dtype=np.float64),
        np.array([tk.phi_rad for tk in tracks], dtype=np.float64),
        hq,
        href,
        uv,
        path.uv[k],
    )
    return m, tracks


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
        tracks = [
            PathTracker(path, track_params(params)).track_segment(
                float(p[0]), float(p[1]), h, int(match.ref_idx[0])
            )
        ]
        t_rows = t_ns[[i]]
    else:
        match, tracks = track_trajectory(path, uv, heading, params)
        t_rows = t_ns
    reloc = relocalization_frame(t_rows, int(t_ns[0]), match, tracks)
    cross = reloc["cross_track_m"].to_numpy(np.float64)
    summary = {
        "mode": mode,
        "plane": params.plane,
        "n": len(reloc),
        "distance_m": stats(reloc["distance_m"]),
        "abs_heading_error_deg": stats(np.abs(reloc["heading_error_deg"])),
        "alignment": alignment,
        "association": params.association if mode == "trajectory" else "polyline",
        "ref_heading": "segment" if mode == "point" else "sample",
        "cross_track_m": stats(cross),
        "abs_cross_track_m": stats(np.abs(cross)),
        "lost": int(reloc["lost"].sum()),
    }
    return {"relocalization": reloc, "summary": Summary.model_validate(summary)}


def _relocalization_files(
    reloc: pd.DataFrame | None,
    summary: Summary | None,
    q_traj: pd.DataFrame | None,
    ref_traj: pd.DataFrame | None,
    ref_tags: pd.DataFrame | None,
) -> ExportFiles | None:
    """SPEC's ``relocalization.csv``, ``summary.json``, ``relocalization.png`` and ``map.png``
    of a query, against the reference's trajectory and tags."""
    if reloc is None or summary is None or q_traj is None or ref_traj is None:
        return None
    doc = json.loads(json.dumps(summary.model_dump(mode="json"), sort_keys=True))  # as stored
    return {
        "relocalization.csv": (
            "relocalization",
            dict(
                reloc=reloc,
                summary=doc,
                q_traj=q_traj,
                ref_traj=ref_traj,
                ref_tags=ref_tags,
                plane_name=summary.plane,
            ),
        )
    }


EXPORTS = (
    Export(
        "relocalization",
        ("relocalization.csv", "summary.json", "relocalization.png", "map.png"),
        {
            "reloc": "report.relocalization",
            "summary": "report.summary",
            "q_traj": "align.trajectory",
            "ref_traj": "reference:smooth.trajectory",
            "ref_tags": "reference:optimize.tag_map",
        },
        _relocalization_files,
    ),
)
