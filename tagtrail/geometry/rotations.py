"""SO(3) helpers: hat, log, Jacobians of exp/log, geodesic angles, chordal and robust means.

Rotations are ``(..., 3, 3)`` float64 matrices, tangent vectors ``(..., 3)`` rotation vectors in
radians (axis * angle). ``Exp`` is :func:`tagtrail.geometry.se3.R_from_rotvec`, ``Log`` is
:func:`log_so3` (angle in [0, pi]; a fast drop-in for ``se3.rotvec_from_R``). Right
perturbations are used throughout: ``Exp(phi + d) ~= Exp(phi) Exp(J_r(phi) d)`` and
``Log(R Exp(d)) ~= Log(R) + J_r^{-1}(Log R) d`` (Chirikjian 2011; Sola et al. 2018, Eq. 143-146).

Grouped functions take a flat batch ``R (N, 3, 3)`` and ``group (N,)`` int labels in
``[0, n_groups)`` and return one rotation per group, vectorised over groups (no Python loop).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.se3 import R_from_rotvec

_SMALL = 1e-4  # below this angle (rad) the Jacobian coefficients use their Taylor series


def cross(a: ArrayLike, b: ArrayLike) -> F64:
    """``np.cross`` of 3-vectors ``(..., 3)`` (broadcast), by components: numpy's own moves
    axes around and costs ~30 us a call, which the live smoother's small solves make many of
    (bench/LIVE_POSE.md)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def hat(v: ArrayLike) -> F64:
    """Skew-symmetric matrices ``(..., 3, 3)`` with ``hat(v) @ w == cross(v, w)``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def _coefficients(rv: F64) -> tuple[F64, F64, F64, F64]:
    """hat(rv), hat(rv)^2 and the angle-dependent scalars a=(1-cos)/t^2, b=(t-sin)/t^3."""
    th = np.linalg.norm(rv, axis=-1)
    small = th < _SMALL
    ths = np.where(small, 1.0, th)
    th2 = th * th
    a = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / (ths * ths))
    b = np.where(small, 1.0 / 6.0 - th2 / 120.0, (ths - np.sin(ths)) / (ths**3))
    K = hat(rv)
    return K, K @ K, a, b


def right_jacobian(rv: ArrayLike) -> F64:
    """Right Jacobian ``J_r(phi)`` ``(..., 3, 3)`` of SO(3) at rotation vectors ``(..., 3)``.

    ``J_r = I - (1 - cos t)/t^2 hat(phi) + (t - sin t)/t^3 hat(phi)^2``, ``t = |phi|``.
    """
    rv = np.asarray(rv, dtype=np.float64)
    K, K2, a, b = _coefficients(rv)
    return np.eye(3) - a[..., None, None] * K + b[..., None, None] * K2


def right_jacobian_inv(rv: ArrayLike) -> F64:
    """Inverse right Jacobian ``J_r^{-1}(phi)`` ``(..., 3, 3)``, valid for ``|phi| < 2 pi``.

    ``J_r^{-1} = I + hat(phi)/2 + (1/t^2 - (1 + cos t)/(2 t sin t)) hat(phi)^2``.
    """
    rv = np.asarray(rv, dtype=np.float64)
    c = right_jacobian_inv_coefficient(np.linalg.norm(rv, axis=-1))
    K = hat(rv)
    return np.eye(3) + 0.5 * K + c[..., None, None] * (K @ K)


def right_jacobian_inv_coefficient(th: ArrayLike) -> F64:
    """``c(t) = 1/t^2 - (1 + cos t)/(2 t sin t)`` of :func:`right_jacobian_inv` at angles ``th``
    (its Taylor series below ``_SMALL``)."""
    th = np.asarray(th, dtype=np.float64)
    small = th < _SMALL
    ths = np.where(small, 1.0, th)
    # sin(t) -> 0 at t = pi: the coefficient stays finite (1/pi^2) but the formula divides 0/0.
    s = np.sin(ths)
    s = np.where(np.abs(s) < 1e-12, 1e-12, s)
    out: F64 = np.where(
        small,
        1.0 / 12.0 + th * th / 720.0,
        1.0 / (ths * ths) - (1.0 + np.cos(ths)) / (2.0 * ths * s),
    )
    return out


def _log_via_quaternion(R: F64) -> F64:
    """``log_so3`` for rotations near pi (Shepperd: largest quaternion component first)."""
    r00, r11, r22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    d01, d02, d12 = R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1]
    s21, s02, s10 = R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]
    diag = np.stack([r00 + r11 + r22, r00, r11, r22], axis=-1)
    big = 1.0 + np.stack([diag[:, 0], r00 - r11 - r22, r11 - r00 - r22, r22 - r00 - r11], axis=-1)
    # Candidate quaternions (w, x, y, z), each scaled by 4 * its largest component.
    q = np.stack(
        [
            np.stack([big[:, 0], s21, s02, s10], axis=-1),
            np.stack([s21, big[:, 1], d01, d02], axis=-1),
            np.stack([s02, d01, big[:, 2], d12], axis=-1),
            np.stack([s10, d02, d12, big[:, 3]], axis=-1),
        ],
        axis=1,
    )
    q = q[np.arange(len(R)), np.argmax(diag, axis=-1)]
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    n = np.linalg.norm(q[:, 1:], axis=-1)
    scale = 2.0 * np.arctan2(n, q[:, 0]) / np.where(n > 0, n, 1.0)
    out_: F64 = q[:, 1:] * scale[:, None]
    return out_


_SKEW_I, _SKEW_J = np.array([2, 0, 1]), np.array([1, 2, 0])


def log_so3(R: ArrayLike) -> F64:
    """Rotation vectors ``(..., 3)`` (angle in [0, pi]) of rotations ``(..., 3, 3)``.

    ``theta = atan2(|s|/2, (tr R - 1)/2)`` with ``s`` the skew part (accurate near 0), and a
    quaternion (Shepperd) path for angles near pi where the skew part vanishes. About 3x faster
    than building a scipy ``Rotation`` for large batches -- it is the hot path of the solvers.
    """
    R = np.asarray(R, dtype=np.float64)
    lead = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    s = R[:, _SKEW_I, _SKEW_J] - R[:, _SKEW_J, _SKEW_I]  # (R21 - R12, R02 - R20, R10 - R01)
    c = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0)
    n = np.sqrt(np.add.reduce(s * s, axis=-1))  # = np.linalg.norm, without its checks
    th = np.arctan2(0.5 * n, c)
    small = n < 1e-12
    scale = np.where(small, 0.5 + th * th / 12.0, th / np.where(small, 1.0, n))
    out = s * scale[:, None]
    near_pi = c < -0.99
    if near_pi.any():
        out[near_pi] = _log_via_quaternion(R[near_pi])
    out_: F64 = out.reshape(lead + (3,))
    return out_


def geodesic_angle(R_a: ArrayLike, R_b: ArrayLike) -> F64:
    """Angle (rad, [0, pi]) of ``R_a^T R_b`` for broadcastable ``(..., 3, 3)`` batches."""
    R_a = np.asarray(R_a, dtype=np.float64)
    R_b = np.asarray(R_b, dtype=np.float64)
    out_: F64 = np.linalg.norm(log_so3(np.swapaxes(R_a, -1, -2) @ R_b), axis=-1)
    return out_


def wrap_angle(a: ArrayLike) -> F64:
    """Wrap angles (rad) to ``(-pi, pi]`` (the ``wrap`` of Eq. 3.15): ``pi - mod(pi - a, 2 pi)``."""
    wrapped: F64 = np.pi - np.mod(np.pi - np.asarray(a, dtype=np.float64), 2.0 * np.pi)
    return wrapped


def project_to_so3(M: ArrayLike) -> F64:
    """Nearest rotations (Frobenius) ``(..., 3, 3)`` of matrices ``(..., 3, 3)`` via SVD."""
    M = np.asarray(M, dtype=np.float64)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = d
    out_: F64 = (U * D[..., None, :]) @ Vt
    return out_


def _group_sum(x: F64, group: I64, n_groups: int) -> F64:
    """Sum rows of ``x (N, ...)`` per group -> ``(n_groups, ...)``."""
    out = np.zeros((n_groups,) + x.shape[1:])
    np.add.at(out, group, x)
    return out


def grouped_chordal_mean(
    R: ArrayLike, group: ArrayLike, n_groups: int, weights: ArrayLike | None = None
) -> F64:
    """Chordal mean per group: ``(n_groups, 3, 3)``; empty groups give the identity."""
    R = np.asarray(R, dtype=np.float64)
    g = np.asarray(group, dtype=np.int64)
    w = np.ones(len(R)) if weights is None else np.asarray(weights, dtype=np.float64)
    S = _group_sum(R * w[:, None, None], g, n_groups)
    empty = _group_sum(w, g, n_groups) <= 0
    S[empty] = np.eye(3)
    return project_to_so3(S)


def grouped_rotation_mean(
    R: ArrayLike,
    group: ArrayLike,
    n_groups: int,
    weights: ArrayLike | None = None,
    *,
    robust: bool = True,
    iters: int = 20,
    tol: float = 1e-12,
) -> F64:
    """Rotation mean per group on the manifold: ``(n_groups, 3, 3)``.

    Starts from the chordal mean, then iterates ``M <- M Exp(sum_i c_i Log(M^T R_i) / sum_i c_i)``.
    ``robust=False``: ``c_i = w_i`` (the Karcher / geodesic L2 mean). ``robust=True``:
    ``c_i = w_i / max(|Log(M^T R_i)|, 1e-9)`` -- the Weiszfeld iteration of the geodesic L1
    median (Hartley et al. 2011, "L1 rotation averaging"), which ignores a minority of flipped
    or wrong rotations that drag an L2 mean away.
    """
    R = np.asarray(R, dtype=np.float64)
    g = np.asarray(group, dtype=np.int64)
    w = np.ones(len(R)) if weights is None else np.asarray(weights, dtype=np.float64)
    M = grouped_chordal_mean(R, g, n_groups, w)
    if len(R) == 0:
        return M
    for _ in range(iters):
        v = log_so3(np.swapaxes(M[g], -1, -2) @ R)
        c = w / np.maximum(np.linalg.norm(v, axis=-1), 1e-9) if robust else w
        num = _group_sum(v * c[:, None], g, n_groups)
        den = _group_sum(c, g, n_groups)
        step = num / np.where(den > 0, den, 1.0)[:, None]
        M = M @ R_from_rotvec(step)
        if np.max(np.linalg.norm(step, axis=-1)) < tol:
            break
    return M


def grouped_median(x: ArrayLike, group: ArrayLike, n_groups: int) -> F64:
    """Component-wise median of rows ``x (N, D)`` per group -> ``(n_groups, D)`` (NaN if empty)."""
    x = np.asarray(x, dtype=np.float64)
    g = np.asarray(group, dtype=np.int64)
    out = np.full((n_groups,) + x.shape[1:], np.nan)
    if len(x) == 0:
        return out
    order = np.argsort(g, kind="stable")
    gs, xs = g[order], x[order]
    starts = np.flatnonzero(np.r_[True, gs[1:] != gs[:-1]])
    counts = np.diff(np.r_[starts, len(gs)])
    # Sort by (group, value) per column, then pick the middle element(s) of each group.
    flat = xs.reshape(len(xs), -1)
    med = np.empty((len(starts), flat.shape[1]))
    for col in range(flat.shape[1]):
        o = np.lexsort((flat[:, col], gs))
        sc = flat[o, col]
        lo = starts + (counts - 1) // 2
        hi = starts + counts // 2
        med[:, col] = 0.5 * (sc[lo] + sc[hi])
    out[gs[starts]] = med.reshape((len(starts),) + x.shape[1:])
    return out
