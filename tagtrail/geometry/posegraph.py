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

with ``E = R_pred^T R_obs`` (:class:`_Problem`, the scipy form of the problem).

:func:`solve` minimises it by Levenberg-Marquardt on the poses themselves (right perturbations
``R_k Exp(d_k)``, ``t_k + dt_k``, relinearised at every accepted step, so ``J_r(d) = I``) with the
IRLS weight ``w_e rho'(s_e)`` per edge (``rho'' = 0``, Triggs et al. 2000: the Gauss-Newton model
stays positive definite). The normal equations are accumulated per tag pair, not per edge: an
edge's translation rows ``[hat(t_pred), -R_i^T, 0, R_i^T]`` are the same for every edge of its
pair, and its rotation rows are ``J_r^-1(r_R) R_obs^T [I, 0, -R_pred, 0]``, whose Gram matrix has
the closed form ``R_obs J_r^-T J_r^-1 R_obs^T = (1 - a th^2) I + a q q^T`` with ``q = R_obs r_R``
(``J_r^-T r_R = r_R``), so each edge costs a few vector operations and the ``(6n, 6n)`` system a
sparse LU (SuperLU, minimum degree on ``A^T + A``). Stops when the relative cost decrease falls
below ``1e-12`` or a step below ``1e-10`` (m, rad): the map's weak directions (long chains) move
the tags by millimetres at cost changes near ``1e-8``, so a loose stop costs accuracy.

:mod:`tagtrail.geometry.joint` then refines such a map on the tags' corners themselves, jointly
with the camera poses (stage ``optimize``, ``method="joint"``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix, diags
from scipy.sparse.csgraph import dijkstra
from scipy.sparse.linalg import splu

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
    right_jacobian_inv_coefficient,
)
from tagtrail.geometry.se3 import R_from_rotvec

BLOCK = 6
FTOL = 1e-12  # relative cost decrease at which solve() stops
XTOL = 1e-10  # largest step component (m, rad) at which solve() stops


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
    t_lh = np.where(flip[:, None], -np.einsum("eba,eb->ea", g.R_obs, g.t_obs), g.t_obs)
    pair_key = lo * n + hi
    keys, pair = np.unique(pair_key, return_inverse=True)
    count = np.bincount(pair, minlength=len(keys)).astype(np.float64)
    plo, phi = keys // n, keys % n
    cost = 1.0 + 1.0 / count
    adj = csr_matrix((np.r_[cost, cost], (np.r_[plo, phi], np.r_[phi, plo])), shape=(n, n))
    dist, pred = dijkstra(adj, indices=g.anchor, return_predecessors=True)
    if not np.isfinite(dist).all():
        lost = np.flatnonzero(~np.isfinite(dist)).tolist()
        raise DataError(f"tag graph: tags (indices) {lost} are not connected to the anchor")
    # Only the tree's pairs need their robust relative pose (each pair's is its own).
    child = np.flatnonzero(pred >= 0)
    parent = pred[child]
    sel = np.zeros(len(keys), dtype=bool)
    sel[np.searchsorted(keys, np.minimum(child, parent) * n + np.maximum(child, parent))] = True
    use, slot, n_sel = sel[pair], np.cumsum(sel) - 1, int(sel.sum())
    R_pair = np.repeat(np.eye(3)[None], len(keys), axis=0)
    t_pair = np.zeros((len(keys), 3))
    R_pair[sel] = grouped_rotation_mean(R_lh[use], slot[pair[use]], n_sel, robust=True, iters=8)
    t_pair[sel] = grouped_median(t_lh[use], slot[pair[use]], n_sel)
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


def _jr_inv_gram_coefficient(th: F64) -> F64:
    """``a(th)`` with ``J_r^-T(phi) J_r^-1(phi) = I + a (phi phi^T - th^2 I)``, ``th = |phi|``.

    With ``J_r^-1 = I + K/2 + c K^2`` (``K = hat(phi)``, ``K^4 = -th^2 K^2``):
    ``a = 2c - 1/4 - c^2 th^2``.
    """
    c = right_jacobian_inv_coefficient(th)
    out: F64 = 2.0 * c - 0.25 - c * c * th * th
    return out


class _Normal:
    """Robust cost and Gauss-Newton normal equations of the graph, accumulated per tag pair.

    Edges are grouped by their ordered pair ``(i, j)``; unknowns are 6 per non-anchor tag,
    ``[d_k (rad), dt_k (m)]`` (right rotation perturbation, world translation).
    """

    def __init__(self, g: PoseGraph, loss: LossName, f_scale: float) -> None:
        self.g, self.loss, self.f2 = g, loss, f_scale * f_scale
        n = g.n_tags
        key = np.asarray(g.idx_i, np.int64) * n + np.asarray(g.idx_j, np.int64)
        order = np.argsort(key, kind="stable")
        ks = key[order]
        self.starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
        self.pi, self.pj = ks[self.starts] // n, ks[self.starts] % n
        self.pair = np.repeat(np.arange(len(self.starts)), np.diff(np.r_[self.starts, len(ks)]))
        self.R_obs = np.ascontiguousarray(np.asarray(g.R_obs, np.float64)[order])
        self.t_obs = np.ascontiguousarray(np.asarray(g.t_obs, np.float64)[order])
        self.w = np.asarray(g.weight, np.float64)[order]
        self.wr2 = float(g.rot_weight_m) ** 2
        col = np.full(n, -1, dtype=np.int64)
        free = np.flatnonzero(np.arange(n) != g.anchor)
        col[free] = 6 * np.arange(len(free))
        self.col, self.n_params = col, 6 * len(free)
        # Each pair's 12 unknowns [d_i, t_i, d_j, t_j] (-1: the anchor's, held fixed).
        k6 = np.arange(6)
        idx = np.concatenate(
            [
                np.where(col[self.pi, None] >= 0, col[self.pi, None] + k6, -1),
                np.where(col[self.pj, None] >= 0, col[self.pj, None] + k6, -1),
            ],
            axis=1,
        )
        rows, cols = np.broadcast_arrays(idx[:, :, None], idx[:, None, :])
        self.h_keep = ((rows >= 0) & (cols >= 0)).reshape(-1)
        self.h_rows, self.h_cols = rows.reshape(-1)[self.h_keep], cols.reshape(-1)[self.h_keep]
        self.g_keep = idx.reshape(-1) >= 0
        self.g_idx = idx.reshape(-1)[self.g_keep]

    def evaluate(self, R: F64, t: F64) -> tuple[float, tuple[F64, ...]]:
        """Cost ``0.5 f^2 sum_e rho(s_e)`` (scipy's convention) and what :meth:`system` needs."""
        Ri_T = np.swapaxes(R[self.pi], -1, -2)
        t_pred = np.einsum("pab,pb->pa", Ri_T, t[self.pj] - t[self.pi])
        R_pred = Ri_T @ R[self.pj]
        r_t = t_pred[self.pair] - self.t_obs
        r_r = log_so3(np.swapaxes(R_pred, -1, -2)[self.pair] @ self.R_obs)
        s = self.w * ((r_t * r_t).sum(axis=1) + self.wr2 * (r_r * r_r).sum(axis=1)) / self.f2
        val, d1 = rho(self.loss, s)
        return 0.5 * self.f2 * float(val.sum()), (Ri_T, t_pred, R_pred, r_t, r_r, self.w * d1)

    def system(self, lin: tuple[F64, ...]) -> tuple[csr_matrix, F64]:
        """``H = sum_e om_e J_e^T J_e`` (sparse ``(p, p)``) and ``g = sum_e om_e J_e^T r_e``."""
        Ri_T, t_pred, R_pred, r_t, r_r, om = lin
        st = self.starts
        P = len(st)
        # Rotation rows: sum_e om wr^2 M^T M and M^T r with M = J_r^-1(r_R) R_obs^T.
        q = np.einsum("eab,eb->ea", self.R_obs, r_r)
        th = np.linalg.norm(r_r, axis=1)
        a = _jr_inv_gram_coefficient(th)
        omr = om * self.wr2
        S = np.add.reduceat(q[:, :, None] * (q * (omr * a)[:, None])[:, None, :], st, axis=0)
        S += np.add.reduceat(omr * (1.0 - a * th * th), st)[:, None, None] * np.eye(3)
        u = np.add.reduceat(q * omr[:, None], st, axis=0)
        # Translation rows, the same for every edge of a pair: C = [hat(t_pred), -Ri^T, 0, Ri^T].
        W = np.add.reduceat(om, st)
        v = np.add.reduceat(r_t * om[:, None], st, axis=0)
        C = np.zeros((P, 3, 12))
        C[:, :, 0:3] = hat(t_pred)
        C[:, :, 3:6] = -Ri_T
        C[:, :, 9:12] = Ri_T
        L = np.zeros((P, 3, 12))  # rotation rows' pair part: d_i - R_pred d_j
        L[:, :, 0:3] = np.eye(3)
        L[:, :, 6:9] = -R_pred
        Ct, Lt = np.swapaxes(C, 1, 2), np.swapaxes(L, 1, 2)
        H = W[:, None, None] * (Ct @ C) + Lt @ (S @ L)
        grad = (Ct @ v[:, :, None] + Lt @ u[:, :, None])[..., 0]
        Hs = coo_matrix(
            (H.reshape(-1)[self.h_keep], (self.h_rows, self.h_cols)),
            shape=(self.n_params, self.n_params),
        ).tocsr()
        gs = np.bincount(
            self.g_idx, weights=grad.reshape(-1)[self.g_keep], minlength=self.n_params
        ).astype(np.float64)
        return Hs, gs

    def retract(self, R: F64, t: F64, dx: F64) -> tuple[F64, F64]:
        d = np.zeros((self.g.n_tags, 6))
        d[self.col >= 0] = dx.reshape(-1, 6)
        return R @ R_from_rotvec(d[:, :3]), t + d[:, 3:]


def solve(
    g: PoseGraph,
    *,
    loss: LossName = "soft_l1",
    f_scale: float = 0.1,
    max_nfev: int | None = 100,
    init: tuple[F64, F64] | None = None,
) -> PoseGraphResult:
    """Minimise Eq. 3.7 over the non-anchor tags; returns poses and per-edge residuals.

    Levenberg-Marquardt (Marquardt's diagonal scaling) on the pair-accumulated normal equations
    of :class:`_Normal`; ``max_nfev`` bounds the cost evaluations (None: 100). ``status`` as
    scipy's: 0 evaluations exhausted, 2 cost change below :data:`FTOL`, 3 step below
    :data:`XTOL`.
    """
    R0, t0 = initial_guess(g) if init is None else init
    # Re-gauge (anchor_T_k = inv(world_T_anchor) world_T_k) so the anchor is exactly identity.
    Ra_T = R0[g.anchor].T
    R, t = Ra_T[None] @ R0, (t0 - t0[g.anchor]) @ Ra_T.T
    R[g.anchor], t[g.anchor] = np.eye(3), 0.0
    if g.n_tags <= 1 or len(g.idx_i) == 0:
        r_t, r_r = relative_residuals(R, t, g)
        return PoseGraphResult(R, t, r_t, r_r, 0.0, 0, 0, "nothing to optimise")
    prob = _Normal(g, loss, f_scale)
    cost, lin = prob.evaluate(R, t)
    nfev, lam = 1, 1e-6
    status, message = 0, "the maximum number of function evaluations is exceeded"
    limit = 100 if max_nfev is None else max_nfev
    while nfev < limit:
        H, grad = prob.system(lin)
        dH = H.diagonal()
        A = (H + diags(lam * np.maximum(dH, 1e-12 * max(float(dH.max()), 1e-300)))).tocsc()
        try:
            lu = splu(
                A,
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
            dx = -lu.solve(grad)
        except RuntimeError:  # an exactly singular factor (e.g. zero weights): damp more
            dx = np.full(prob.n_params, np.nan)
        R_new, t_new = prob.retract(R, t, np.nan_to_num(dx))
        cost_new, lin_new = prob.evaluate(R_new, t_new)
        nfev += 1
        if not np.isfinite(dx).all() or not cost_new <= cost:  # also refuses NaN
            lam *= 10.0
            if lam > 1e12:
                status, message = 2, "no step decreases the cost"
                break
            continue
        drop, old = cost - cost_new, cost
        R, t, cost, lin = R_new, t_new, cost_new, lin_new
        lam = max(lam / 10.0, 1e-12)
        if np.abs(dx).max() < XTOL:
            status, message = 3, "`xtol` termination condition is satisfied."
            break
        if drop <= FTOL * old:
            status, message = 2, "`ftol` termination condition is satisfied."
            break
    r_t, r_r = relative_residuals(R, t, g)
    return PoseGraphResult(R, t, r_t, r_r, cost, nfev, status, message)
