"""The map's joint solve, started from the pose graph (stage ``optimize``).

:func:`refine_map` links the tags the pose graph left out through the trajectory
(:func:`~.start.link_tags`), solves the tags and cameras jointly (:func:`~.setup.solve_on_corners`)
and assembles the report block; :func:`choose_hypotheses` decides the tag pairs with a close rival
hypothesis by which pose graph the joint solve from there fits better.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.joint.odometry import OdometryData
from tagtrail.geometry.joint.problem import CornerRows
from tagtrail.geometry.joint.settings import JointSettings
from tagtrail.geometry.joint.setup import Solved, bridge, corner_problem, solve_on_corners
from tagtrail.geometry.joint.start import link_tags
from tagtrail.geometry.posegraph import PoseGraphResult
from tagtrail.geometry.se3 import make_T


@dataclass(frozen=True)
class MapRefinement:
    """The joint solve's map: the tag ids ``ids`` it holds (the pose graph's plus the tags
    ``linked`` through the trajectory), their ``world_T_tag`` (``R``, ``t``), standard
    deviations ``std (N, 2)`` (m, rad; the anchor 0, unobserved NaN), the solution and the
    report block (``optimize.report.bundle``, as plain values)."""

    ids: I64
    R: F64
    t: F64
    std: F64
    linked: list[int]
    solved: Solved
    block: dict[str, Any]


def refine_map(
    R: F64,
    t: F64,
    tags: I64,
    anchor: int,
    rows: CornerRows,
    camera: CameraModel,
    settings: JointSettings,
    timed: bool,
    odometry: OdometryData | None = None,
) -> MapRefinement:
    """The joint solve from the pose-graph map ``R (T, 3, 3)``, ``t (T, 3)`` of the sorted ids
    ``tags`` (``anchor``: the gauge tag's index) on the corner ``rows`` of every observed tag;
    ``timed``: the stamps are capture times (else no prior and no tag linked through the
    trajectory); ``odometry``: the wheel-odometry prior's data (tags beyond a stretch without
    tags linked by the wheels' dead reckoning, the prior in the solve)."""
    ids = np.union1d(tags, rows.tag_id)
    W = np.full((len(ids), 4, 4), np.nan)
    W[np.searchsorted(ids, tags)] = make_T(R, t)
    known = np.isin(ids, tags)
    k = np.searchsorted(ids, rows.tag_id)
    linked: list[int] = []
    if timed and not known[k].all():
        pb = corner_problem(rows, k, camera, settings, timed)
        W, now = link_tags(
            W,
            known,
            rows.cam_T_tag,
            pb.ob,
            pb.t_s,
            px_per_unit=camera.focal_px,
            max_gap_s=pb.max_gap_s,
            **bridge(odometry, settings, int(pb.t_ns[0])),
        )
        linked = ids[now & ~known].tolist()
        known = now
    rows = rows.take(known[k])
    ids, W = ids[known], W[known]
    k = np.searchsorted(ids, rows.tag_id)
    pb = corner_problem(rows, k, camera, settings, timed)
    a = int(np.searchsorted(ids, tags[anchor]))
    free = (np.arange(len(ids)) != a) & (np.bincount(k, minlength=len(ids)) > 0)
    out = solve_on_corners(pb, W, free, settings, odometry=odometry)
    res, pb = out.res, out.pb  # pb: with the frames the odometry posed
    n_tags = np.bincount(pb.ob.frame, minlength=len(pb.t_ns))
    block = {
        "frames": int(len(pb.t_ns)),
        "single_tag_frames": int((n_tags == 1).sum()),
        "observations": int(len(rows.t_ns)),
        "motion_prior_frames": res.prior_terms,
        "ippe_second_solution": int((out.choice % 2 == 1).sum()),
        "linked_tags": linked,
        "iterations": res.iters,
        "converged": res.converged,
        "cost": res.cost,
        "variance_factor": res.variance_factor,
        "corner_sigma_px": res.sigma_px,
        "rms_px": float(np.sqrt(np.mean(res.res_px**2))),
        "p95_px": float(np.percentile(res.res_px, 95)),
        "ground": None if out.ground is None else dataclasses.asdict(out.ground),
        "odometry": None if out.odometry is None else dataclasses.asdict(out.odometry),
    }
    assert res.tag_std is not None
    fixed = np.where(np.arange(len(ids)) == a, 0.0, np.nan)[:, None]  # the anchor; unobserved
    std = np.where(free[:, None], res.tag_std, fixed)
    return MapRefinement(ids, res.R_tag, res.t_tag, std, linked, out, block)


def choose_hypotheses(
    rows: CornerRows,
    tags: I64,
    anchor: int,
    camera: CameraModel,
    settings: JointSettings,
    key: I64,
    hypothesis: I64,
    order: list[int],
    res: PoseGraphResult,
    solve_graph: Callable[[np.ndarray], PoseGraphResult],
    max_iter: int,
) -> tuple[np.ndarray, PoseGraphResult, list[list[int]]]:
    """Decide the tag pairs with a rival hypothesis by the frames' continuity: for each pair key
    in ``order`` (of the edges' ``key``), the pose graph is solved (``solve_graph`` of the
    edges to use) with the pair's rival edges (``hypothesis`` 1) instead and kept if the joint
    solve from there (corners and motion prior, ``max_iter`` iterations from
    ``initial_cameras``' start) costs less. A mirrored tag seen only while the view hardly
    changes agrees with itself across those frames; the frames before and after do not agree
    with it. ``rows``: the corner rows of the sorted ``tags`` (``anchor`` the gauge tag's index),
    ``res``: the pose graph's solution. Returns the edges to use, the pose graph's solution and
    the flipped pairs."""
    k = np.searchsorted(tags, rows.tag_id)
    pb = corner_problem(rows, k, camera, settings, True)
    free = (np.arange(len(tags)) != anchor) & (np.bincount(k, minlength=len(tags)) > 0)

    def cost(r: PoseGraphResult) -> float:
        return solve_on_corners(
            pb,
            make_T(r.R, r.t),
            free,
            settings,
            max_iter=max_iter,
            covariance=False,
            decide=False,
        ).res.cost

    use, best = hypothesis == 0, cost(res)
    flipped: list[list[int]] = []
    for r in order:
        trial = np.where(key == r, hypothesis == 1, use)
        r_res = solve_graph(trial)  # afresh: a flip turns a whole branch
        c = cost(r_res)
        if c < best:
            use, res, best = trial, r_res, c
            flipped.append([int(r >> 32), int(r & 0xFFFFFFFF)])
    return use, res, flipped
