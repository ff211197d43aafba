"""Tag pose graph: robust non-linear least squares over relative tag observations (Eq. 3.2-3.7).

Unknowns: ``world_T_tag`` of every tag but the anchor, which is fixed at the identity (gauge).
Each edge observation ``e`` of the pair ``(i, j)`` carries ``i_T_j^obs = (R_obs, t_obs)`` (Eq. 3.2)
and gives the 6-residual (Eq. 3.3, 3.5, 3.6)::

    i_T_j^pred = (world_T_i)^-1 world_T_j = (R_i^T R_j, R_i^T (t_j - t_i))
    err_e = sqrt(w_e) * [ t_pred - t_obs ; rot_weight_m * Log(R_pred^T R_obs) ]

and the cost is ``sum_e f^2 rho(|err_e|^2 / f^2)`` (Eq. 3.7, ``f`` = ``f_scale``): the robust loss
acts on the whole 6-vector of an edge, as in the paper, not per component.

Parametrisation (Eq. 3.4: rotation vector + translation per tag): ``R_k = R0_k Exp(d_k)``,
``t_k`` free, where ``R0`` is the spanning-tree initial guess -- a rotation vector relative to the
initial guess keeps the parametrisation far from its ``|d| = pi`` singularity. The Jacobian is
analytic and sparse (right perturbations, see :mod:`tagtrail.geometry.rotations`)::

    d r_t / d d_i = hat(t_pred) J_r(d_i)     d r_t / d t_i = -R_i^T     d r_t / d t_j = R_i^T
    d r_R / d d_i = J_r^-1(r_R) R_obs^T J_r(d_i)      d r_R / d d_j = -J_r^-1(r_R) E^T J_r(d_j)

with ``E = R_pred^T R_obs``. Solved with ``scipy.optimize.least_squares`` (``trf``, LSMR on the
sparse Jacobian).

:mod:`tagtrail.geometry.bundle` then refines such a map on the tags' corners themselves, jointly
with the camera poses (stage ``optimize``, ``method="joint"``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from tagtrail.errors import DataError
from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.robust import LossName, rho
from tagtrail.geometry.rotations import (
    grouped_median,
    grouped_rotation_mean,
    hat,
    log_so3,
    right_jacobian,
    right_jacobian_inv,
)
from tagtrail.geometry.se3 import R_from_rotvec

BLOCK = 6


def block_loss(name: LossName, block: int = BLOCK) -> str | Callable[[F64], F64]:
    """A scipy ``least_squares`` loss applying ``rho`` to the squared norm of each residual block.

    scipy calls it with ``z = (f / f_scale)^2`` per residual component; we sum ``z`` over each
    block of ``block`` consecutive components, and return ``rho(s)/block`` (so the cost sums to
    ``sum rho(s)``), ``rho'(s)`` (so the gradient is exact) and ``rho'' = 0`` (IRLS weighting,
    which keeps the Gauss-Newton model positive definite).
    """
    if name == "linear":
        return "linear"

    def loss(z: F64) -> F64:
        r, d1 = rho(name, z.reshape(-1, block).sum(axis=1))
        out = np.zeros((3, z.size))
        out[0] = np.repeat(r / block, block)
        out[1] = np.repeat(d1, block)
        return out

    return loss


@dataclass(frozen=True)
class PoseGraph:
    """Edges of a tag graph. Tags are indices ``0..n_tags-1``; ``idx_i < idx_j`` not required.

    ``R_obs (E, 3, 3)``, ``t_obs (E, 3)`` (m): observed ``i_T_j``; ``weight (E,)``: relative
    confidence (multiplies the squared residual); ``rot_weight_m``: metres per radian of rotation
    residual (1.0 = the paper's plain stacking).
    """

    n_tags: int
    anchor: int
    idx_i: I64
    idx_j: I64
    R_obs: F64
    t_obs: F64
    weight: F64
    rot_weight_m: float = 1.0


@dataclass(frozen=True)
class PoseGraphResult:
    """Optimised ``world_T_tag`` as ``R (n, 3, 3)``, ``t (n, 3)``; per-edge unweighted residuals."""

    R: F64
    t: F64
    res_t: F64  # (E, 3) m, t_pred - t_obs
    res_r: F64  # (E, 3) rad, Log(R_pred^T R_obs)
    cost: float
    nfev: int
    status: int
    message: str


def relative_residuals(R: F64, t: F64, g: PoseGraph) -> tuple[F64, F64]:
    """Unweighted residuals ``(E, 3)`` m and ``(E, 3)`` rad of Eq. 3.5-3.6 for poses ``R, t``."""
    Ri_T = np.swapaxes(R[g.idx_i], -1, -2)
    t_pred = np.einsum("eab,eb->ea", Ri_T, t[g.idx_j] - t[g.idx_i])
    R_pred = Ri_T @ R[g.idx_j]
    return t_pred - g.t_obs, log_so3(np.swapaxes(R_pred, -1, -2) @ g.R_obs)


def initial_guess(g: PoseGraph) -> tuple[F64, F64]:
    """Spanning-tree initialisation: ``world_T_tag`` ``(n, 3, 3)``, ``(n, 3)``.

    Each tag pair gets a robust relative pose (median translation, geodesic L1 median rotation).
    The tree is the shortest-path tree from the anchor with edge cost ``1 + 1/n_pair``: fewest
    hops (breadth first), ties broken by the pair with the most co-observations. Raises
    :class:`DataError` if a tag is not connected to the anchor.
    """
    n = g.n_tags
    lo, hi = np.minimum(g.idx_i, g.idx_j), np.maximum(g.idx_i, g.idx_j)
    flip = g.idx_i > g.idx_j
    # Express every observation as lo_T_hi.
    R_lh = np.where(flip[:, None, None], np.swapaxes(g.R_obs, -1, -2), g.R_obs)
    t_lh = np.where(
        flip[:, None], -np.einsum("eba,eb->ea", g.R_obs, g.t_obs), g.t_obs
    )
    pair_key = lo * n + hi
    keys, pair = np.unique(pair_key, return_inverse=True)
    R_pair = grouped_rotation_mean(R_lh, pair, len(keys), robust=True, iters=8)
    t_pair = grouped_median(t_lh, pair, len(keys))
    count = np.bincount(pair, minlength=len(keys)).astype(np.float64)
    plo, phi = keys // n, keys % n
    cost = 1.0 + 1.0 / count
    adj = csr_matrix((np.r_[cost, cost], (np.r_[plo, phi], np.r_[phi, plo])), shape=(n, n))
    dist, pred = dijkstra(adj, indices=g.anchor, return_predecessors=True)
    if not np.isfinite(dist).all():
        lost = np.flatnonzero(~np.isfinite(dist)).tolist()
        raise DataError(f"tag graph: tags (indices) {lost} are not connected to the anchor")
    pair_of = {(int(a), int(b)): k for k, (a, b) in enumerate(zip(plo, phi, strict=True))}
    R0 = np.repeat(np.eye(3)[None], n, axis=0)
    t0 = np.zeros((n, 3))
    for node in np.argsort(dist, kind="stable"):
        p = pred[node]
        if p < 0:
            continue
        if p < node:
            k = pair_of[(int(p), int(node))]
            pR_n, pt_n = R_pair[k], t_pair[k]
        else:
            k = pair_of[(int(node), int(p))]
            pR_n, pt_n = R_pair[k].T, -R_pair[k].T @ t_pair[k]
        R0[node] = R0[p] @ pR_n
        t0[node] = t0[p] + R0[p] @ pt_n
    return R0, t0


class _Problem:
    """Residual and sparse analytic Jacobian of the graph around the linearisation ``R0``."""

    def __init__(self, g: PoseGraph, R0: F64) -> None:
        self.g, self.R0 = g, R0
        free = np.flatnonzero(np.arange(g.n_tags) != g.anchor)
        col = np.full(g.n_tags, -1, dtype=np.int64)
        col[free] = 6 * np.arange(len(free))
        self.n_params = 6 * len(free)
        self.sw = np.sqrt(np.asarray(g.weight, dtype=np.float64))
        ci, cj = col[g.idx_i], col[g.idx_j]
        E = len(g.idx_i)
        k3 = np.arange(3)
        cols = np.full((E, 6, 9), -1, dtype=np.int64)

        def block(c: I64, off: int) -> I64:
            return np.where(c[:, None] >= 0, c[:, None] + off + k3, -1)

        cols[:, :3, :] = np.concatenate([block(ci, 0), block(ci, 3), block(cj, 3)], axis=1)[
            :, None, :
        ]
        cols[:, 3:, :6] = np.concatenate([block(ci, 0), block(cj, 0)], axis=1)[:, None, :]
        self.keep = cols.reshape(-1) >= 0
        self.cols = cols.reshape(-1)[self.keep]
        self.indptr = np.r_[0, np.cumsum((cols >= 0).sum(axis=2).reshape(-1))]
        self.shape = (6 * E, self.n_params)

    def unpack(self, x: F64) -> tuple[F64, F64, F64]:
        """Poses ``R (n, 3, 3)``, ``t (n, 3)`` and rotation increments ``d (n, 3)``."""
        n = self.g.n_tags
        p = x.reshape(-1, 6)
        d, t = np.zeros((n, 3)), np.zeros((n, 3))
        free = np.arange(n) != self.g.anchor
        d[free], t[free] = p[:, :3], p[:, 3:]
        return self.R0 @ R_from_rotvec(d), t, d

    def fun(self, x: F64) -> F64:
        R, t, _ = self.unpack(x)
        r_t, r_r = relative_residuals(R, t, self.g)
        res = np.concatenate([r_t, self.g.rot_weight_m * r_r], axis=1) * self.sw[:, None]
        return res.reshape(-1)

    def jac(self, x: F64) -> csr_matrix:
        g = self.g
        R, t, d = self.unpack(x)
        Jr = right_jacobian(d)
        Ri_T = np.swapaxes(R[g.idx_i], -1, -2)
        t_pred = np.einsum("eab,eb->ea", Ri_T, t[g.idx_j] - t[g.idx_i])
        Et = R[g.idx_j].swapaxes(-1, -2) @ R[g.idx_i] @ g.R_obs  # E = R_pred^T R_obs
        Jinv = right_jacobian_inv(log_so3(Et))
        E = len(g.idx_i)
        vals = np.zeros((E, 6, 9))
        vals[:, :3, 0:3] = hat(t_pred) @ Jr[g.idx_i]
        vals[:, :3, 3:6] = -Ri_T
        vals[:, :3, 6:9] = Ri_T
        wr = g.rot_weight_m
        vals[:, 3:, 0:3] = wr * (Jinv @ np.swapaxes(g.R_obs, -1, -2) @ Jr[g.idx_i])
        vals[:, 3:, 3:6] = -wr * (Jinv @ np.swapaxes(Et, -1, -2) @ Jr[g.idx_j])
        vals *= self.sw[:, None, None]
        return csr_matrix((vals.reshape(-1)[self.keep], self.cols, self.indptr), shape=self.shape)


def solve(
    g: PoseGraph,
    *,
    loss: LossName = "soft_l1",
    f_scale: float = 0.1,
    max_nfev: int | None = 100,
    init: tuple[F64, F64] | None = None,
) -> PoseGraphResult:
    """Minimise Eq. 3.7 over the non-anchor tags; returns poses and per-edge residuals."""
    R0, t0 = initial_guess(g) if init is None else init
    # Re-gauge (anchor_T_k = inv(world_T_anchor) world_T_k) so the anchor is exactly identity.
    Ra_T = R0[g.anchor].T
    R0, t0 = Ra_T[None] @ R0, (t0 - t0[g.anchor]) @ Ra_T.T
    R0[g.anchor], t0[g.anchor] = np.eye(3), 0.0
    prob = _Problem(g, R0)
    free = np.arange(g.n_tags) != g.anchor
    x0 = np.concatenate([np.zeros((free.sum(), 3)), t0[free]], axis=1).reshape(-1)
    if prob.n_params == 0 or len(g.idx_i) == 0:
        r_t, r_r = relative_residuals(R0, t0, g)
        return PoseGraphResult(R0, t0, r_t, r_r, 0.0, 0, 0, "nothing to optimise")
    sol = least_squares(
        prob.fun,
        x0,
        jac=prob.jac,
        method="trf",
        loss=block_loss(loss),
        f_scale=f_scale,
        x_scale="jac",
        tr_solver="lsmr",
        max_nfev=max_nfev,
    )
    R, t, _ = prob.unpack(sol.x)
    r_t, r_r = relative_residuals(R, t, g)
    return PoseGraphResult(
        R, t, r_t, r_r, float(sol.cost), int(sol.nfev), int(sol.status), str(sol.message)
    )
