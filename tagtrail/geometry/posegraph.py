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

:func:`bundle_adjust` then refines such a map on the tags' corners themselves, jointly with the
camera poses (stage ``optimize``, ``refine="corners"``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.sparse.linalg import spsolve

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


# --- refinement on tag corners (bundle adjustment) ---------------------------------------------


@dataclass(frozen=True)
class CornerObservations:
    """Tag corners seen in frames: observation ``o`` is tag ``tag[o]`` (index ``0..T-1``) in frame
    ``frame[o]`` (index ``0..F-1``), its corners ``pts_tag (O, 4, 3)`` (tag frame, m) seen at
    ``uv (O, 4, 2)`` (undistorted normalised image coordinates, ``x/z, y/z``)."""

    frame: I64
    tag: I64
    pts_tag: F64
    uv: F64


@dataclass(frozen=True)
class BundleResult:
    """Refined ``world_T_tag`` (``R_tag (T, 3, 3)``, ``t_tag (T, 3)``) and ``cam_T_world``
    (``R_cam (F, 3, 3)``, ``t_cam (F, 3)``); ``res_px (O,)``: RMS corner reprojection error of
    each observation (px); ``cost``: robust cost (px^2); ``iters``: accepted LM steps."""

    R_tag: F64
    t_tag: F64
    R_cam: F64
    t_cam: F64
    res_px: F64
    cost: float
    iters: int
    converged: bool


def _project(R_cam: F64, t_cam: F64, R_tag: F64, t_tag: F64, ob: CornerObservations
             ) -> tuple[F64, F64, F64]:
    """Residuals ``(O, 4, 2)`` (normalised), points in world and camera frames ``(O, 4, 3)``."""
    pts_w = np.einsum("oij,okj->oki", R_tag[ob.tag], ob.pts_tag) + t_tag[ob.tag][:, None]
    pts_c = np.einsum("oij,okj->oki", R_cam[ob.frame], pts_w) + t_cam[ob.frame][:, None]
    z = np.where(pts_c[..., 2:3] > 1e-9, pts_c[..., 2:3], 1e-9)
    return pts_c[..., :2] / z - ob.uv, pts_w, pts_c


def _same_frame_pairs(frame: I64) -> tuple[I64, I64]:
    """All ordered pairs ``(a, b)`` of observations in the same frame, ``a == b`` included."""
    order = np.argsort(frame, kind="stable")
    f = frame[order]
    starts = np.flatnonzero(np.r_[True, f[1:] != f[:-1]])
    size = np.diff(np.r_[starts, len(f)])
    grp = np.repeat(np.arange(len(starts)), size)  # frame group of each sorted observation
    reps = size[grp]  # each observation pairs with every member of its group
    a = np.repeat(np.arange(len(f)), reps)
    b = starts[grp][a] + np.arange(len(a)) - np.repeat(np.cumsum(reps) - reps, reps)
    return order[a], order[b]


def bundle_adjust(
    R_tag: F64,
    t_tag: F64,
    R_cam: F64,
    t_cam: F64,
    ob: CornerObservations,
    anchor: int,
    *,
    px_per_unit: float,
    loss: LossName = "huber",
    f_scale_px: float = 1.0,
    max_iter: int = 50,
) -> BundleResult:
    """Jointly refine tag poses and camera poses on the corner reprojection error.

    ``min sum_o f^2 rho(|r_o|^2 / f^2)``, ``r_o = px_per_unit * (pi(cam_T_world world_T_tag X) -
    uv)`` the 8-vector of observation ``o`` in pixels (``px_per_unit``: focal length), ``rho`` a
    robust loss on the whole tag (an outlier detection is down-weighted as one), ``f`` =
    ``f_scale_px``. Tag ``anchor`` stays fixed (the gauge). This is the maximum-likelihood map
    under Gaussian corner noise: unlike the pairwise relative poses of Eq. 3.2 it does not inherit
    the bias of single-tag PnP (a small tag's out-of-plane rotation, levered over the distance to
    the other tag), because each camera pose is shared by every tag of its frame (Triggs et al.,
    "Bundle adjustment -- a modern synthesis", 2000).

    Levenberg-Marquardt with IRLS weights; camera poses are eliminated per frame (Schur
    complement), leaving a sparse ``6T x 6T`` system in the tags (blocks of co-visible tags).
    Left perturbations: ``R <- Exp(w) R``, ``t <- Exp(w) t + v`` for both ``cam_T_world`` and
    ``world_T_tag``.
    """
    n_f, n_t, n_o = len(R_cam), len(R_tag), len(ob.frame)
    free = np.flatnonzero(np.arange(n_t) != anchor)
    cols = (6 * free[:, None] + np.arange(6)).reshape(-1)
    pa, pb = _same_frame_pairs(ob.frame)
    k6 = np.arange(6)
    # Sparse reduced system in the free tags: co-visibility blocks, then the diagonal blocks.
    ta, tb = np.r_[ob.tag[pa], np.arange(n_t)], np.r_[ob.tag[pb], np.arange(n_t)]
    shape = (len(ta), 6, 6)
    s_rows = np.broadcast_to((6 * ta)[:, None, None] + k6[:, None], shape).reshape(-1)
    s_cols = np.broadcast_to((6 * tb)[:, None, None] + k6[None, :], shape).reshape(-1)
    eye3 = np.broadcast_to(np.eye(3), (n_o, 4, 3, 3))
    f2 = f_scale_px**2

    def evaluate(Rc: F64, tc: F64, Rt: F64, tt: F64) -> tuple[float, F64, F64, F64, F64]:
        r, pw, pc = _project(Rc, tc, Rt, tt, ob)
        sq = np.sum(r * r, axis=(1, 2)) * px_per_unit**2
        bad = (pc[..., 2] <= 1e-6).any(axis=1)  # behind the camera: an outlier, no gradient
        val, w = rho(loss, np.where(bad, 1e12, sq) / f2)
        return float(f2 * val.sum()), r, pw, pc, np.where(bad, 0.0, w)

    cost, r, pw, pc, w = evaluate(R_cam, t_cam, R_tag, t_tag)
    lam, it, converged = 1e-4, 0, not (len(free) and n_o)
    while it < max_iter and len(free) and n_o:
        z = pc[..., 2]
        Jp = np.zeros((n_o, 4, 2, 3))
        Jp[..., 0, 0] = Jp[..., 1, 1] = 1.0 / z
        Jp[..., 2] = -pc[..., :2] / (z * z)[..., None]
        Jc = (Jp @ np.concatenate([-hat(pc), eye3], axis=-1)).reshape(n_o, 8, 6)
        Jt = (Jp @ R_cam[ob.frame][:, None] @ np.concatenate([-hat(pw), eye3], axis=-1))
        Jt = Jt.reshape(n_o, 8, 6)
        rv = r.reshape(n_o, 8)
        W = w[:, None, None]
        Hcc = _sum_blocks(np.einsum("oki,okj->oij", Jc, Jc) * W, ob.frame, n_f)
        Htt = _sum_blocks(np.einsum("oki,okj->oij", Jt, Jt) * W, ob.tag, n_t)
        Hct = np.einsum("oki,okj->oij", Jc, Jt) * W
        gc = _sum_blocks(np.einsum("oki,ok->oi", Jc, rv) * w[:, None], ob.frame, n_f)
        gt = _sum_blocks(np.einsum("oki,ok->oi", Jt, rv) * w[:, None], ob.tag, n_t)
        while True:
            Hinv = np.linalg.inv(Hcc + lam * Hcc * np.eye(6) + 1e-12 * np.eye(6))
            M = Hinv[ob.frame] @ Hct  # (O, 6, 6)
            vals = np.r_[-np.einsum("pji,pjk->pik", Hct[pa], M[pb]).reshape(-1),
                         (Htt + lam * Htt * np.eye(6) + 1e-12 * np.eye(6)).reshape(-1)]
            S = coo_matrix((vals, (s_rows, s_cols)), shape=(6 * n_t, 6 * n_t)).tocsr()
            y = np.einsum("fij,fj->fi", Hinv, gc)
            b = _sum_blocks(np.einsum("oji,oj->oi", Hct, y[ob.frame]), ob.tag, n_t) - gt
            dt = np.zeros(6 * n_t)
            dt[cols] = spsolve(S[cols][:, cols].tocsc(), b.reshape(-1)[cols])
            if not np.isfinite(dt).all():  # singular (a tag left without weight): no step
                dt[:] = 0.0
            dt6 = dt.reshape(n_t, 6)
            rhs = -gc - _sum_blocks(np.einsum("oij,oj->oi", Hct, dt6[ob.tag]), ob.frame, n_f)
            dc = np.einsum("fij,fj->fi", Hinv, rhs)
            Rc, tc = _left_update(R_cam, t_cam, dc)
            Rt, tt = _left_update(R_tag, t_tag, dt6)
            new = evaluate(Rc, tc, Rt, tt)
            if new[0] <= cost or lam > 1e8:
                break
            lam *= 10.0
        if new[0] > cost:
            converged = True  # no descent left at any damping: a (local) minimum
            break
        step = max(np.abs(dt).max(), np.abs(dc).max(initial=0.0))
        done = cost - new[0] <= 1e-10 * cost or step < 1e-12
        R_cam, t_cam, R_tag, t_tag = Rc, tc, Rt, tt
        cost, r, pw, pc, w = new
        it, lam = it + 1, max(lam / 10.0, 1e-9)
        if done:
            converged = True
            break
    res_px = np.sqrt(np.mean(np.sum(r * r, axis=2), axis=1)) * px_per_unit
    return BundleResult(R_tag, t_tag, R_cam, t_cam, res_px, cost, it, converged)


def _sum_blocks(x: F64, idx: I64, n: int) -> F64:
    """``out[k] = sum of x[o] with idx[o] == k`` for blocks ``x (O, ...)``."""
    flat = x.reshape(len(x), -1)
    out = np.stack([np.bincount(idx, flat[:, c], n) for c in range(flat.shape[1])], axis=1)
    return out.reshape((n, *x.shape[1:]))


def _left_update(R: F64, t: F64, d: F64) -> tuple[F64, F64]:
    dR = R_from_rotvec(d[:, :3])
    return dR @ R, np.einsum("nij,nj->ni", dR, t) + d[:, 3:]
