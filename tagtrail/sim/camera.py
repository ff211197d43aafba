"""The simulated camera: the LIMO's lens, the renderer's undistortion grid, tag visibility.

The camera is :class:`tagtrail.geometry.camera.CameraModel`, the one every source reads: pixel
convention OpenCV's (pixel centres at integer coordinates), camera frame the optical frame (x right,
y down, z forward). Tag frame per SPEC: origin at the tag centre, x right, y up, z out of the face;
detector corner i sits at ``tag_corners(s)[i]`` (:func:`tagtrail.geometry.fusion.tag_corners`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tagtrail.errors import CameraModelError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import tag_corners

# The LIMO's Orbbec Dabai colour camera (NOTES "The LIMO"), 640x480: (fx, fy, cx, cy) px and
# plumb_bob (k1, k2, p1, p2, k3).
LIMO_K = (442.17, 443.88, 323.04, 246.51)
LIMO_D = (0.0449, -0.0770, 0.0025, 0.0012, 0.0)
FRAME_ID = "camera_color_optical_frame"  # header.frame_id of the simulated images and detections
_GRIDS: dict[tuple[object, ...], tuple[F64, tuple[float, float, float, float]]] = {}


def limo_camera() -> CameraModel:
    """The LIMO's colour camera, 640x480, plumb_bob (``.scaled(w, h)`` for other sizes)."""
    fx, fy, cx, cy = LIMO_K
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return CameraModel(640, 480, K, np.array(LIMO_D), "plumb_bob")


def _undistortion(camera: CameraModel) -> tuple[F64, tuple[float, float, float, float]]:
    # Cached by value: CameraModel compares by identity, and callers build their own.
    key = camera.value_key()
    hit = _GRIDS.get(key)
    if hit is not None:
        return hit
    u, v = np.meshgrid(
        np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64)
    )
    px = np.stack([u, v], -1)
    grid = camera.undistort(px)
    back = camera.project(np.concatenate([grid, np.ones_like(u)[..., None]], -1))
    err = float(np.abs(back - px).max())
    if not err < 1e-3:
        raise CameraModelError(
            f"camera distortion {camera.distortion_model} {camera.D.tolist()} is not "
            f"invertible over the image (residual {err:.3g} px)"
        )
    grid.setflags(write=False)
    bounds = (
        float(grid[..., 0].min()),
        float(grid[..., 0].max()),
        float(grid[..., 1].min()),
        float(grid[..., 1].max()),
    )
    if len(_GRIDS) >= 8:
        _GRIDS.clear()
    _GRIDS[key] = grid, bounds
    return grid, bounds


def undistort_grid(camera: CameraModel) -> F64:
    """Normalised ideal coordinates ``(H, W, 2)`` of every distorted pixel centre (read-only)."""
    return _undistortion(camera)[0]


def ideal_bounds(camera: CameraModel) -> tuple[float, float, float, float]:
    """``(xmin, xmax, ymin, ymax)`` of normalised ideal coordinates that land inside the image.

    Points outside this box are rejected before distorting: the polynomial model folds far-off
    points back into the image.
    """
    return _undistortion(camera)[1]


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
    corners_tag = tag_corners(np.asarray(sizes_m, dtype=np.float64))  # (M, 4, 3)
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
