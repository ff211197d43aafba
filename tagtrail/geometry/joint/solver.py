"""The joint solve: tag poses and camera poses on the tags' corners, held together in time.

Unknowns: ``world_T_tag`` of the free tags (all but the anchor for a map; none for a trajectory
against a fixed map) and ``cam_T_world`` of every frame seeing a tag, frames in time order.
Cost (every term whitened, so it reads as a negative log-likelihood)::

    sum_o  f^2 rho(|r_o|^2 / f^2)  +  sum_k |m_k|^2

``r_o`` (8,): observation ``o``'s corner reprojection errors in pixels divided by
``sigma_px`` (the corner noise), ``rho`` a robust loss on the whole tag with scale ``f`` (in
units of ``sigma_px``) -- the maximum-likelihood map under Gaussian corner noise, which does not
inherit the bias of single-tag PnP. A tag's weight follows from its geometry: a small, far or
oblique tag's corners move less per metre or radian of pose, and are noisier
(:func:`corner_sigma`), so its observation counts less; a bridge between two parts of the map
seen in one or two frames weighs what those frames' corners say, no more.

``m_k`` (6,): a constant-velocity (white-noise-on-acceleration) motion prior at each frame ``k``
whose neighbours ``k-1, k+1`` lie within ``max_gap_s`` (gaps without tags stay gaps: the chain
breaks there and nothing is invented across). With ``h1 = t_k - t_{k-1}``, ``h2 = t_{k+1} - t_k``,
``c`` the camera centre in the world and ``w_j = Log(R_j^T R_{j+1})`` the body-frame increment of
``world_R_cam``::

    a_k     = 2 / (h1 + h2) * ((c_{k+1} - c_k) / h2 - (c_k - c_{k-1}) / h1)     (m/s^2)
    alpha_k = 2 / (h1 + h2) * (w_k / h2 - w_{k-1} / h1)                         (rad/s^2)
    m_k     = sqrt(3 h / 2) * [alpha_k / ang_sigma ; a_k / acc_sigma],  h = (h1 + h2) / 2

White noise of density ``acc_sigma`` (m/s^2/sqrt(Hz)) on the acceleration gives the second
difference a variance ``2 h^3 acc_sigma^2 / 3``, hence the scale. Single-tag frames are held by
their neighbours, and tags never seen together are linked through the trajectory.

Gauss-Newton / Levenberg-Marquardt with IRLS weights. The camera block of the normal equations
is banded (the prior couples frames ``k-1..k+1``: 17 sub-diagonals), so the cameras are
eliminated by a banded Cholesky (LAPACK ``pbtrf``) and the free tags solved on their dense Schur
complement. Left perturbations ``R <- Exp(w) R``, ``t <- Exp(w) t + v`` of ``cam_T_world`` and
``world_T_tag``. Covariances (the inverse of the normal matrix at the solution, times the
a-posteriori variance factor) give each tag's and each frame's standard deviation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve, cho_solve_banded, cholesky_banded
from scipy.sparse import coo_matrix

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.drive import (
    N_MOUNT,
    WHEELED_BOUND,
    DrivePrior,
    Mount,
    drive_terms,
    fit_mount,
    steps,
    strain,
)
from tagtrail.geometry.drive import robust_weights as drive_weights
from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.ground import (
    PLANAR_BOUND,
    GroundPrior,
    Plane,
    centres,
    planarity,
    plane_terms,
    robust_weights,
)
from tagtrail.geometry.robust import LossName, rho
from tagtrail.geometry.rotations import hat, log_so3, right_jacobian_inv
from tagtrail.geometry.se3 import R_from_rotvec, inv
from tagtrail.geometry.smoothing import segment_triples

BAND = 17  # sub-diagonals of the camera block: frames k-1, k, k+1 of 6 parameters each
_CHUNK = 20_000_000  # floats of A^-1 B held at once (Schur complement built in column chunks)


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
class MotionPrior:
    """Constant-velocity prior over frames stamped ``t_s (F,)`` (s, increasing): acceleration
    noise densities ``acc_sigma`` (m/s^2/sqrt(Hz)) and ``ang_sigma`` (rad/s^2/sqrt(Hz));
    stamps further apart than ``max_gap_s`` break the chain. ``loss`` acts on each frame's
    whitened 6-vector with scale ``f_scale`` (standard deviations): motion far beyond the prior
    (a bump, or stamps that are not the capture times) stops being smoothed instead of bending
    the map."""

    t_s: F64
    acc_sigma: float
    ang_sigma: float
    max_gap_s: float
    loss: LossName = "cauchy"
    f_scale: float = 3.0


@dataclass(frozen=True)
class JointResult:
    """Solved ``world_T_tag`` (``R_tag (T, 3, 3)``, ``t_tag (T, 3)``) and ``cam_T_world``
    (``R_cam (F, 3, 3)``, ``t_cam (F, 3)``); ``res_px (O,)``: RMS corner error of each
    observation (px); ``tag_std``/``cam_std`` ``(T|F, 2)``: position (m) and rotation (rad)
    standard deviations (RMS over the axes; 0 for fixed tags; None unless asked for) and
    ``cam_cov (F, 6, 6)`` each frame's covariance of the left perturbation ``[w ; v]`` of
    ``cam_T_world`` (the map's share included when it is free; scaled as the std);
    ``variance_factor``: the whitened cost per degree of freedom (1 when the noise is as
    assumed); ``prior_terms``: frames held by the motion prior; ``sigma_px``: the median corner
    noise used (estimated with ``estimate_noise``)."""

    R_tag: F64
    t_tag: F64
    R_cam: F64
    t_cam: F64
    res_px: F64
    cost: float
    iters: int
    converged: bool
    variance_factor: float
    prior_terms: int
    sigma_px: float
    tag_std: F64 | None = None
    cam_std: F64 | None = None
    cam_cov: F64 | None = None
    plane: Plane | None = None
    mount: Mount | None = None


def _project(R_cam: F64, t_cam: F64, R_tag: F64, t_tag: F64, ob: CornerObservations
             ) -> tuple[F64, F64, F64]:
    """Residuals ``(O, 4, 2)`` (normalised), points in world and camera frames ``(O, 4, 3)``."""
    pts_w = np.einsum("oij,okj->oki", R_tag[ob.tag], ob.pts_tag) + t_tag[ob.tag][:, None]
    pts_c = np.einsum("oij,okj->oki", R_cam[ob.frame], pts_w) + t_cam[ob.frame][:, None]
    z = np.where(pts_c[..., 2:3] > 1e-9, pts_c[..., 2:3], 1e-9)
    return pts_c[..., :2] / z - ob.uv, pts_w, pts_c


def sum_blocks(x: F64, idx: I64, n: int) -> F64:
    """``out[k] = sum of x[o] with idx[o] == k`` for blocks ``x (O, ...)``."""
    flat = x.reshape(len(x), -1)
    out = np.stack([np.bincount(idx, flat[:, c], n) for c in range(flat.shape[1])], axis=1)
    return out.reshape((n, *x.shape[1:]))


def left_update(R: F64, t: F64, d: F64) -> tuple[F64, F64]:
    """``(Exp(w) R, Exp(w) t + v)`` for steps ``d = [w ; v]`` ``(N, 6)``."""
    dR = R_from_rotvec(d[:, :3])
    return dR @ R, np.einsum("nij,nj->ni", dR, t) + d[:, 3:]


class _Prior:
    """The motion prior's residuals ``(M, 6)`` and Jacobians ``(M, 3, 6, 6)`` (frames k-1, k,
    k+1) at cameras ``R_cam, t_cam`` (``cam_T_world``)."""

    def __init__(self, prior: MotionPrior | None, n_f: int) -> None:
        k = (segment_triples(np.asarray(prior.t_s, np.float64), prior.max_gap_s)
             if prior is not None and n_f >= 3 else np.zeros(0, np.int64))
        self.k = k.astype(np.int64)
        self.loss: LossName = "linear" if prior is None else prior.loss
        self.f2 = 1.0 if prior is None else prior.f_scale**2
        if prior is None or not len(k):
            return
        t = np.asarray(prior.t_s, np.float64)
        self.h1, self.h2 = t[k] - t[k - 1], t[k + 1] - t[k]
        self.g = 2.0 / (self.h1 + self.h2)
        # a_k = cm c_{k-1} + c0 c_k + cp c_{k+1}
        self.coef = np.stack([self.g / self.h1, -self.g * (1 / self.h1 + 1 / self.h2),
                              self.g / self.h2], axis=1)
        s = np.sqrt(0.75 * (self.h1 + self.h2))  # sqrt(3 h / 2), h the mean step
        self.s_r, self.s_t = s / prior.ang_sigma, s / prior.acc_sigma

    def evaluate(self, R: F64, t: F64) -> tuple[F64, F64]:
        k = self.k
        if not len(k):
            return np.zeros((0, 6)), np.zeros((0, 3, 6, 6))
        c = centres(R, t)
        E = R[:-1] @ np.swapaxes(R[1:], 1, 2)  # world_R_cam_j^T world_R_cam_{j+1}
        e = log_so3(E)
        Jinv = right_jacobian_inv(e)
        a = np.einsum("mj,mji->mi", self.coef, np.stack([c[k - 1], c[k], c[k + 1]], axis=1))
        alpha = self.g[:, None] * (e[k] / self.h2[:, None] - e[k - 1] / self.h1[:, None])
        m = np.concatenate([alpha * self.s_r[:, None], a * self.s_t[:, None]], axis=1)
        J = np.zeros((len(k), 3, 6, 6))
        gr = (self.g * self.s_r)[:, None, None]
        J[:, 0, :3, :3] = -gr / self.h1[:, None, None] * (Jinv[k - 1] @ np.swapaxes(E[k - 1], 1, 2))
        J[:, 1, :3, :3] = gr * (Jinv[k] @ np.swapaxes(E[k], 1, 2) / self.h2[:, None, None]
                                + Jinv[k - 1] / self.h1[:, None, None])
        J[:, 2, :3, :3] = -gr / self.h2[:, None, None] * Jinv[k]
        for j, f in enumerate((k - 1, k, k + 1)):  # d c / d v = -world_R_cam = -R^T
            J[:, j, 3:, 3:] = -(self.coef[:, j] * self.s_t)[:, None, None] * np.swapaxes(R[f], 1, 2)
        return m, J


def _band_index(n_f: int) -> tuple[I64, I64, I64, I64, I64]:
    """Scatter indices from camera blocks ``Ablk (F, 3, 6, 6)`` (``Ablk[f, d]`` = block row
    ``f + d``, column ``f``) into LAPACK's lower band storage ``ab (BAND + 1, 6F)``."""
    d, a, b = np.meshgrid(np.arange(3), np.arange(6), np.arange(6), indexing="ij")
    keep = (6 * d + a - b) >= 0
    d, a, b = d[keep], a[keep], b[keep]
    f = np.arange(n_f)
    rows = np.broadcast_to((6 * d + a - b)[:, None], (len(d), n_f))
    cols = 6 * f[None, :] + b[:, None]
    return rows, cols, d, a, b


def _band(Ablk: F64, idx: tuple[I64, I64, I64, I64, I64], lam: float) -> F64:
    rows, cols, d, a, b = idx
    n_f = len(Ablk)
    ab = np.zeros((BAND + 1, 6 * n_f))
    ab[rows, cols] = np.moveaxis(Ablk[:, d, a, b], 0, 1)
    ab[0] *= 1.0 + lam
    ab[0] += 1e-12
    return ab


def _banded_diag_inverse(cb: F64) -> F64:
    """The 6x6 diagonal blocks ``(F, 6, 6)`` of ``A^-1`` from the lower banded Cholesky factor
    ``cb`` of ``A`` (Takahashi's recursion on the band, O(n band^2))."""
    n, b = cb.shape[1], cb.shape[0] - 1
    Z = np.zeros((b + 1, n + b))  # Z[d, j] = (A^-1)[j + d, j]; padded columns are zero
    pad = np.zeros((b + 1, n + b))
    pad[:, :n] = cb
    # window W[p, q] = Z[j+1+p, j+1+q] over the next b indices, read from band storage
    dd = np.abs(np.arange(b)[:, None] - np.arange(b)[None, :])
    lo = np.minimum(np.arange(b)[:, None], np.arange(b)[None, :]) + 1
    for j in range(n - 1, -1, -1):
        ljj, lv = pad[0, j], pad[1:, j]
        W = Z[dd, j + lo]
        zc = -(W @ lv) / ljj
        Z[1:, j] = zc
        Z[0, j] = 1.0 / (ljj * ljj) - (lv @ zc) / ljj
    out = np.zeros((n // 6, 6, 6))
    for p in range(6):
        for q in range(6):
            lo_, d_ = min(p, q), abs(p - q)
            out[:, p, q] = Z[d_, np.arange(n // 6) * 6 + lo_]
    return out


def solve_joint(
    R_tag: F64,
    t_tag: F64,
    R_cam: F64,
    t_cam: F64,
    ob: CornerObservations,
    free: np.ndarray,
    *,
    px_per_unit: float,
    sigma_px: float | F64 = 1.0,
    loss: LossName = "huber",
    f_scale_px: float = 1.0,
    max_iter: int = 50,
    prior: MotionPrior | None = None,
    covariance: bool = False,
    estimate_noise: bool = False,
    ground: GroundPrior | None = None,
    plane: Plane | None = None,
    drive: DrivePrior | None = None,
    mount: Mount | None = None,
) -> JointResult:
    """Minimise the module's cost over the free tags (``free (T,)`` bool) and every camera,
    from the given start; cameras must be in time order when ``prior`` is given. ``sigma_px``:
    the corner noise, one value or one per observation (:func:`corner_sigma`); the robust scale
    ``f_scale_px`` is taken at its median. ``estimate_noise``: after the first solve, rescale the
    corner noise to what the residuals show (clamped to 0.05-5 px) and solve again, so that
    precise corners are not outweighed by the motion prior (nor noisy ones by it overruled);
    ``JointResult.sigma_px`` reports the median noise used. ``ground``: the ground-plane
    prior (:mod:`tagtrail.geometry.ground`), its plane free from the start ``plane``;
    ``drive``: the wheeled-drive prior on top of it (:mod:`tagtrail.geometry.drive`, the steps
    those of ``prior``), the camera's mount free from ``mount``."""
    n_f, n_t, n_o = len(R_cam), len(R_tag), len(ob.frame)
    free = np.asarray(free, bool)
    free_idx = np.flatnonzero(free)
    n_free = len(free_idx)
    col = np.full(n_t, -1)
    col[free_idx] = np.arange(n_free)
    of = np.flatnonzero(free[ob.tag])  # observations of free tags
    brow = np.broadcast_to((6 * ob.frame[of])[:, None, None] + np.arange(6)[:, None],
                           (len(of), 6, 6)).reshape(-1)
    bcol = np.broadcast_to((6 * col[ob.tag[of]])[:, None, None] + np.arange(6)[None, :],
                           (len(of), 6, 6)).reshape(-1)
    pr = _Prior(prior, n_f)
    kp = pr.k
    if ground is not None and plane is None:
        raise ValueError("solve_joint: a ground prior needs a start plane")
    has_plane = ground is not None and n_f > 0
    if drive is not None and (not has_plane or prior is None or mount is None):
        raise ValueError("solve_joint: a drive prior needs a ground prior, a motion prior and "
                         "a start mount")
    js = steps(prior.t_s, prior.max_gap_s) if drive is not None and prior is not None else None
    n_g = (6 + (N_MOUNT if js is not None else 0)) if has_plane else 0  # the global unknowns
    n_dense = 6 * n_free + n_g  # columns of B: the free tags', then the plane's and mount's
    if has_plane:  # the globals' block column in B: every frame's 6 rows x the n_g parameters
        prow = np.broadcast_to((6 * np.arange(n_f))[:, None, None] + np.arange(6)[:, None],
                               (n_f, 6, n_g)).reshape(-1)
        pcol = np.broadcast_to(6 * n_free + np.arange(n_g)[None, :], (n_f, 6, n_g)).reshape(-1)
    bidx = _band_index(n_f)
    eye3 = np.broadcast_to(np.eye(3), (n_o, 4, 3, 3))
    # normalised coordinates -> units of each observation's corner noise
    sig = np.broadcast_to(np.asarray(sigma_px, np.float64), (n_o,)).copy()
    scale = px_per_unit / sig
    f = f_scale_px / float(np.median(sig)) if n_o else 1.0
    f2 = f * f

    def evaluate(Rc: F64, tc: F64, Rt: F64, tt: F64, pl: Plane | None, mt: Mount | None
                 ) -> tuple[float, F64, F64, F64, F64, F64, F64, tuple[F64, ...] | None]:
        r, pw, pc = _project(Rc, tc, Rt, tt, ob)
        sq = np.sum(r * r, axis=(1, 2)) * scale**2
        bad = (pc[..., 2] <= 1e-6).any(axis=1)  # behind the camera: an outlier, no gradient
        val, w = rho(loss, np.where(bad, 1e12, sq) / f2)
        m, Jm = pr.evaluate(Rc, tc)
        val_m, w_m = rho(pr.loss, np.sum(m * m, axis=1) / pr.f2)
        cost = float(f2 * val.sum() + pr.f2 * val_m.sum())
        g: tuple[F64, ...] | None = None
        if has_plane:
            assert ground is not None and pl is not None
            p, Jpc, Jpg = plane_terms(Rc, tc, pl, ground)
            val_p, w_p = robust_weights(p, ground)
            cost += float(val_p.sum())
            s = np.sqrt(w_p)
            g = (p * s[:, None], Jpc * s[:, None, None], Jpg * s[:, None, None])
            if js is not None:
                assert drive is not None and mt is not None and prior is not None
                q, Jqc, Jqg = drive_terms(Rc, tc, prior.t_s, js, pl, mt, drive)
                val_q, w_q = drive_weights(q, drive)
                cost += float(val_q.sum())
                s = np.sqrt(w_q)
                g = (*g[:3], q * s, Jqc * s[:, None, None], Jqg * s[:, None])
        return cost, r, pw, pc, np.where(bad, 0.0, w), m * np.sqrt(w_m)[:, None], Jm * np.sqrt(
            w_m)[:, None, None, None], g

    def normal_equations(Rc: F64, r: F64, pw: F64, pc: F64, w: F64, m: F64, Jm: F64,
                         g: tuple[F64, ...] | None
                         ) -> tuple[F64, F64, F64, F64, F64 | None, F64 | None, coo_matrix]:
        z = pc[..., 2]
        Jp = np.zeros((n_o, 4, 2, 3))
        Jp[..., 0, 0] = Jp[..., 1, 1] = scale[:, None] / z
        Jp[..., 2] = -scale[:, None, None] * pc[..., :2] / (z * z)[..., None]
        Jc = (Jp @ np.concatenate([-hat(pc), eye3], axis=-1)).reshape(n_o, 8, 6)
        Jt = (Jp @ Rc[ob.frame][:, None] @ np.concatenate([-hat(pw), eye3], axis=-1))
        Jt = Jt.reshape(n_o, 8, 6)
        rv = r.reshape(n_o, 8) * scale[:, None]
        W = w[:, None, None]
        Ablk = np.zeros((n_f, 3, 6, 6))
        Ablk[:, 0] = sum_blocks(np.einsum("oki,okj->oij", Jc, Jc) * W, ob.frame, n_f)
        gc = sum_blocks(np.einsum("oki,ok->oi", Jc, rv) * w[:, None], ob.frame, n_f)
        if len(kp):
            for i in range(3):
                gc[kp - 1 + i] += np.einsum("mki,mk->mi", Jm[:, i], m)
                for j in range(i, 3):  # block row k-1+j, column k-1+i
                    Ablk[kp - 1 + i, j - i] += np.einsum("mki,mkj->mij", Jm[:, j], Jm[:, i])
        Htt = sum_blocks(np.einsum("oki,okj->oij", Jt, Jt) * W, ob.tag, n_t)[free_idx]
        gt = sum_blocks(np.einsum("oki,ok->oi", Jt, rv) * w[:, None], ob.tag, n_t)[free_idx]
        Hct = (np.einsum("oki,okj->oij", Jc, Jt) * W)[of]
        vals, rows, cols = Hct.reshape(-1), brow, bcol
        Hgg = gg = None
        if g is not None:  # the plane (and mount): one more dense block, coupled to every frame
            p, Jpc, Jpg = g[:3]
            Ablk[:, 0] += np.einsum("fki,fkj->fij", Jpc, Jpc)
            gc += np.einsum("fki,fk->fi", Jpc, p)
            Hgg = np.zeros((n_g, n_g))
            Hgg[:6, :6] = np.einsum("fki,fkj->ij", Jpg, Jpg)
            gg = np.zeros(n_g)
            gg[:6] = np.einsum("fki,fk->i", Jpg, p)
            Bg = np.zeros((n_f, 6, n_g))
            Bg[:, :, :6] = np.einsum("fki,fkj->fij", Jpc, Jpg)
            if len(g) > 3:  # the drive's steps: frames j and j + 1, the plane and the mount
                q, Jqc, Jqg = g[3:]
                a, b = js, js + 1  # type: ignore[operator]
                Ablk[a, 0] += np.einsum("pi,pj->pij", Jqc[:, 0], Jqc[:, 0])
                Ablk[b, 0] += np.einsum("pi,pj->pij", Jqc[:, 1], Jqc[:, 1])
                Ablk[a, 1] += np.einsum("pi,pj->pij", Jqc[:, 1], Jqc[:, 0])  # row j+1, column j
                gc[a] += Jqc[:, 0] * q[:, None]
                gc[b] += Jqc[:, 1] * q[:, None]
                Hgg += Jqg.T @ Jqg
                gg += Jqg.T @ q
                Bg[a] += np.einsum("pi,pj->pij", Jqc[:, 0], Jqg)
                Bg[b] += np.einsum("pi,pj->pij", Jqc[:, 1], Jqg)
            # globals the frames leave undetermined (a parked robot: the plane's normal; a
            # straight drive: its roll about the path, the lever arm) take no step that way,
            # instead of crawling
            Hgg += 1e-6 * np.trace(Hgg) / n_g * np.eye(n_g)
            vals = np.concatenate([vals, Bg.reshape(-1)])
            rows, cols = np.concatenate([rows, prow]), np.concatenate([cols, pcol])
        B = coo_matrix((vals, (rows, cols)), shape=(6 * n_f, n_dense)).tocsc()
        return Ablk, gc, Htt, gt, Hgg, gg, B

    def schur(cb: F64, Htt: F64, Hgg: F64 | None, B: coo_matrix, lam: float) -> F64:
        C = np.zeros((n_dense, n_dense))
        blocks = [*Htt, *([] if Hgg is None else [Hgg])]
        eps = 1e-9 * max(float(np.mean([np.trace(H) / len(H) * 6 for H in blocks])), 1e-300)
        for i, H in enumerate(blocks):  # eps: a tag nothing constrains gets no step, not a NaN
            sl = slice(6 * i, 6 * i + len(H))
            C[sl, sl] = H * (1.0 + lam * np.eye(len(H))) + eps * np.eye(len(H))
        step = max(6, (_CHUNK // max(6 * n_f, 1)) // 6 * 6)
        for c0 in range(0, n_dense, step):
            Bc = B[:, c0:c0 + step]
            X = cho_solve_banded((cb, True), Bc.toarray())
            C[:, c0:c0 + step] -= (B.T @ X)
        return C

    it = 0
    pl = plane if has_plane else None
    mt = mount if js is not None else None
    cost, r, pw, pc, w, m, Jm, g = evaluate(R_cam, t_cam, R_tag, t_tag, pl, mt)
    for round_ in range(2 if estimate_noise and n_o else 1):
        if round_:  # the corner noise the residuals show, then the solve again from there
            sq0 = np.sum(r * r, axis=(1, 2)) * scale**2
            dof0 = 8 * n_o - 6 * (n_f + n_free)
            if dof0 <= 0:
                break
            factor = float(np.sum(w * sq0) / dof0)
            sig = np.clip(sig * np.sqrt(factor), 0.05, 5.0)
            scale = px_per_unit / sig
            f = f_scale_px / float(np.median(sig))
            f2 = f * f
            cost, r, pw, pc, w, m, Jm, g = evaluate(R_cam, t_cam, R_tag, t_tag, pl, mt)
        lam, converged = 1e-4, n_o == 0
        while it < max_iter * (round_ + 1) and n_o:
            Ablk, gc, Htt, gt, Hgg, gg, B = normal_equations(R_cam, r, pw, pc, w, m, Jm, g)
            while True:
                try:
                    cb = cholesky_banded(_band(Ablk, bidx, lam), lower=True)
                    dt = np.zeros((n_t, 6))
                    dg = np.zeros(n_g)
                    if n_dense:
                        y = cho_solve_banded((cb, True), gc.reshape(-1))
                        S = schur(cb, Htt, Hgg, B, lam)
                        rhs = -np.concatenate([gt.reshape(-1), [] if gg is None else gg]) + B.T @ y
                        dd = cho_solve(cho_factor(S), rhs)
                        dt[free_idx], dg = dd[:6 * n_free].reshape(n_free, 6), dd[6 * n_free:]
                        dcv = -y - cho_solve_banded((cb, True), B @ dd)
                    else:
                        dcv = -cho_solve_banded((cb, True), gc.reshape(-1))
                    dc = dcv.reshape(n_f, 6)
                    ok = bool(np.isfinite(dc).all() and np.isfinite(dt).all()
                              and np.isfinite(dg).all())
                except (LinAlgError, ValueError):
                    ok = False
                if ok:
                    Rc, tc = left_update(R_cam, t_cam, dc)
                    Rt, tt = left_update(R_tag, t_tag, dt)
                    pl_new = pl.update(dg[:6]) if pl is not None else None
                    mt_new = mt.update(dg[6:], pl.u) if mt is not None and pl is not None else None
                    new = evaluate(Rc, tc, Rt, tt, pl_new, mt_new)
                    if new[0] <= cost:
                        break
                if lam > 1e8:
                    break
                lam *= 10.0
            if not ok or new[0] > cost:
                converged = True  # no descent left at any damping: a (local) minimum
                break
            step_size = max(np.abs(dt).max(initial=0.0), np.abs(dc).max(initial=0.0),
                            np.abs(dg).max(initial=0.0))
            # a decrease of the whitened cost (a chi^2) under 1e-6 changes nothing: a flat
            # direction (a parked robot's undetermined ground plane) is not crawled along
            done = (cost - new[0] <= max(1e-10 * cost, 1e-6) or step_size < 1e-12)
            R_cam, t_cam, R_tag, t_tag, pl, mt = Rc, tc, Rt, tt, pl_new, mt_new
            cost, r, pw, pc, w, m, Jm, g = new
            it, lam = it + 1, max(lam / 10.0, 1e-9)
            if done:
                converged = True
                break
    sq = np.sum(r * r, axis=(1, 2)) * scale**2
    dof = 8 * n_o + 6 * len(kp) - 6 * (n_f + n_free)
    chi2 = float(np.sum(w * sq) + np.sum(m * m))
    if g is not None:  # height and two tilt angles per frame; the plane's 5 degrees of freedom
        dof += 3 * n_f - 5
        chi2 += float(np.sum(g[0] ** 2))
        if len(g) > 3:  # one lateral step per pair of frames; the mount's 2
            dof += len(g[3]) - N_MOUNT
            chi2 += float(np.sum(g[3] ** 2))
    vf = chi2 / dof if dof > 0 else float("nan")
    res_px = observation_rms_px(R_cam, t_cam, R_tag, t_tag, ob, px_per_unit)
    tag_std = cam_std = cam_cov = None
    if covariance and n_o:
        tag_std, cam_std, cam_cov = _std(
            normal_equations(R_cam, r, pw, pc, w, m, Jm, g), bidx, free_idx, t_tag, n_t,
            max(vf, 1.0) if np.isfinite(vf) else 1.0, schur)
    return JointResult(R_tag, t_tag, R_cam, t_cam, res_px, cost, it, converged, vf, len(kp),
                       float(np.median(sig)) if n_o else float("nan"), tag_std, cam_std, cam_cov,
                       pl, mt)


def _std(ne: tuple[F64, F64, F64, F64, F64 | None, F64 | None, coo_matrix],
         bidx: tuple[I64, ...], free_idx: I64, t_tag: F64, n_t: int, vf: float, schur: object
         ) -> tuple[F64, F64, F64]:
    """Per-tag and per-frame ``(position m, rotation rad)`` standard deviations (RMS over the
    axes) and each frame's 6x6 covariance, from the inverse normal matrix, scaled by the
    variance factor ``vf`` (>= 1)."""
    Ablk, _, Htt, _, Hgg, _, B = ne
    n_f = len(Ablk)
    cb = cholesky_banded(_band(Ablk, bidx, 0.0), lower=True)  # type: ignore[arg-type]
    if np.any(Ablk[:, 1:]):  # frames coupled by the prior: the band's selected inverse
        cam_cov = _banded_diag_inverse(cb)
    else:  # independent frames: each block's own inverse
        cam_cov = np.asarray(np.linalg.inv(Ablk[:, 0] + 1e-12 * np.eye(6)), np.float64)
    tag_std = np.zeros((n_t, 2))
    if len(Htt) or Hgg is not None:  # the free tags, then the ground plane (and mount) if any
        S = schur(cb, Htt, Hgg, B, 0.0)  # type: ignore[operator]
        Sinv = cho_solve(cho_factor(S), np.eye(len(S)))
        if len(free_idx):
            blocks = np.stack([Sinv[6 * i:6 * i + 6, 6 * i:6 * i + 6]
                               for i in range(len(free_idx))])
            J = np.zeros((len(free_idx), 3, 6))
            J[:, :, :3] = -hat(t_tag[free_idx])  # d t = -hat(t) w + v
            J[:, :, 3:] = np.eye(3)
            pos = np.einsum("nij,njk,nlk->nil", J, blocks, J)
            tag_std[free_idx, 0] = np.sqrt(np.trace(pos, axis1=1, axis2=2) * vf / 3)
            tag_std[free_idx, 1] = np.sqrt(np.trace(blocks[:, :3, :3], axis1=1, axis2=2) * vf / 3)
        if 6 * n_f * len(S) <= _CHUNK:  # the map's share: X S^-1 X^T, X = A^-1 B
            X = cho_solve_banded((cb, True), B.toarray()).reshape(n_f, 6, -1)
            cam_cov = cam_cov + np.einsum("fik,fjk->fij", X @ Sinv, X)
    cam_cov = cam_cov * vf
    cam_std = np.stack([np.sqrt(np.trace(cam_cov[:, 3:, 3:], axis1=1, axis2=2) / 3),
                        np.sqrt(np.trace(cam_cov[:, :3, :3], axis1=1, axis2=2) / 3)], axis=1)
    return tag_std, cam_std, cam_cov


def solve_grounded(
    res: JointResult, resolve: Callable[..., JointResult], ground: GroundPrior, mode: str,
    drive: DrivePrior | None = None, drive_mode: str = "auto",
    motion: MotionPrior | None = None,
) -> tuple[JointResult, dict[str, Any]]:
    """The ground-plane prior on a solution ``res`` solved without it (with ``cam_cov``):
    ``mode`` ``plane`` applies it, ``auto`` only when the motion is planar
    (:func:`tagtrail.geometry.ground.planarity` below ``PLANAR_BOUND``); with ``drive`` and the
    ``motion`` prior whose steps it constrains, the wheeled-drive prior is solved with it:
    ``drive_mode`` ``wheeled`` keeps it, ``auto`` only where the corners leave its steps
    unstrained (:func:`tagtrail.geometry.drive.strain` below ``WHEELED_BOUND``; else the plane
    alone is solved for). ``resolve(start, ground=, plane=[, drive=, mount=])`` solves again
    from ``start`` with the priors. Returns the solution and a report block: applied, the
    planarity figure, the plane's normal (world), the camera's tilt to it (deg from its y
    axis), the camera centres' RMS height off it (m), the RMS tilt off the mean (deg), the
    frames the robust loss let go (beyond 3 sigma), and ``drive`` (:func:`_drive_block`, None
    without a drive prior)."""
    assert res.cam_cov is not None
    plane, stat = planarity(res.R_cam, res.t_cam, res.cam_cov, ground)
    applied = mode == "plane" or stat < PLANAR_BOUND
    drive_block = None
    if applied and drive is not None and motion is not None:
        js = steps(motion.t_s, motion.max_gap_s)
        start = fit_mount(res.R_cam, res.t_cam, motion.t_s, js, plane)
        driven = resolve(res, ground=ground, plane=plane, drive=drive, mount=start)
        assert driven.mount is not None and driven.plane is not None
        q, _, _ = drive_terms(driven.R_cam, driven.t_cam, motion.t_s, js, driven.plane,
                              driven.mount, drive)
        fit = strain(q, drive, driven.variance_factor)
        wheeled = drive_mode == "wheeled" or bool(fit < WHEELED_BOUND)
        drive_block = _drive_block(driven, q, motion, js, drive, drive_mode, wheeled, fit)
        if wheeled:
            res = driven
    if applied and (drive_block is None or not drive_block["applied"]):
        res = resolve(res, ground=ground, plane=plane)
    if applied:
        assert res.plane is not None
        plane = res.plane
    p, _, _ = plane_terms(res.R_cam, res.t_cam, plane, ground)
    u = plane.u / max(float(np.linalg.norm(plane.u)), 1e-300)
    return res, {
        "mode": mode, "applied": bool(applied), "planarity": stat,
        "normal": [float(v) for v in plane.n],
        "camera_tilt_deg": float(np.degrees(np.arccos(np.clip(-u[1], -1.0, 1.0)))),
        "height_rms_m": float(np.sqrt(np.mean(p[:, 0] ** 2))) * ground.height_sigma_m,
        "tilt_rms_deg": float(np.degrees(np.sqrt(np.mean(np.sum(p[:, 1:] ** 2, axis=1)))
                                         * ground.tilt_sigma_rad)),
        "frames_off": int((np.sum(p * p, axis=1) > ground.f_scale**2).sum()),
        "drive": drive_block,
    }


def _drive_block(driven: JointResult, q: F64, motion: MotionPrior, js: I64, drive: DrivePrior,
                 mode: str, applied: bool, fit: float) -> dict[str, Any]:
    """The drive prior's report, from the solution solved with it (``q``: its whitened
    steps): the mode, applied, the strain that decided ``auto``, the camera's lever arm (m)
    and its yaw from the robot's forward axis (deg, about the plane's normal, positive to the
    left), the RMS lateral velocity beyond the lever arm (m/s) and the steps the robust loss
    let go (beyond 3 sigma)."""
    assert driven.plane is not None and driven.mount is not None
    h = motion.t_s[js + 1] - motion.t_s[js]
    u = driven.plane.u / max(float(np.linalg.norm(driven.plane.u)), 1e-300)
    fwd = np.cross(driven.mount.lateral(u)[0], u)  # the robot's forward axis, camera frame
    z = np.array([0.0, 0.0, 1.0]) - u[2] * u
    yaw = np.degrees(np.arctan2(np.cross(fwd, z) @ u, fwd @ z))
    lat = q * drive.lateral_sigma / np.sqrt(h)  # m/s
    return {"mode": mode, "applied": bool(applied), "strain": fit,
            "lever_m": driven.mount.lever_m, "camera_yaw_deg": float(yaw),
            "lateral_rms_mps": float(np.sqrt(np.mean(lat**2))) if len(lat) else 0.0,
            "steps_off": int((q * q > drive.f_scale**2).sum())}


@dataclass(frozen=True)
class FrameEvidence:
    """How far each frame of a joint solution sits from its own corners: ``reproj_px (F,)`` its
    RMS corner error, ``alone_reproj_px`` that of the frame solved on its corners alone (the map
    fixed, no motion prior: the per-frame solution), ``shift_m`` / ``shift_deg`` the change of
    the camera centre and orientation the motion prior made, ``shift_sigma`` that change in the
    per-frame solution's standard deviations (Mahalanobis distance over the 6 pose parameters:
    below 4.74 in 99.9 % of frames when the prior only removes noise of the assumed size);
    ``R_alone (F, 3, 3)``, ``t_alone (F, 3)``: the per-frame solution's ``cam_T_world``."""

    reproj_px: F64
    alone_reproj_px: F64
    shift_m: F64
    shift_deg: F64
    shift_sigma: F64
    R_alone: F64
    t_alone: F64


SHIFT_SIGMA_BOUND = 4.74  # sqrt of chi^2 with 6 dof at 99.9 %


def frame_rms_px(res_px: F64, frame: I64, n_f: int) -> F64:
    """Each frame's RMS corner error ``(F,)`` from its observations' RMS errors ``res_px``."""
    n = np.bincount(frame, minlength=n_f)
    return np.sqrt(np.bincount(frame, res_px**2, n_f) / np.maximum(n, 1))


def observation_rms_px(R_cam: F64, t_cam: F64, R_tag: F64, t_tag: F64,
                       ob: CornerObservations, px_per_unit: float) -> F64:
    """Each observation's RMS corner error ``(O,)`` (px) at cameras ``cam_T_world`` and tags
    ``world_T_tag``."""
    r, _, _ = _project(R_cam, t_cam, R_tag, t_tag, ob)
    return np.asarray(np.sqrt(np.mean(np.sum(r * r, axis=2), axis=1)) * px_per_unit)


def frame_evidence(res: JointResult, ob: CornerObservations, *, px_per_unit: float,
                   sigma_px: float | F64, loss: LossName, f_scale_px: float,
                   estimate_noise: bool = False, max_iter: int = 50) -> FrameEvidence:
    """:class:`FrameEvidence` of the cameras of ``res`` (tags fixed): every frame solved again on
    its own corners from where the joint solution left it (the same noise model and loss), then
    compared with it."""
    n_f = len(res.R_cam)
    alone = solve_joint(res.R_tag, res.t_tag, res.R_cam, res.t_cam, ob,
                        np.zeros(len(res.R_tag), bool), px_per_unit=px_per_unit,
                        sigma_px=sigma_px, loss=loss, f_scale_px=f_scale_px, max_iter=max_iter,
                        covariance=True, estimate_noise=estimate_noise)
    w = log_so3(res.R_cam @ np.swapaxes(alone.R_cam, 1, 2))
    d = np.concatenate([w, res.t_cam - np.einsum("nij,nj->ni", R_from_rotvec(w), alone.t_cam)],
                       axis=1)
    assert alone.cam_cov is not None
    vf = alone.variance_factor if np.isfinite(alone.variance_factor) else 1.0
    cov = alone.cam_cov * (vf / max(vf, 1.0))  # at the noise the residuals show, not above it
    maha = np.einsum("ni,ni->n", d, np.linalg.solve(cov, d[..., None])[..., 0])
    centre, centre_alone = centres(res.R_cam, res.t_cam), centres(alone.R_cam, alone.t_cam)
    return FrameEvidence(
        reproj_px=frame_rms_px(res.res_px, ob.frame, n_f),
        alone_reproj_px=frame_rms_px(alone.res_px, ob.frame, n_f),
        shift_m=np.linalg.norm(centre - centre_alone, axis=1),
        shift_deg=np.degrees(np.linalg.norm(w, axis=1)),
        shift_sigma=np.sqrt(np.maximum(maha, 0.0)), R_alone=alone.R_cam, t_alone=alone.t_cam)


def same_frame_pairs(frame: I64) -> tuple[I64, I64]:
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


def corner_sigma(corners_px: F64, sigma_px: float, side_ref_px: float = 20.0) -> F64:
    """Each observation's corner noise ``(O,)`` px: ``sigma_px`` for a tag whose mean side is
    ``side_ref_px``, scaling as ``sqrt(side_ref_px / side)`` within 0.5-2x -- a corner is fitted
    to edges whose pixel count grows with the side, so a small, far or foreshortened (oblique)
    tag's corners are noisier (the weighting by geometry; its low decision margin goes with
    it)."""
    c = np.asarray(corners_px, np.float64).reshape(-1, 4, 2)
    side = np.linalg.norm(c - np.roll(c, 1, axis=1), axis=2).mean(axis=1)
    ratio = np.sqrt(side_ref_px / np.maximum(side, 1e-6))
    return np.asarray(sigma_px * np.clip(np.nan_to_num(ratio, nan=1.0), 0.5, 2.0))


def corner_observations(frame_idx: I64, t_ns: I64, tag: I64, corners_px: F64, size_m: F64,
                        camera: CameraModel) -> tuple[CornerObservations, I64]:
    """Observations (frames numbered in time order) and each frame's stamp ``(F,)`` (ns), from
    per-observation frame ids, stamps, tag indices, corners ``(O, 4, 2)`` (px) and sizes (m)."""
    frames, f = np.unique(frame_idx, return_inverse=True)
    stamp = np.zeros(len(frames), np.int64)
    stamp[f] = t_ns
    order = np.argsort(stamp, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    ob = CornerObservations(frame=rank[f], tag=np.asarray(tag, np.int64),
                            pts_tag=tag_corners(size_m), uv=camera.undistort(corners_px))
    return ob, stamp[order]


def initial_cameras(
    world_T_tag: F64, cam_T_tag: F64, ob: CornerObservations, t_s: F64, *,
    px_per_unit: float, max_gap_s: float, speed_mps: float = 1.5, turn_dps: float = 120.0,
    cap_px: float = 8.0,
) -> tuple[F64, I64, float]:
    """A start for :func:`solve_joint`: each frame's ``cam_T_world`` ``(F, 4, 4)`` chosen among
    its tags' IPPE solutions, the choice ``(F,)`` (the observation index * 2 + solution) and the
    sequence's total cost (the map's fit to the frames and their continuity).

    ``world_T_tag (O, 4, 4)`` is each observation's tag in the current map, ``cam_T_tag
    (O, 2, 4, 4)`` both IPPE solutions (NaN where absent). Every solution of every tag of a frame
    is a candidate camera pose, scored by how well it reprojects all the frame's tags (squared px,
    capped at ``cap_px`` per tag: the map may be off); consecutive frames (within ``max_gap_s``)
    add a penalty on the jump between candidates, ``(|dc| / (speed h + 2 cm))^2 + (angle /
    (turn h + 2 deg))^2``. Dynamic programming (Viterbi) over each chain picks the sequence of
    least total cost: a single-tag frame's ambiguous pair is decided by its neighbours."""
    n_o, n_f = len(ob.frame), len(t_s)
    cand = cam_T_tag @ inv(world_T_tag)[:, None]  # (O, 2, 4, 4) cam_T_world
    valid = np.isfinite(cand).all(axis=(2, 3))
    a, b = same_frame_pairs(ob.frame)
    unary = np.zeros((n_o, 2))
    pts_w = (np.einsum("oij,okj->oki", world_T_tag[:, :3, :3], ob.pts_tag)
             + world_T_tag[:, None, :3, 3])
    cap2 = (cap_px / px_per_unit) ** 2
    for s in range(2):
        for lo in range(0, len(a), 200_000):
            aa, bb = a[lo:lo + 200_000], b[lo:lo + 200_000]
            err = _capped_sq(np.nan_to_num(cand[aa, s]), pts_w[bb], ob.uv[bb], cap2)
            unary[:, s] += np.bincount(aa, err, n_o)
    unary = unary * px_per_unit**2
    unary[~valid] = np.inf
    # candidates per frame, in frame order
    order = np.lexsort((np.arange(n_o), ob.frame))
    starts = np.searchsorted(ob.frame[order], np.arange(n_f + 1))
    choice = np.zeros(n_f, np.int64)
    out = np.zeros((n_f, 4, 4))
    Tc = np.nan_to_num(cand).reshape(-1, 4, 4)
    centre = -np.einsum("nji,nj->ni", Tc[:, :3, :3], Tc[:, :3, 3])
    U = unary.reshape(-1)
    gap = np.r_[np.inf, np.diff(t_s)]
    back: list[I64] = []
    cost = np.zeros(0)
    prev = np.zeros(0, np.int64)
    idx_of: list[I64] = []

    total = 0.0

    def finish(upto: int) -> None:  # backtrack the chain ending at frame upto - 1
        nonlocal total
        if not idx_of:
            return
        j = int(np.argmin(cost))
        total += float(cost[j])
        for fr in range(upto - 1, upto - 1 - len(idx_of), -1):
            c = idx_of[fr - (upto - len(idx_of))][j]
            choice[fr] = c
            out[fr] = Tc[c]
            j = int(back[fr - (upto - len(idx_of))][j])

    for fr in range(n_f):
        obs = order[starts[fr]:starts[fr + 1]]
        ids = (2 * obs[:, None] + np.arange(2)).reshape(-1)
        ids = ids[np.isfinite(U[ids])]
        if not len(ids):  # no usable solution: the caller keeps such frames out
            ids = (2 * obs[:1])
        if gap[fr] > max_gap_s or gap[fr] <= 0 or not idx_of:
            finish(fr)
            back, idx_of = [], []
            cost = U[ids].copy()
            back.append(np.zeros(len(ids), np.int64))
        else:
            h = gap[fr]
            dc = np.linalg.norm(centre[prev][:, None] - centre[ids][None], axis=-1)
            cosang = (np.einsum("pij,qij->pq", Tc[prev, :3, :3], Tc[ids, :3, :3]) - 1) / 2
            ang = np.arccos(np.clip(cosang, -1.0, 1.0))
            trans = ((dc / (speed_mps * h + 0.02)) ** 2
                     + (ang / (np.radians(turn_dps) * h + np.radians(2.0))) ** 2)
            tot = cost[:, None] + trans
            bk = np.argmin(tot, axis=0)
            cost = tot[bk, np.arange(len(ids))] + U[ids]
            back.append(bk)
        idx_of.append(ids)
        prev = ids
    finish(n_f)
    return out, choice, total



def _pose_distance(A: F64, B: F64) -> F64:
    """``|dt| + 0.5 m * angle`` between poses ``(..., 4, 4)`` (broadcast)."""
    dt = np.linalg.norm(A[..., :3, 3] - B[..., :3, 3], axis=-1)
    c = (np.einsum("...ij,...ij->...", A[..., :3, :3], B[..., :3, :3]) - 1.0) / 2.0
    return np.asarray(dt + 0.5 * np.arccos(np.clip(c, -1.0, 1.0)))


def _medoid(cands: F64) -> F64:
    """The candidate pose ``(4, 4)`` among ``cands (n, 2, 4, 4)`` (both IPPE solutions of ``n``
    sightings, NaN where absent) closest, summed over the sightings, to each sighting's nearer
    solution: the solution the sightings agree on."""
    flat = cands.reshape(-1, 4, 4)
    ok = np.flatnonzero(np.isfinite(flat).all(axis=(1, 2)))
    d = _pose_distance(flat[ok][:, None, None], cands[None])  # (k, n, 2)
    d = np.where(np.isfinite(d), d, np.inf).min(axis=2)
    d = np.where(np.isfinite(d), d, 0.0).sum(axis=1)
    return np.asarray(flat[ok[int(np.argmin(d))]])


def link_tags(
    world_T_tag: F64, known: np.ndarray, cam_T_tag: F64, ob: CornerObservations, t_s: F64, *,
    px_per_unit: float, max_gap_s: float, sightings: int = 3,
) -> tuple[F64, np.ndarray]:
    """Place tags the pose graph could not (never seen together with a mapped tag without
    ambiguity) through the trajectory: one sweep in time, each frame posed from its known tags
    (the candidate that reprojects them best) or, with none, by constant-velocity extrapolation
    from the last two posed frames -- never across more than ``max_gap_s`` -- and an unknown tag
    placed once it has ``sightings`` posed sightings (or at its last), at the IPPE solution they
    agree on. Returns the map ``(T, 4, 4)`` and the known mask ``(T,)``; the joint solve then
    refines it all."""
    world_T_tag, known = world_T_tag.copy(), np.asarray(known, bool).copy()
    n_f = len(t_s)
    order = np.lexsort((ob.tag, ob.frame))
    starts = np.searchsorted(ob.frame[order], np.arange(n_f + 1))
    last_sighting = np.full(len(known), -1)
    np.maximum.at(last_sighting, ob.tag, ob.frame)
    pending: dict[int, list[F64]] = {}
    posed: list[tuple[float, F64]] = []  # (t, world_T_cam) of the last two posed frames
    t_known = -np.inf  # when a frame was last posed from known tags
    for fr in range(n_f):
        obs = order[starts[fr]:starts[fr + 1]]
        k = known[ob.tag[obs]]
        pose = None
        if k.any():
            pose = _best_candidate(world_T_tag, cam_T_tag, ob, obs[k], px_per_unit)
            if pose is not None:
                t_known = float(t_s[fr])
        elif len(posed) == 2 and t_s[fr] - t_known <= max_gap_s:
            (t1, T1), (t2, T2) = posed
            a = (t_s[fr] - t2) / max(t2 - t1, 1e-9)
            pose = np.eye(4)
            pose[:3, :3] = T2[:3, :3] @ R_from_rotvec(a * log_so3(T1[:3, :3].T @ T2[:3, :3]))
            pose[:3, 3] = T2[:3, 3] + a * (T2[:3, 3] - T1[:3, 3])
        if pose is None:
            continue
        if posed and t_s[fr] - posed[-1][0] > max_gap_s:
            posed = []
        posed = [*posed[-1:], (float(t_s[fr]), pose)]
        for o in obs[~k]:
            tag = int(ob.tag[o])
            pending.setdefault(tag, []).append(pose @ cam_T_tag[o])
            if len(pending[tag]) >= sightings or fr >= last_sighting[tag]:
                world_T_tag[tag] = _medoid(np.stack(pending.pop(tag)))
                known[tag] = True
    return world_T_tag, known


def _best_candidate(world_T_tag: F64, cam_T_tag: F64, ob: CornerObservations, kn: I64,
                    px_per_unit: float) -> F64 | None:
    """Of the IPPE candidates ``world_T_cam`` of observations ``kn`` (known tags of one frame),
    the one reprojecting all of them best (squared px, capped per tag); None if none is finite."""
    cand = (world_T_tag[ob.tag[kn]][:, None] @ inv(cam_T_tag[kn])).reshape(-1, 4, 4)
    cand = cand[np.isfinite(cand).all(axis=(1, 2))]
    if not len(cand):
        return None
    pts_w = (np.einsum("oij,okj->oki", world_T_tag[ob.tag[kn], :3, :3], ob.pts_tag[kn])
             + world_T_tag[ob.tag[kn], None, :3, 3])
    score = _capped_sq(inv(cand)[:, None], pts_w[None], ob.uv[kn][None],
                       (8.0 / px_per_unit) ** 2).sum(1)
    return np.asarray(cand[int(np.argmin(score))])


def _capped_sq(cam_T_world: F64, pts_w: F64, uv: F64, cap2: float) -> F64:
    """Mean squared corner error (normalised units) of world corners ``pts_w (..., 4, 3)`` seen
    at ``uv (..., 4, 2)`` from ``cam_T_world (..., 4, 4)`` (broadcast), capped at ``cap2``
    (a corner behind the camera counts as the cap): the candidate score of the start poses."""
    pc = (np.einsum("...ij,...kj->...ki", cam_T_world[..., :3, :3], pts_w)
          + cam_T_world[..., None, :3, 3])
    z = pc[..., 2:3]
    e = np.where(z > 1e-6, pc[..., :2] / np.where(z > 1e-6, z, 1.0) - uv, 1e3)
    return np.asarray(np.minimum(np.mean(np.sum(e * e, -1), -1), cap2))
