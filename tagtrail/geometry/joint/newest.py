"""A fixed-lag window's newest frame without re-solving the window: the filter's step.

After a window's solve, what its cost knows of its last two frames is their marginal Gaussian:
mean the solved poses, covariance the inverse normal matrix's block
(:attr:`~.problem.JointResult.tail_cov`). A new frame's pose then minimises its own corners'
cost and the terms of the priors that reach it (the motion prior's triple, the drive's and the
odometry's step into it, its own ground term) with those two frames under that Gaussian,
eliminated in closed form: a stack of terms ``r = r0 + A d_new + B d_prev`` with ``d_prev ~
N(0, S)`` is whitened by ``(I + B S B^T)^-1``. For a linear problem this is the re-solved
window's newest frame exactly (a smoother's newest frame is its filtered estimate); here it
costs a few 6x6 solves instead of the window's banded solve, so a live node can send the pose
first and re-solve the window after (``stream/continuity.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.joint.problem import (
    CornerObservations,
    Corners,
    Prior,
    corner_jacobians,
    project,
)
from tagtrail.geometry.robust import rho
from tagtrail.geometry.se3 import R_of_rotvec


@dataclass(frozen=True)
class Newest:
    """The new frame's ``cam_T_world`` ``(R, t)``, the covariance ``(6, 6)`` of its
    ``[w ; v]`` (unscaled: the inverse of its normal matrix) and the Gauss-Newton ``steps``
    taken."""

    R: F64
    t: F64
    cov: F64
    steps: int


def solve_newest(
    R_cam: F64,
    t_cam: F64,
    tail_cov: F64,
    R_tag: F64,
    t_tag: F64,
    ob: CornerObservations,
    corners: Corners,
    f_scale: float,
    priors: Sequence[Prior],
    iters: int = 2,
    rows: Rows | None = None,
    tol: float = 0.0,
) -> Newest | None:
    """The third of the frames ``cam_T_world`` ``R_cam (3, 3, 3)``, ``t_cam (3, 3)`` (the
    first two: the window's solved last frames, with joint covariance ``tail_cov (12, 12)``;
    the third: its start) from its corners ``ob`` (tags ``world_T_tag`` ``R_tag, t_tag``,
    weighed by ``corners`` with the window's loss scale ``f_scale``, in noise units) and the
    ``priors``' terms over the three frames that reach it (module docstring), those taken
    once at the start (their robust weights too: start where they expect the frame, e.g. at
    the motion's extrapolation); ``iters`` Gauss-Newton steps on the corners, fewer once a
    step moves the frame less than ``tol`` in each component (m, rad). ``rows``: more priors'
    terms, taken beforehand (:func:`prior_rows`, at this start). None when a step fails (the
    caller re-solves its window)."""
    R_cam, t_cam = R_cam.copy(), t_cam.copy()
    sig = np.broadcast_to(np.asarray(corners.sigma_px, np.float64), (len(ob.tag),))
    scale = corners.px_per_unit / sig
    f2 = f_scale * f_scale
    Hp, gp = prior_normal(prior_rows(R_cam, t_cam, priors, rows), tail_cov)
    moved = np.zeros(6)  # the new frame's steps so far: the priors' linear model moves with it
    H = Hp
    steps = 0
    for _ in range(iters):
        r, _, pc = project(R_cam[2:], t_cam[2:], R_tag, t_tag, ob)
        rv = r.reshape(len(r), 8) * scale[:, None]
        bad = (pc[..., 2] <= 1e-6).any(axis=1)
        _, w = rho(corners.loss, np.where(bad, 1e12, np.sum(rv * rv, axis=1)) / f2)
        w = np.where(bad, 0.0, w)
        Jc = corner_jacobians(pc, scale)[1]
        H = np.einsum("oki,okj,o->ij", Jc, Jc, w) + Hp
        g = np.einsum("oki,ok,o->i", Jc, rv, w) + gp + Hp @ moved
        try:
            step = -np.linalg.solve(H + 1e-12 * np.eye(6), g)
        except np.linalg.LinAlgError:
            return None
        if not np.isfinite(step).all():
            return None
        dR = R_of_rotvec(step[:3])  # left_update's, for one frame without scipy's ~40 us
        R_cam[2], t_cam[2] = dR @ R_cam[2], dR @ t_cam[2] + step[3:]
        moved += step
        steps += 1
        if np.abs(step).max() < tol:
            break
    try:
        cov = np.asarray(np.linalg.inv(H + 1e-12 * np.eye(6)), np.float64)
    except np.linalg.LinAlgError:
        return None
    return Newest(R_cam[2], t_cam[2], cov, steps)


Rows = tuple[F64, F64, F64]
"""The priors' terms that reach the new frame, stacked: residuals ``r (m,)`` and their
Jacobians on the new frame ``A (m, 6)`` and on the two before it ``B (m, 12)``."""


def prior_rows(R_cam: F64, t_cam: F64, priors: Sequence[Prior], rows: Rows | None = None) -> Rows:
    """The terms of ``priors`` over the three frames that reach the third (after ``rows``,
    when given): evaluating them is most of the step's time, and all but the odometry's can
    be taken before the frame arrives (``stream/continuity.py``)."""
    rs, As, Bs = ([rows[0]], [rows[1]], [rows[2]]) if rows is not None else ([], [], [])
    for p in priors:
        T = p.terms(R_cam, t_cam, {})
        n = T.Jc.shape[1]
        sel = T.first + n - 1 == 2  # the terms that reach the new frame
        if not sel.any():
            continue
        Jt, d = T.Jc[sel], T.r.shape[1]
        m = len(Jt)
        B = np.zeros((m, d, 12))
        for i in range(n - 1):  # frame 3 - n + i of the two before
            f = 3 - n + i
            B[:, :, 6 * f : 6 * f + 6] = Jt[:, i]
        rs.append(T.r[sel].reshape(-1))
        As.append(Jt[:, n - 1].reshape(m * d, 6))
        Bs.append(B.reshape(m * d, 12))
    if not rs:
        return np.zeros(0), np.zeros((0, 6)), np.zeros((0, 12))
    if len(rs) == 1:
        return rs[0], As[0], Bs[0]
    return np.concatenate(rs), np.concatenate(As), np.concatenate(Bs)


def prior_normal(rows: Rows, tail_cov: F64) -> tuple[F64, F64]:
    """The priors' share of the new frame's normal equations ``(6, 6), (6,)`` at the start:
    their terms ``rows``, the two frames before under their marginal (module docstring).
    Taken once: over the millimetres the corners then move the frame the priors are linear
    (their robust weights held)."""
    rp, A, B = rows
    if not len(rp):
        return np.zeros((6, 6)), np.zeros(6)
    M = np.eye(len(rp)) + B @ tail_cov @ B.T
    X = np.linalg.solve(M, np.column_stack([A, rp]))
    return A.T @ X[:, :6], A.T @ X[:, 6]
