"""Pinhole camera with plumb_bob distortion, tag corners and tag visibility for the simulator.

Pixel convention: OpenCV's (pixel centres at integer coordinates). The camera frame is the optical
frame (x right, y down, z forward). Tag frame per SPEC: origin at the tag centre, x right, y up,
z out of the face; detector corner i sits at ``tag_corners(s)[i]``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from functools import lru_cache
from typing import Any

import numpy as np

from tagtrail.errors import SpecError
from tagtrail.geometry.se3 import F64

# The LIMO's Orbbec Dabai colour camera (NOTES "The LIMO"), 640x480.
LIMO_K = (442.17, 443.88, 323.04, 246.51)
LIMO_D = (0.0449, -0.0770, 0.0025, 0.0012, 0.0)


@dataclass(frozen=True)
class CameraModel:
    """A ``width x height`` camera: intrinsics (px), plumb_bob ``dist`` = (k1, k2, p1, p2, k3)."""

    width: int = 640
    height: int = 480
    fx: float = LIMO_K[0]
    fy: float = LIMO_K[1]
    cx: float = LIMO_K[2]
    cy: float = LIMO_K[3]
    dist: tuple[float, ...] = LIMO_D
    frame_id: str = "camera_color_optical_frame"

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16 or self.fx <= 0 or self.fy <= 0:
            raise SpecError(
                f"invalid camera {self.width}x{self.height}, fx={self.fx}, fy={self.fy}"
            )
        if len(self.dist) != 5:
            raise SpecError(f"plumb_bob needs 5 distortion coefficients, got {len(self.dist)}")

    @property
    def K(self) -> F64:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def D(self) -> F64:
        return np.asarray(self.dist, dtype=np.float64)

    def scaled(self, width: int, height: int) -> CameraModel:
        """The same lens on a ``width x height`` sensor (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        return replace(
            self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
        )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["dist"] = [float(x) for x in self.dist]
        d["distortion_model"] = "plumb_bob"
        return d

    def project(self, pts_cam: F64) -> F64:
        """Distorted pixels ``(..., 2)`` of points ``(..., 3)`` in the camera frame (plumb_bob)."""
        xy = distort(pts_cam[..., :2] / pts_cam[..., 2:3], self.dist)
        return np.stack([self.fx * xy[..., 0] + self.cx, self.fy * xy[..., 1] + self.cy], -1)


def distort(xy: F64, dist: tuple[float, ...]) -> F64:
    """Brown-Conrady (plumb_bob) distortion of normalised coordinates ``(..., 2)``."""
    k1, k2, p1, p2, k3 = dist
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], -1)


def undistort(xy_d: F64, dist: tuple[float, ...], iters: int = 40) -> F64:
    """Invert :func:`distort` on normalised coordinates ``(..., 2)`` (fixed-point iteration,
    converges to ~1e-12 for mild lenses; check the residual if in doubt)."""
    k1, k2, p1, p2, k3 = dist
    xy = xy_d.copy()
    for _ in range(iters):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        xy = np.stack([(xy_d[..., 0] - dx) / radial, (xy_d[..., 1] - dy) / radial], -1)
    return xy


@lru_cache(maxsize=8)
def undistort_grid(camera: CameraModel) -> F64:
    """Normalised ideal coordinates ``(H, W, 2)`` of every distorted pixel centre."""
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64),
                       np.arange(camera.height, dtype=np.float64))
    xy_d = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy], -1)
    xy = undistort(xy_d, camera.dist)
    err = np.abs(distort(xy, camera.dist) - xy_d).max() * max(camera.fx, camera.fy)
    if not err < 1e-3:
        raise SpecError(f"camera distortion {camera.dist} is not invertible over the image "
                        f"(residual {err:.3g} px)")
    return xy


@lru_cache(maxsize=8)
def ideal_bounds(camera: CameraModel) -> tuple[float, float, float, float]:
    """``(xmin, xmax, ymin, ymax)`` of normalised ideal coordinates that land inside the image.

    Points outside this box are rejected before distorting: the polynomial model folds far-off
    points back into the image.
    """
    g = undistort_grid(camera)
    return float(g[..., 0].min()), float(g[..., 0].max()), float(g[..., 1].min()), float(
        g[..., 1].max()
    )


def tag_corners(size_m: float | F64) -> F64:
    """Detector corners 0..3 in the tag frame (SPEC), shape ``(..., 4, 3)``, metres."""
    s = np.asarray(size_m, dtype=np.float64)[..., None] / 2.0
    sx = np.array([-1.0, 1.0, 1.0, -1.0])
    sy = np.array([-1.0, -1.0, 1.0, 1.0])
    return np.stack([sx * s, sy * s, np.zeros_like(sx * s)], -1)


@dataclass(frozen=True)
class Visibility:
    """Which tags a detector would report: ``(N, M)`` arrays, corners ``(N, M, 4, 2)`` px."""

    visible: np.ndarray
    corners_px: F64
    edge_px: F64
    cos_incidence: F64
    range_m: F64


def tag_visibility(
    camera: CameraModel,
    cam_T_tag: F64,
    sizes_m: F64,
    *,
    max_range_m: float = 3.5,
    max_incidence_deg: float = 65.0,
    min_edge_px: float = 12.0,
    margin_px: float = 2.0,
) -> Visibility:
    """Tags fully in view, facing the camera, within range and large enough.

    ``cam_T_tag`` is ``(N, M, 4, 4)`` (N frames, M tags), ``sizes_m`` is ``(M,)``. Incidence is the
    angle between the tag's z axis and the direction from the tag to the camera.
    """
    corners_tag = tag_corners(np.asarray(sizes_m))  # (M, 4, 3)
    R, t = cam_T_tag[..., :3, :3], cam_T_tag[..., :3, 3]
    pts = np.einsum("nmij,mkj->nmki", R, corners_tag) + t[..., None, :]
    rng = np.linalg.norm(t, axis=-1)
    cos_inc = np.einsum("nmi,nmi->nm", R[..., :, 2], -t) / np.maximum(rng, 1e-12)
    z = pts[..., 2]
    safe = np.where(z > 1e-3, z, 1.0)[..., None]
    norm = pts[..., :2] / safe
    xmin, xmax, ymin, ymax = ideal_bounds(camera)
    in_box = (norm[..., 0] > xmin) & (norm[..., 0] < xmax)
    in_box &= (norm[..., 1] > ymin) & (norm[..., 1] < ymax) & (z > 0.05)
    px = camera.project(np.concatenate([norm, np.ones_like(safe)], -1))
    in_img = (px[..., 0] >= margin_px) & (px[..., 0] <= camera.width - 1 - margin_px)
    in_img &= (px[..., 1] >= margin_px) & (px[..., 1] <= camera.height - 1 - margin_px)
    edge = np.linalg.norm(px - np.roll(px, 1, axis=-2), axis=-1).min(axis=-1)
    visible = (in_box & in_img).all(axis=-1) & (rng <= max_range_m)
    visible &= (cos_inc >= np.cos(np.radians(max_incidence_deg))) & (edge >= min_edge_px)
    return Visibility(visible, px, edge, cos_inc, rng)
