"""Temporal regularisation of a pose sequence on SO(3) x R^3 (paper Sec. 3.1, last step).

Unknowns: ``p_k`` and ``R_k = R^_k Exp(dr_k)`` around the raw poses ``(R^_k, p^_k)``.
Residual blocks (3-vectors), each divided by its standard deviation::

    data      (p_k - p^_k) / pos_sigma           Log(R^_k^T R_k) / rot_sigma  (= dr_k / rot_sigma)
    accel     a_k / pos_acc                      alpha_k / rot_acc

with non-uniform finite differences over each interior sample of a segment
(``h1 = t_k - t_{k-1}``, ``h2 = t_{k+1} - t_k``)::

    a_k     = 2 / (h1 + h2) * ((p_{k+1} - p_k) / h2 - (p_k - p_{k-1}) / h1)        (m/s^2)
    alpha_k = 2 / (h1 + h2) * (w_k / h2 - w_{k-1} / h1),  w_k = Log(R_k^T R_{k+1})  (rad/s^2)

``w_k`` is the increment between consecutive orientations on the manifold (its axis is the same
in the frames of ``R_k`` and ``R_{k+1}``), so yaw crossing +-180 deg is as smooth as any other
angle. A robust loss (``f_scale`` in standard deviations) acts on each 3-vector block, so real
manoeuvres and outlier frames (e.g. an IPPE flip) are not smeared. Segments break where the
stamps jump by more than ``max_gap_s`` (or do not increase). Sparse analytic Jacobian; scipy
``least_squares`` (``trf``).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.posegraph import block_loss
from tagtrail.geometry.robust import LossName
from tagtrail.geometry.rotations import log_so3, right_jacobian, right_jacobian_inv
from tagtrail.geometry.se3 import R_from_rotvec


def segment_triples(t_s: F64, max_gap_s: float) -> I64:
    """Indices ``(M,)`` of samples ``k`` whose neighbours ``k-1, k+1`` are in the same segment."""
    dt = np.diff(t_s)
    brk = (dt > max_gap_s) | (dt <= 0)
    k = np.arange(1, len(t_s) - 1)
    return k[~brk[k - 1] & ~brk[k]] if len(k) else k


class _Smoother:
    def __init__(
        self,
        t_s: F64,
        R_hat: F64,
        p_hat: F64,
        triples: I64,
        sig: tuple[float, float, float, float],
    ) -> None:
        self.R_hat, self.p_hat, self.k = R_hat, p_hat, triples
        self.n = len(t_s)
        self.s_p, self.s_r, self.s_a, self.s_al = sig
        h1 = t_s[triples] - t_s[triples - 1]
        h2 = t_s[triples + 1] - t_s[triples]
        c = 2.0 / (h1 + h2)
        # a_k = cm * p_{k-1} + c0 * p_k + cp * p_{k+1}
        self.cm, self.c0, self.cp = c / h1, -c * (1 / h1 + 1 / h2), c / h2
        # Segment increments w_j = Log(R_j^T R_{j+1}) are needed for j = k-1 and j = k.
        self.j = np.unique(np.r_[triples - 1, triples])
        self.jpos = {
            "m": np.searchsorted(self.j, triples - 1),
            "p": np.searchsorted(self.j, triples),
        }

    def unpack(self, x: F64) -> tuple[F64, F64, F64]:
        v = x.reshape(self.n, 6)
        return self.R_hat @ R_from_rotvec(v[:, 3:]), v[:, :3], v[:, 3:]

    def fun(self, x: F64) -> F64:
        R, p, dr = self.unpack(x)
        k = self.k
        acc = self.cm[:, None] * p[k - 1] + self.c0[:, None] * p[k] + self.cp[:, None] * p[k + 1]
        w = log_so3(np.swapaxes(R[self.j], -1, -2) @ R[self.j + 1])
        wm, wp = w[self.jpos["m"]], w[self.jpos["p"]]
        alpha = self.cp[:, None] * wp - self.cm[:, None] * wm
        return np.concatenate(
            [
                (p - self.p_hat).reshape(-1) / self.s_p,
                dr.reshape(-1) / self.s_r,
                acc.reshape(-1) / self.s_a,
                alpha.reshape(-1) / self.s_al,
            ]
        )

    def jac(self, x: F64) -> csr_matrix:
        R, _, dr = self.unpack(x)
        n, k, m = self.n, self.k, len(self.k)
        Jr = right_jacobian(dr)
        M = np.swapaxes(R[self.j], -1, -2) @ R[self.j + 1]
        Jinv = right_jacobian_inv(log_so3(M))
        d_prev = -Jinv @ np.swapaxes(M, -1, -2) @ Jr[self.j]  # d w_j / d dr_j
        d_next = Jinv @ Jr[self.j + 1]  # d w_j / d dr_{j+1}
        a, b = self.jpos["m"], self.jpos["p"]
        cm, cp = self.cm[:, None, None], self.cp[:, None, None]
        eye = np.eye(3)
        blocks = [  # (row block offset, row index (B,), pose index (B,), col offset, (B,3,3))
            (0, np.arange(n), np.arange(n), 0, np.broadcast_to(eye / self.s_p, (n, 3, 3))),
            (n, np.arange(n), np.arange(n), 3, np.broadcast_to(eye / self.s_r, (n, 3, 3))),
        ]
        rows = np.arange(m)
        for pose, coef in ((k - 1, self.cm), (k, self.c0), (k + 1, self.cp)):
            blocks.append((2 * n, rows, pose, 0, coef[:, None, None] * eye / self.s_a))
        al = 1.0 / self.s_al
        blocks.append((2 * n + m, rows, k - 1, 3, -cm * d_prev[a] * al))
        blocks.append((2 * n + m, rows, k, 3, (cp * d_prev[b] - cm * d_next[a]) * al))
        blocks.append((2 * n + m, rows, k + 1, 3, cp * d_next[b] * al))
        r_all, c_all, v_all = [], [], []
        i3 = np.arange(3)
        for off, row, pose, coff, val in blocks:
            r = 3 * (off + row)[:, None, None] + i3[None, :, None]
            c = 6 * pose[:, None, None] + coff + i3[None, None, :]
            r_all.append(np.broadcast_to(r, val.shape).reshape(-1))
            c_all.append(np.broadcast_to(c, val.shape).reshape(-1))
            v_all.append(np.asarray(val).reshape(-1))
        shape = (3 * (2 * n + 2 * m), 6 * n)
        return coo_matrix(
            (np.concatenate(v_all), (np.concatenate(r_all), np.concatenate(c_all))), shape=shape
        ).tocsr()


def smooth_poses(
    t_s: F64,
    R: F64,
    p: F64,
    *,
    pos_sigma_m: float,
    rot_sigma_rad: float,
    pos_acc: float,
    rot_acc: float,
    loss: LossName = "soft_l1",
    f_scale: float = 3.0,
    max_gap_s: float = 1.0,
    max_nfev: int = 50,
) -> tuple[F64, F64]:
    """Smoothed rotations ``(N, 3, 3)`` and positions ``(N, 3)`` (m) of poses at ``t_s`` (s,
    ascending). ``pos_acc`` (m/s^2) and ``rot_acc`` (rad/s^2): standard deviations of the
    acceleration terms; ``pos_sigma_m``, ``rot_sigma_rad``: of the data terms.
    """
    triples = segment_triples(np.asarray(t_s, dtype=np.float64), max_gap_s)
    if len(triples) == 0:
        return R.copy(), p.copy()
    prob = _Smoother(t_s, R, p, triples, (pos_sigma_m, rot_sigma_rad, pos_acc, rot_acc))
    # Positions are absolute parameters: with x0 != 0 scipy's initial trust radius
    # (|x0 / x_scale|) admits the full Gauss-Newton step at once (x0 = 0 would give radius 1 and
    # ~10 iterations of doubling before the first real step).
    x0 = np.concatenate([p, np.zeros_like(p)], axis=1).reshape(-1)
    sol = least_squares(
        prob.fun,
        x0,
        jac=prob.jac,
        method="trf",
        loss=block_loss(loss, 3),
        f_scale=f_scale,
        x_scale="jac",
        tr_solver="lsmr",
        max_nfev=max_nfev,
        ftol=1e-6,
        xtol=1e-6,
    )
    R_s, p_s, _ = prob.unpack(sol.x)
    return R_s, p_s
