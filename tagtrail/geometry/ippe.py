"""Both IPPE poses of square tags (Collins & Bartoli 2014, OpenCV's ``SOLVEPNP_IPPE_SQUARE``).

Tag frame (SPEC): origin at the tag centre, x right, y up, z out of the face; the detector's
corners 0..3 sit at (−s/2, −s/2), (s/2, −s/2), (s/2, s/2), (−s/2, s/2). ``SOLVEPNP_IPPE_SQUARE``
ignores the object points' values and assumes its canonical square (−s/2, s/2), (s/2, s/2),
(s/2, −s/2), (−s/2, −s/2) — the SPEC corners 3, 2, 1, 0 — so the corners are passed in that order
and the pose comes out in the SPEC frame directly. Corners are undistorted to normalized
coordinates, solved for a unit square with an identity camera matrix and the translation scaled
by the tag's size (IPPE is scale-covariant).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.se3 import R_from_rotvec, T_from_xyz_quat, make_T, transform_points

UNIT_CORNERS_TAG = tag_corners(np.ones(1))[0]  # SPEC corner order, unit square
_IPPE_ORDER = [3, 2, 1, 0]  # SPEC corners in IPPE_SQUARE's canonical order
# Undistorted rays beyond this tangent (89.994°) point nowhere a tag can be seen; such corners
# (garbage in a detection message) would only overflow the reprojection.
_MAX_NORM = 1e4


def solve_ippe(
    corners_px: NDArray[Any], sizes: NDArray[Any], camera: CameraModel
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Both IPPE poses of square tags.

    ``corners_px``: (n, 4, 2) distorted pixels, SPEC corner order; ``sizes``: (n,) m.
    Returns ``cam_T_tag`` (n, 2, 4, 4) and ``reproj_px`` (n, 2), best solution first; a tag whose
    solve fails (degenerate, non-finite or far out-of-view corners) gets NaN.
    """
    corners_px = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    n = len(corners_px)
    norm = np.ascontiguousarray(camera.undistort(corners_px)[:, _IPPE_ORDER])
    obj = np.ascontiguousarray(UNIT_CORNERS_TAG[_IPPE_ORDER])
    eye = np.eye(3)
    rv = np.full((n, 2, 3), np.nan)
    tv = np.full((n, 2, 3), np.nan)
    usable = np.abs(norm).max(axis=(1, 2), initial=0.0) < _MAX_NORM  # False for NaN too
    for i in np.flatnonzero(usable):
        try:
            k, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                obj, norm[i], eye, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
        except cv2.error:
            continue
        for j in range(min(int(k), 2)):
            rv[i, j] = rvecs[j].reshape(3)
            tv[i, j] = tvecs[j].reshape(3)
    ok = np.isfinite(rv).all(axis=-1)
    R = np.full((n, 2, 3, 3), np.nan)
    R[ok] = R_from_rotvec(rv[ok])
    t = tv * np.asarray(sizes, dtype=np.float64)[:, None, None]
    T = make_T(R, t)
    pts_tag = UNIT_CORNERS_TAG * np.asarray(sizes, dtype=np.float64)[:, None, None]  # (n, 4, 3)
    pts_cam = transform_points(T[:, :, None], pts_tag[:, None])  # (n, 2, 4, 3)
    err = np.full((n, 2), np.nan)
    if ok.any():
        proj = camera.project(pts_cam[ok])  # (k, 4, 2)
        d2 = np.sum((proj - np.broadcast_to(corners_px[:, None], (n, 2, 4, 2))[ok]) ** 2, -1)
        err[ok] = np.sqrt(d2.mean(-1))
    swap = np.nan_to_num(err[:, 1], nan=np.inf) < np.nan_to_num(err[:, 0], nan=np.inf)
    T[swap] = T[swap][:, ::-1]
    err[swap] = err[swap][:, ::-1]
    return T, err


def ambiguity(reproj_px: NDArray[Any], alt_reproj_px: NDArray[Any]) -> NDArray[np.float64]:
    """``reproj_px / alt_reproj_px`` (n,); 1 (ambiguous) where the alternative is not > 0 — both
    solutions exact, or none — instead of a division by zero."""
    alt = np.asarray(alt_reproj_px, dtype=np.float64)
    out: F64 = np.divide(reproj_px, alt, out=np.ones(len(alt)), where=alt > 0)
    return out


def best_pose(pose: F64, alt_pose: F64 | None = None, reproj_px: F64 | None = None,
              alt_reproj_px: F64 | None = None) -> F64:
    """``cam_T_tag`` ``(N, 4, 4)`` from ``pose`` ``(N, 7)`` (x, y, z, qx, qy, qz, qw): of the two
    IPPE solutions, the one with the lower reprojection error; without the alternative (poses
    given by a source), the only pose."""
    vals = np.asarray(pose, dtype=np.float64)
    if alt_pose is not None and reproj_px is not None and alt_reproj_px is not None:
        alt = np.asarray(alt_pose, dtype=np.float64)
        use_alt = (np.asarray(alt_reproj_px) < np.asarray(reproj_px)) & np.isfinite(alt).all(1)
        vals = np.where(use_alt[:, None], alt, vals)
    return T_from_xyz_quat(vals[:, :3], vals[:, 3:])
