"""Rigid transforms, batched.

Convention (used everywhere in tagtrail): ``a_T_b`` is a 4x4 float64 matrix that maps points
expressed in frame ``b`` into frame ``a``: ``p_a = a_T_b @ p_b``. Frames cancel when composing,
e.g. ``world_T_cam = world_T_tag @ inv(cam_T_tag)``. Every function accepts batches of shape
``(..., 4, 4)`` (or ``(..., 3)`` vectors), returns new arrays and never mutates its inputs.
Quaternions are ordered ``q_xyzw`` (scalar last, as ROS and scipy).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from tagtrail.geometry.arrays import F64


def make_T(R: ArrayLike, t: ArrayLike) -> F64:
    """Transforms ``(..., 4, 4)`` from rotations ``(..., 3, 3)`` and translations ``(..., 3)``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def inv(T: ArrayLike) -> F64:
    """Inverse of rigid transforms via ``R^T, -R^T t`` (exact, no general matrix inverse)."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    t = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    return make_T(Rt, t)


def compose(*Ts: ArrayLike) -> F64:
    """Matrix product ``T1 @ T2 @ ...`` with broadcasting over batch dimensions."""
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(a_T_b: ArrayLike, pts_b: ArrayLike) -> F64:
    """Map points ``(..., 3)`` in frame b to frame a."""
    a_T_b = np.asarray(a_T_b, dtype=np.float64)
    pts_b = np.asarray(pts_b, dtype=np.float64)
    out_: F64 = np.einsum("...ij,...j->...i", a_T_b[..., :3, :3], pts_b) + a_T_b[..., :3, 3]
    return out_


def _batch_rot(R: F64) -> tuple[Rotation, tuple[int, ...]]:
    lead = R.shape[:-2]
    # scipy's Cython kernels reject read-only buffers (e.g. arrays from Parquet): copy.
    return Rotation.from_matrix(np.array(R.reshape(-1, 3, 3))), lead


def rotvec_from_R(R: ArrayLike) -> F64:
    """Axis-angle vectors ``(..., 3)`` (radians, angle in [0, pi]) of rotations ``(..., 3, 3)``."""
    rot, lead = _batch_rot(np.asarray(R, dtype=np.float64))
    out_: F64 = rot.as_rotvec().reshape(lead + (3,))
    return out_


def R_from_rotvec(rv: ArrayLike) -> F64:
    """Rotation matrices ``(..., 3, 3)`` of axis-angle vectors ``(..., 3)``."""
    rv = np.asarray(rv, dtype=np.float64)
    R = Rotation.from_rotvec(np.array(rv.reshape(-1, 3))).as_matrix()
    out_: F64 = R.reshape(rv.shape[:-1] + (3, 3))
    return out_


def R_of_rotvec(rv: ArrayLike) -> F64:
    """:func:`R_from_rotvec` of one axis-angle vector ``(3,)``: Rodrigues' formula in plain
    floats, without scipy's ~40 us a call (a live node's every dead-reckoned pose)."""
    x, y, z = np.asarray(rv, dtype=np.float64).reshape(3).tolist()
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:  # the series' first terms: exact to double precision there
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        half = math.sin(th / 2) / th
        a, b = math.sin(th) / th, 2.0 * half * half  # (1 - cos) / th^2, without cancellation
    return np.array(
        [
            [1.0 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y],
            [b * x * y + a * z, 1.0 - b * (x * x + z * z), b * y * z - a * x],
            [b * x * z - a * y, b * y * z + a * x, 1.0 - b * (x * x + y * y)],
        ]
    )


def quat_xyzw_from_R(R: ArrayLike) -> F64:
    """Unit quaternions ``(..., 4)`` ordered (qx, qy, qz, qw), with qw >= 0."""
    rot, lead = _batch_rot(np.asarray(R, dtype=np.float64))
    q = rot.as_quat(canonical=True)
    out_: F64 = q.reshape(lead + (4,))
    return out_


def quat_xyzw_of(R: ArrayLike) -> tuple[float, float, float, float]:
    """:func:`quat_xyzw_from_R` of one orthonormal rotation matrix ``(3, 3)``, in plain floats:
    scipy's formulas (the branch of the largest of the diagonal and the trace) and sign
    (qw >= 0; at qw = 0 the first non-zero component > 0), without its ~70 us a call (a live
    node's every pose)."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(R, dtype=np.float64).tolist()
    tr = a + e + i
    k = max(range(4), key=(a, e, i, tr).__getitem__)  # the first of equal maxima, as argmax
    if k == 0:
        q = (1 - tr + 2 * a, d + b, g + c, h - f)
    elif k == 1:
        q = (b + d, 1 - tr + 2 * e, h + f, c - g)
    elif k == 2:
        q = (c + g, f + h, 1 - tr + 2 * i, d - b)
    else:
        q = (h - f, c - g, d - b, 1 + tr)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    x, y, z, w = (v / n for v in q)
    if w < 0 or (w == 0 and next((v for v in (x, y, z) if v != 0), 0.0) < 0):
        x, y, z, w = -x, -y, -z, -w
    return x, y, z, w


def R_from_quat_xyzw(q_xyzw: ArrayLike) -> F64:
    """Rotation matrices of quaternions ``(..., 4)`` ordered (qx, qy, qz, qw); normalised first."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    R = Rotation.from_quat(np.array(q.reshape(-1, 4))).as_matrix()
    out_: F64 = R.reshape(q.shape[:-1] + (3, 3))
    return out_


def T_from_xyz_quat(xyz: ArrayLike, q_xyzw: ArrayLike) -> F64:
    """Transforms from positions ``(..., 3)`` and quaternions ``(..., 4)`` (qx, qy, qz, qw)."""
    return make_T(R_from_quat_xyzw(q_xyzw), xyz)


def xyz_quat_from_T(T: ArrayLike) -> tuple[F64, F64]:
    """Split transforms into positions ``(..., 3)`` and quaternions ``(..., 4)`` (xyzw)."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), quat_xyzw_from_R(T[..., :3, :3])


def T_from_rotvec_t(rv: ArrayLike, t: ArrayLike) -> F64:
    """Transforms from axis-angle ``(..., 3)`` and translation ``(..., 3)`` (OpenCV rvec/tvec)."""
    return make_T(R_from_rotvec(rv), t)


def rotation_angle(R: ArrayLike) -> F64:
    """Rotation angle in radians, [0, pi], of rotations ``(..., 3, 3)`` (numerically safe)."""
    R = np.asarray(R, dtype=np.float64)
    out_: F64 = np.linalg.norm(rotvec_from_R(R), axis=-1)
    return out_


def pose_error(a_T_b: ArrayLike, a_T_b_ref: ArrayLike) -> tuple[F64, F64]:
    """Translation error (m) and rotation error (rad) between two batches of poses."""
    a_T_b = np.asarray(a_T_b, dtype=np.float64)
    a_T_b_ref = np.asarray(a_T_b_ref, dtype=np.float64)
    dt = np.linalg.norm(a_T_b[..., :3, 3] - a_T_b_ref[..., :3, 3], axis=-1)
    dR = np.swapaxes(a_T_b_ref[..., :3, :3], -1, -2) @ a_T_b[..., :3, :3]
    return dt, rotation_angle(dR)
