"""Planes, headings and the reference path: the geometry of relocalization (paper §3.2).

A plane is an orthonormal, right-handed basis ``(e1, e2, n)`` of the world frame, ``n = e1 × e2``;
a world point ``p`` has in-plane coordinates ``(u, v) = (p·e1, p·e2)`` (no origin shift, so with
``xz`` they are the world x and z). The heading of a camera is ``θ = atan2(f·e2, f·e1)`` with
``f`` its optical axis (the z column of ``world_R_cam``). Example: in the original set-up (anchor
tag upright on a wall, world y up) ``plane="xz"`` gives ``e1 = x, e2 = z, n = −y``.

:class:`ReferencePath` is built once from the reference trajectory (planar samples, Eq. 3.14
headings, a KD-tree, polyline segments) and then answers queries — a batch offline, or one pose
at a time in the live node — without rebuilding anything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from tagtrail.errors import DataError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.pathindex import PathIndex
from tagtrail.geometry.rotations import wrap_angle

PlaneName = Literal["auto", "xz", "xy", "yz"]
PLANES: tuple[str, ...] = ("auto", "xz", "xy", "yz")
_FIXED = {"xz": (0, 2), "xy": (0, 1), "yz": (1, 2)}
#: Below this RMS spread (m) along their 2nd principal axis the reference positions do not define
#: a plane (a straight or parked run); ``auto`` then takes n from the cameras' mean y axis.
MIN_PLANE_SPREAD_M = 0.01
_TIE_M = 1e-12  # distances closer than this are ties; the earlier segment wins
_BRUTE_MAX = 8192  # single-pose queries scan references up to this size (faster than the tree)


def circular_mean(angles: ArrayLike) -> float:
    """Circular mean (rad) of angles (rad): ``atan2(mean sin, mean cos)``."""
    a = np.asarray(angles, dtype=np.float64)
    if a.size == 0:
        raise DataError("circular mean of no angles")
    return float(np.arctan2(np.sin(a).mean(), np.cos(a).mean()))


@dataclass(frozen=True)
class Plane:
    """In-plane axes ``e1, e2`` and normal ``n = e1 × e2`` (unit ``(3,)`` world vectors)."""

    name: str
    e1: F64
    e2: F64
    n: F64

    @property
    def basis(self) -> F64:
        """``(3, 3)`` matrix with rows ``e1, e2, n``: world vector → (u, v, w) plane coordinates."""
        return np.stack([self.e1, self.e2, self.n])

    def to_uv(self, pts_world: ArrayLike) -> F64:
        """In-plane coordinates ``(..., 2)`` (m) of world points ``(..., 3)`` (m)."""
        return np.asarray(pts_world, dtype=np.float64) @ self.basis[:2].T

    def heading(self, world_R_cam: ArrayLike) -> F64:
        """Headings ``(...)`` (rad) of camera rotations ``(..., 3, 3)``: atan2(f·e2, f·e1)."""
        f_uv = np.asarray(world_R_cam, dtype=np.float64)[..., :, 2] @ self.basis[:2].T
        return np.arctan2(f_uv[..., 1], f_uv[..., 0])

    def v_down(self, world_R_cam: ArrayLike) -> bool:
        """Whether a drawing seen from above shows v downwards: the normal points along the
        cameras' mean "down" (their y axis; rotations ``(N, 3, 3)``)."""
        return bool(self.n @ np.asarray(world_R_cam, dtype=np.float64)[:, :, 1].mean(axis=0) > 0)

    def rotation_about_normal(self, angle_rad: float) -> F64:
        """World rotation ``(3, 3)`` by ``angle_rad`` about ``n``: adds the angle to headings."""
        c, s = np.cos(angle_rad), np.sin(angle_rad)
        B = self.basis
        R: F64 = B.T @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ B
        return R


def _unit(v: F64) -> F64:
    return v / np.linalg.norm(v)


def resolve_plane(
    name: str, positions_world: ArrayLike | None = None, world_R_cam: ArrayLike | None = None
) -> Plane:
    """The plane called ``name`` (SPEC Conventions); ``auto`` needs the reference poses.

    ``auto``: n = normal of the least-squares plane of ``positions_world (N, 3)`` (m), oriented
    along the mean camera y axis (``world_R_cam (N, 3, 3)``, optical y = "down"); n = that mean
    axis when the positions do not span a plane. e1 = world x projected on the plane (world z if
    x ∥ n), e2 = n × e1. An upright anchor tag (world y up) gives ≈ ``xz``.
    """
    if name in _FIXED:
        i, j = _FIXED[name]
        e1, e2 = np.eye(3)[i], np.eye(3)[j]
        return Plane(name, e1, e2, np.cross(e1, e2))
    if name != "auto":
        raise DataError(f"unknown plane {name!r}: use one of {', '.join(PLANES)}")
    if positions_world is None or world_R_cam is None:
        raise DataError("plane 'auto' needs the reference trajectory's positions and rotations")
    P = np.asarray(positions_world, dtype=np.float64).reshape(-1, 3)
    R = np.asarray(world_R_cam, dtype=np.float64).reshape(-1, 3, 3)
    if len(P) == 0 or len(R) == 0:
        raise DataError("plane 'auto': the reference trajectory has no poses")
    if not (np.isfinite(P).all() and np.isfinite(R).all()):
        raise DataError("plane 'auto': the reference trajectory has non-finite poses")
    down = R[:, :, 1].mean(axis=0)
    if np.linalg.norm(down) < 1e-6:
        raise DataError("plane 'auto': the reference trajectory has no usable camera orientation")
    n = _unit(down)
    if len(P) >= 3:
        _, s, vt = np.linalg.svd(P - P.mean(axis=0), full_matrices=False)
        if s[1] / np.sqrt(len(P)) >= MIN_PLANE_SPREAD_M:
            n = vt[2] if vt[2] @ down >= 0 else -vt[2]
    e1 = np.eye(3)[0] - (np.eye(3)[0] @ n) * n
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.eye(3)[2] - (np.eye(3)[2] @ n) * n
    e1 = _unit(e1)
    return Plane("auto", e1, np.cross(n, e1), n)


def path_headings(uv: ArrayLike) -> F64:
    """Reference headings ``(N,)`` (rad) of planar samples ``uv (N, 2)`` (Eq. 3.14).

    Centred difference ``p[k+1] − p[k−1]``, one-sided at the ends; where it vanishes (a pause)
    the previous heading is kept (the next one at the start, 0 if the path never moves).
    """
    p = np.asarray(uv, dtype=np.float64)
    if len(p) < 2:
        return np.zeros(len(p))
    d = np.empty_like(p)
    d[1:-1] = p[2:] - p[:-2]
    d[0], d[-1] = p[1] - p[0], p[-1] - p[-2]
    h = np.arctan2(d[:, 1], d[:, 0])
    ok = np.hypot(d[:, 0], d[:, 1]) > 1e-12
    if not ok.any():
        return np.zeros(len(p))
    idx = np.where(ok, np.arange(len(p)), 0)
    idx = np.maximum.accumulate(idx)
    idx[: np.argmax(ok)] = np.argmax(ok)
    return h[idx]


class PathMatch(NamedTuple):
    """Association of M query poses with the reference (arrays of length M; angles in rad)."""

    ref_idx: NDArray[np.int64]  # k* (Eq. 3.12), or the segment [k, k+1] in polyline mode
    distance_m: F64  # D (Eq. 3.13)
    phi_rad: F64  # wrap(θq − θref) (Eq. 3.15)
    query_heading_rad: F64
    ref_heading_rad: F64
    query_uv: F64  # (M, 2)
    ref_uv: F64  # (M, 2): the reference sample, or the nearest point of the polyline


class PoseMatch(NamedTuple):
    """:class:`PathMatch` of one pose as Python floats (the live node's per-message result)."""

    ref_idx: int
    distance_m: float
    phi_rad: float
    query_heading_rad: float
    ref_heading_rad: float
    u: float
    v: float
    ref_u: float
    ref_v: float


class ReferencePath:
    """The reference trajectory reduced to a plane, ready for nearest-sample/segment queries.

    ``positions_world (N, 3)`` (m) are world_T_cam positions in time order; ``plane`` is a
    :class:`Plane` (see :func:`resolve_plane`). Built once: planar samples ``uv``, headings
    (Eq. 3.14), a KD-tree over ``uv`` and the polyline segments with their headings.
    """

    def __init__(self, positions_world: ArrayLike, plane: Plane) -> None:
        P = np.asarray(positions_world, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(P).all():
            raise DataError("the reference trajectory has non-finite positions")
        self.plane = plane
        self._B2 = np.ascontiguousarray(plane.basis[:2].T)  # (3, 2)
        self.uv = P @ self._B2
        if len(self.uv) < 2 or np.ptp(self.uv, axis=0).max() <= 1e-9:
            raise DataError("the reference trajectory needs at least 2 distinct planar positions")
        self.heading_rad = path_headings(self.uv)
        self.tree = cKDTree(self.uv)
        self.seg_a = self.uv[:-1]
        self.seg_d = self.uv[1:] - self.uv[:-1]
        self.seg_len2 = np.einsum("ij,ij->i", self.seg_d, self.seg_d)
        self.seg_heading_rad = np.arctan2(self.seg_d[:, 1], self.seg_d[:, 0])
        self._seg_ok = self.seg_len2 > 1e-24
        # single-pose fast path: plain floats, and a brute-force scan while it beats the tree
        self._e1, self._e2 = plane.e1.tolist(), plane.e2.tolist()
        self._u, self._v = self.uv[:, 0].copy(), self.uv[:, 1].copy()
        self._h = self.heading_rad.tolist()
        self._index: PathIndex | None = None  # built on the first long single-pose query

    def __len__(self) -> int:
        return len(self.uv)

    def planar(self, positions_world: ArrayLike, world_R_cam: ArrayLike) -> tuple[F64, F64]:
        """Planar positions ``(M, 2)`` (m) and headings ``(M,)`` (rad) of world poses."""
        uv = np.asarray(positions_world, dtype=np.float64).reshape(-1, 3) @ self._B2
        f = np.asarray(world_R_cam, dtype=np.float64).reshape(-1, 3, 3)[:, :, 2] @ self._B2
        return uv, np.arctan2(f[:, 1], f[:, 0])

    def query(self, positions_world: ArrayLike, world_R_cam: ArrayLike) -> PathMatch:
        """Nearest reference sample of each pose (Eqs. 3.12–3.15, ``trajectory`` mode).

        ``positions_world (M, 3)`` or ``(3,)`` (m), ``world_R_cam (M, 3, 3)`` or ``(3, 3)``.
        """
        uv, heading = self.planar(positions_world, world_R_cam)
        return self.query_uv(uv, heading)

    def query_uv(self, uv: ArrayLike, heading_rad: ArrayLike) -> PathMatch:
        """As :meth:`query`, from planar positions ``(M, 2)`` (m) and headings ``(M,)`` (rad)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        hq = np.asarray(heading_rad, dtype=np.float64).reshape(-1)
        dist, k = self.tree.query(uv)
        k = np.asarray(k, dtype=np.int64)
        href = self.heading_rad[k]
        return PathMatch(k, np.asarray(dist), wrap_angle(hq - href), hq, href, uv, self.uv[k])

    def query_one(self, position_world: ArrayLike, world_R_cam: ArrayLike) -> PoseMatch:
        """:meth:`query` for one pose ``(3,)`` (m), ``(3, 3)``, in microseconds (live node)."""
        x, y, z = np.asarray(position_world, dtype=np.float64).tolist()
        (_, _, fx), (_, _, fy), (_, _, fz) = np.asarray(world_R_cam, dtype=np.float64).tolist()
        return self.query_point(x, y, z, fx, fy, fz)

    def query_point(
        self, x: float, y: float, z: float, fx: float, fy: float, fz: float
    ) -> PoseMatch:
        """:meth:`query_one` of plain floats: position ``(x, y, z)`` (m) and optical axis
        ``f = world_R_cam[:, 2]`` — the live node's per-pose call, with no array conversions."""
        u, v, hq = self.planar_point(x, y, z, fx, fy, fz)
        dist, k = self.nearest_sample(u, v)
        href = self._h[k]
        phi = math.pi - (math.pi - (hq - href)) % (2.0 * math.pi)
        return PoseMatch(k, dist, phi, hq, href, u, v, float(self._u[k]), float(self._v[k]))

    def planar_point(
        self, x: float, y: float, z: float, fx: float, fy: float, fz: float
    ) -> tuple[float, float, float]:
        """``(u, v, θ)`` (m, m, rad) of a world position ``(x, y, z)`` (m) and optical axis
        ``f = world_R_cam[:, 2]``, in plain floats (the live node's per-pose call)."""
        (a1, b1, c1), (a2, b2, c2) = self._e1, self._e2
        u, v = a1 * x + b1 * y + c1 * z, a2 * x + b2 * y + c2 * z
        return u, v, math.atan2(a2 * fx + b2 * fy + c2 * fz, a1 * fx + b1 * fy + c1 * fz)

    def nearest_sample(self, u: float, v: float) -> tuple[float, int]:
        """``(D (m), k*)``: the reference sample nearest the planar point ``(u, v)`` (m) over the
        whole path (Eq. 3.12; ties → the lowest index), for one pose in microseconds."""
        if len(self._h) <= _BRUTE_MAX:
            d2 = self._u - np.array(u)  # 0-d arrays: numpy calls with Python floats cost more
            dv = self._v - np.array(v)
            d2 *= d2
            dv *= dv
            d2 += dv
            k = int(d2.argmin())
            return math.sqrt(float(d2[k])), k
        # a k-d tree is slow inside a loop; PathIndex uses the path's order (exact)
        if self._index is None:
            self._index = PathIndex(self.uv)
        return self._index.query_one(u, v)

    def query_polyline(self, uv: ArrayLike, heading_rad: ArrayLike) -> PathMatch:
        """Nearest point of the reference polyline (``point`` mode); θref = that segment's heading.

        ``ref_idx`` is the segment ``[k, k+1]``; at a vertex shared by two segments the earlier
        segment wins (as the original tool). ``uv (M, 2)`` (m), ``heading_rad (M,)``.
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        hq = np.asarray(heading_rad, dtype=np.float64).reshape(-1)
        seg = np.empty(len(uv), dtype=np.int64)
        proj = np.empty_like(uv)
        # chunks bound the (M, S) temporaries to ~1e6 entries
        step = max(1, 1_000_000 // len(self.seg_a))
        for lo in range(0, len(uv), step):
            q = uv[lo : lo + step, None, :]  # (m, 1, 2)
            t = np.einsum("msj,sj->ms", q - self.seg_a, self.seg_d)
            t = np.clip(np.divide(t, self.seg_len2, where=self._seg_ok, out=np.zeros_like(t)), 0, 1)
            p = self.seg_a + t[..., None] * self.seg_d  # (m, S, 2)
            d = np.hypot(*(q - p).transpose(2, 0, 1))
            d[:, ~self._seg_ok] = np.inf
            best = np.argmax(d <= d.min(axis=1, keepdims=True) + _TIE_M, axis=1)
            seg[lo : lo + step] = best
            proj[lo : lo + step] = p[np.arange(len(best)), best]
        href = self.seg_heading_rad[seg]
        dist = np.hypot(*(uv - proj).T)
        return PathMatch(seg, dist, wrap_angle(hq - href), hq, href, uv, proj)


def reduce_to_point(uv: ArrayLike, heading_rad: ArrayLike) -> tuple[F64, float, int]:
    """A parked capture as one pose: median ``(u, v)`` (m), circular-mean heading (rad), and the
    index of the sample nearest that median (for its time stamp). ``uv (M, 2)``."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        raise DataError("the query trajectory is empty")
    med = np.median(uv, axis=0)
    i = int(np.argmin(np.hypot(*(uv - med).T)))
    return med, circular_mean(heading_rad), i


def capture_radius_p95(uv: ArrayLike) -> float:
    """95th percentile (m) of the distances of planar positions ``(M, 2)`` to their centroid."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) < 2:
        return 0.0
    return float(np.percentile(np.hypot(*(uv - uv.mean(axis=0)).T), 95))


def reference_plane(name: str, P: F64, R: F64) -> Plane:
    """The plane ``name``; ``auto`` is fitted to the reference poses ``P (N, 3)``, ``R (N, 3, 3)``
    (SPEC Conventions)."""
    if name != "auto":
        return resolve_plane(name)
    if len(P) == 0:
        raise DataError("plane 'auto': the reference trajectory is empty")
    return resolve_plane("auto", P, R)
