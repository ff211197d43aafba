"""The motion prior: a constant-velocity (white-noise-on-acceleration) prior over the frames.

``m_k`` (6,) at each frame ``k`` whose neighbours ``k-1, k+1`` lie within ``max_gap_s`` (gaps
without tags stay gaps: the chain breaks there and nothing is invented across). With ``h1 = t_k -
t_{k-1}``, ``h2 = t_{k+1} - t_k``, ``c`` the camera centre in the world and ``w_j = Log(R_j^T
R_{j+1})`` the body-frame increment of ``world_R_cam``::

    a_k     = 2 / (h1 + h2) * ((c_{k+1} - c_k) / h2 - (c_k - c_{k-1}) / h1)     (m/s^2)
    alpha_k = 2 / (h1 + h2) * (w_k / h2 - w_{k-1} / h1)                         (rad/s^2)
    m_k     = sqrt(3 h / 2) * [alpha_k / ang_sigma ; a_k / acc_sigma],  h = (h1 + h2) / 2

``frame="camera"`` takes the translation part in the camera's own frame instead (a constant
twist), with ``q_j = R_j (c_{j+1} - c_j)`` the step to the next frame seen from camera ``j``
(``R_j`` = cam_R_world)::

    a_k     = 2 / (h1 + h2) * (q_k / h2 - q_{k-1} / h1)

A robot driving an arc at constant speed and turn rate has zero residual there, where the
world-frame second difference (its centripetal ``v w``) pulls each frame towards its
neighbours' chord — and the newest frame of a live window, which only the past constrains,
towards the straight extrapolation: the live smoother's lag on curves
(``stream/continuity.py``; bench/LIVE_POSE.md: a rendered circle posed live to 0.36 mm
instead of 5.2). Offline, with frames on both sides, the world frame stays: there the camera
frame ties a wrong heading to the path (with 1 s of 20 % wheel slip in a 5 s stretch without
tags: 26 cm against 4.3, tests/geometry/test_odometry_prior.py).

White noise of density ``acc_sigma`` (m/s^2/sqrt(Hz)) on the acceleration gives the second
difference a variance ``2 h^3 acc_sigma^2 / 3``, hence the scale. Single-tag frames are held by
their neighbours, and tags never seen together are linked through the trajectory. A robust loss
on each frame's 6-vector: motion far beyond the prior (a bump, or stamps that are not the
capture times) stops being smoothed instead of bending the map. The prior has no unknowns of its
own; it ties frames ``k-1, k, k+1`` (the camera block of the normal equations stays banded).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.joint.problem import Terms, centres
from tagtrail.geometry.robust import LossName, rho
from tagtrail.geometry.rotations import hat, log_so3, right_jacobian_inv
from tagtrail.geometry.smoothing import segment_triples


@dataclass(frozen=True)
class MotionPrior:
    """Constant-velocity prior over frames stamped ``t_s (F,)`` (s, increasing): acceleration
    noise densities ``acc_sigma`` (m/s^2/sqrt(Hz)) and ``ang_sigma`` (rad/s^2/sqrt(Hz));
    stamps further apart than ``max_gap_s`` break the chain. ``loss`` acts on each frame's
    whitened 6-vector with scale ``f_scale`` (standard deviations); ``frame``: the velocity's
    (module docstring)."""

    t_s: F64
    acc_sigma: float
    ang_sigma: float
    max_gap_s: float
    loss: LossName = "cauchy"
    f_scale: float = 3.0
    frame: Literal["world", "camera"] = "world"

    name = "motion"
    n_params = 0
    start = None
    uses: tuple[str, ...] = ()

    @cached_property
    def k(self) -> I64:
        """The frames ``k (M,)`` held by the prior (both neighbours within ``max_gap_s``)."""
        t = np.asarray(self.t_s, np.float64)
        if len(t) < 3:
            return np.zeros(0, np.int64)
        return segment_triples(t, self.max_gap_s).astype(np.int64)

    @cached_property
    def _coef(self) -> tuple[F64, F64, F64, F64, F64, F64]:
        """``h1, h2, g = 2 / (h1 + h2)``, ``coef (M, 3)`` (``a_k = coef . [c_{k-1}, c_k,
        c_{k+1}]``) and the whitening scales of the rotation and translation parts."""
        k, t = self.k, np.asarray(self.t_s, np.float64)
        h1, h2 = t[k] - t[k - 1], t[k + 1] - t[k]
        g = 2.0 / (h1 + h2)
        coef = np.stack([g / h1, -g * (1 / h1 + 1 / h2), g / h2], axis=1)
        s = np.sqrt(0.75 * (h1 + h2))  # sqrt(3 h / 2), h the mean step
        return h1, h2, g, coef, s / self.ang_sigma, s / self.acc_sigma

    def residuals(self, R: F64, t: F64) -> tuple[F64, F64]:
        """Unweighted residuals ``(M, 6)`` and Jacobians ``(M, 3, 6, 6)`` (frames k-1, k, k+1)
        at cameras ``R, t`` (``cam_T_world``)."""
        k = self.k
        if not len(k):
            return np.zeros((0, 6)), np.zeros((0, 3, 6, 6))
        h1, h2, g, coef, s_r, s_t = self._coef
        c = centres(R, t)
        E = R[:-1] @ np.swapaxes(R[1:], 1, 2)  # world_R_cam_j^T world_R_cam_{j+1}
        e = log_so3(E)
        Jinv = right_jacobian_inv(e)
        if self.frame == "camera":
            q = np.einsum("fij,fj->fi", R[:-1], c[1:] - c[:-1])  # step j -> j+1 from camera j
            a = g[:, None] * (q[k] / h2[:, None] - q[k - 1] / h1[:, None])
        else:
            a = np.einsum("mj,mji->mi", coef, np.stack([c[k - 1], c[k], c[k + 1]], axis=1))
        alpha = g[:, None] * (e[k] / h2[:, None] - e[k - 1] / h1[:, None])
        m = np.concatenate([alpha * s_r[:, None], a * s_t[:, None]], axis=1)
        J = np.zeros((len(k), 3, 6, 6))
        gr = (g * s_r)[:, None, None]
        J[:, 0, :3, :3] = -gr / h1[:, None, None] * (Jinv[k - 1] @ np.swapaxes(E[k - 1], 1, 2))
        J[:, 1, :3, :3] = gr * (
            Jinv[k] @ np.swapaxes(E[k], 1, 2) / h2[:, None, None] + Jinv[k - 1] / h1[:, None, None]
        )
        J[:, 2, :3, :3] = -gr / h2[:, None, None] * Jinv[k]
        if self.frame == "camera":  # d q_j / d w_j = -hat(q_j); d c / d v = -R^T
            gt = (g * s_t)[:, None, None]
            J[:, 0, 3:, :3] = gt / h1[:, None, None] * hat(q[k - 1])
            J[:, 0, 3:, 3:] = -gt / h1[:, None, None] * np.eye(3)
            J[:, 1, 3:, :3] = -gt / h2[:, None, None] * hat(q[k])
            J[:, 1, 3:, 3:] = gt * (np.eye(3) / h2[:, None, None] + E[k - 1] / h1[:, None, None])
            J[:, 2, 3:, 3:] = -gt / h2[:, None, None] * E[k]
            return m, J
        for j, f in enumerate((k - 1, k, k + 1)):  # d c / d v = -world_R_cam = -R^T
            J[:, j, 3:, 3:] = -(coef[:, j] * s_t)[:, None, None] * np.swapaxes(R[f], 1, 2)
        return m, J

    def terms(self, R_cam: F64, t_cam: F64, values: Mapping[str, Any]) -> Terms:
        m, J = self.residuals(R_cam, t_cam)
        f2 = self.f_scale**2
        val, w = rho(self.loss, np.sum(m * m, axis=1) / f2)
        s = np.sqrt(w)
        return Terms(
            float(f2 * val.sum()),
            m * s[:, None],
            self.k - 1,
            J * s[:, None, None, None],
            None,
            6 * len(self.k),
        )

    def update(self, value: Any, step: F64, values: Mapping[str, Any]) -> Any:
        return None
