"""Camera poses from a known tag map (Eq. 3.1, 3.8): per-tag estimates and their per-frame fusion.

``camera_estimates`` gives ``world_T_cam^(i) = world_T_tag_i (cam_T_tag_i)^-1`` for each
observation. A frame seeing several mapped tags fuses them by

- ``fuse_mean``: translation mean + chordal rotation mean (vectorised over frames);
- ``fuse_robust``: per-frame robust least squares over the per-tag estimates, by IRLS,
  ``min_{R,t} sum_i rho(|[t - t_i ; w_r Log(R_i^T R)]|^2 / f^2)`` (vectorised over frames);
- ``multi_tag_pnp``: one PnP over every corner of every mapped tag (RANSAC + Levenberg-Marquardt),
  which does not inherit the per-tag IPPE ambiguity (the corners themselves are unambiguous).

``frame_poses`` is the per-frame method choice (``auto`` / ``avg`` / ``lsq`` / ``pnp``) built on
these, batched over frames: the one implementation behind the trajectory stage and the live
``stream localize`` node.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.robust import LossName, irls_weights
from tagtrail.geometry.rotations import grouped_chordal_mean, hat, log_so3
from tagtrail.geometry.se3 import R_from_rotvec, T_from_rotvec_t, inv, make_T, transform_points

Method = Literal["auto", "avg", "lsq", "pnp"]


def camera_estimates(world_T_tag: F64, cam_T_tag: F64) -> F64:
    """Eq. 3.8: ``world_T_cam^(i)`` ``(N, 4, 4)`` from paired ``(N, 4, 4)`` batches."""
    return world_T_tag @ inv(cam_T_tag)


def _group_mean(x: F64, group: I64, n: int, w: F64) -> F64:
    den = np.bincount(group, w, n)
    num = np.stack([np.bincount(group, w * x[:, k], n) for k in range(x.shape[1])], axis=1)
    return num / np.where(den > 0, den, 1.0)[:, None]


def fuse_mean(world_T_cam_i: F64, group: I64, n_groups: int, w: F64 | None = None) -> F64:
    """Per-group mean pose ``(n_groups, 4, 4)``: mean translation, chordal rotation mean."""
    w = np.ones(len(group)) if w is None else w
    R = grouped_chordal_mean(world_T_cam_i[:, :3, :3], group, n_groups, w)
    return make_T(R, _group_mean(world_T_cam_i[:, :3, 3], group, n_groups, w))


def fuse_robust(
    world_T_cam_i: F64,
    group: I64,
    n_groups: int,
    *,
    loss: LossName = "soft_l1",
    f_scale: float = 0.1,
    rot_weight_m: float = 1.0,
    iters: int = 15,
) -> F64:
    """Per-group robust pose ``(n_groups, 4, 4)`` by IRLS from the mean (module docstring).

    Each iteration reweights estimate ``i`` by ``rho'(|e_i|^2 / f^2)`` and takes one Gauss-Newton
    step on the manifold: ``t = sum c t_i / sum c``, ``R <- R Exp(sum c Log(R^T R_i) / sum c)``.
    """
    T = fuse_mean(world_T_cam_i, group, n_groups)
    R_i, t_i = world_T_cam_i[:, :3, :3], world_T_cam_i[:, :3, 3]
    for _ in range(iters):
        R, t = T[:, :3, :3], T[:, :3, 3]
        v = log_so3(np.swapaxes(R[group], -1, -2) @ R_i)  # Log(R^T R_i) = -Log(R_i^T R)
        sq = np.sum((t[group] - t_i) ** 2, axis=1) + rot_weight_m**2 * np.sum(v * v, axis=1)
        c = irls_weights(loss, sq, f_scale)
        step = _group_mean(v, group, n_groups, c)
        T = make_T(R @ R_from_rotvec(step), _group_mean(t_i, group, n_groups, c))
        if np.max(np.abs(step), initial=0.0) < 1e-12:
            break
    return T


def tag_corners(size_m: F64) -> F64:
    """Corners ``(N, 4, 3)`` in the tag frame (m), detector order: (-s/2,-s/2), (s/2,-s/2), ..."""
    h = 0.5 * np.asarray(size_m, dtype=np.float64)[:, None]
    sx = np.array([-1.0, 1.0, 1.0, -1.0])
    sy = np.array([-1.0, -1.0, 1.0, 1.0])
    return np.stack([h * sx, h * sy, np.zeros_like(h * sx)], axis=-1)


def multi_tag_pnp(
    pts_world: F64,
    pts_norm: F64,
    *,
    ransac_thresh: float,
    min_inlier_ratio: float = 0.5,
) -> tuple[F64 | None, int]:
    """``world_T_cam`` ``(4, 4)`` from points ``(M, 3)`` (world, m) seen at ``(M, 2)`` undistorted
    normalised image coordinates; returns ``(pose, n_inliers)``, ``(None, 0)`` on failure.

    ``cv2.solvePnPRansac`` with the AP3P minimal solver (OpenCV's default 5-point EPnP kernel
    degenerates on coplanar points, i.e. tags on one wall), inlier threshold ``ransac_thresh``
    in normalised units (pixels / focal length), OpenCV's fixed RNG seed (deterministic); then
    SQPnP on the inliers (a global minimum) and Levenberg-Marquardt refinement. Fails when fewer
    than ``max(6, min_inlier_ratio * M)`` points are inliers.
    """
    obj = np.ascontiguousarray(pts_world, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(pts_norm, dtype=np.float64).reshape(-1, 1, 2)
    if len(obj) < 6:
        return None, 0
    K = np.eye(3)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj,
        img,
        K,
        None,
        iterationsCount=100,
        reprojectionError=ransac_thresh,
        confidence=0.999,
        flags=cv2.SOLVEPNP_AP3P,
    )
    if not ok or inl is None or len(inl) < max(6, min_inlier_ratio * len(obj)):
        return None, 0
    idx = inl.reshape(-1)
    ok, rvec, tvec = cv2.solvePnP(obj[idx], img[idx], K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None, 0
    rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], K, None, rvec, tvec)
    cam_T_world = T_from_rotvec_t(rvec.reshape(3), tvec.reshape(3))
    cam_T_world = refine_pnp(cam_T_world, obj[idx, 0], img[idx, 0])
    return inv(cam_T_world), len(idx)


def refine_pnp(cam_T_world: F64, pts_world: F64, pts_norm: F64, iters: int = 3) -> F64:
    """Gauss-Newton polish of ``cam_T_world`` ``(4, 4)`` on the normalised reprojection error of
    points ``(M, 3)`` seen at ``(M, 2)`` (left perturbation ``Exp(w) R``, ``Exp(w) t + v``).

    OpenCV's ``solvePnPRefineLM`` stops ~1e-9 m short of the optimum on exact data, whatever its
    criteria; from there two or three Gauss-Newton steps reach machine precision.
    """
    T = cam_T_world
    eye = np.broadcast_to(np.eye(3), (len(pts_world), 3, 3))
    for _ in range(iters):
        p = pts_world @ T[:3, :3].T + T[:3, 3]
        iz = 1.0 / p[:, 2]
        r = (p[:, :2] * iz[:, None] - pts_norm).reshape(-1)
        duv = np.zeros((len(p), 2, 3))  # d(x/z, y/z) / dp
        duv[:, 0, 0] = duv[:, 1, 1] = iz
        duv[:, :, 2] = -p[:, :2] * (iz * iz)[:, None]
        J = (duv @ np.concatenate([-hat(p), eye], axis=2)).reshape(-1, 6)
        step = np.linalg.solve(J.T @ J, -J.T @ r)
        dR = cv2.Rodrigues(step[:3])[0]
        T = make_T(dR @ T[:3, :3], dR @ T[:3, 3] + step[3:])
        if np.abs(step).max() < 1e-14:
            break
    return T


class FramePoses(NamedTuple):
    """What :func:`frame_poses` gives, per frame."""

    world_T_cam: F64
    """``(n_frames, 4, 4)``; NaN for a frame without observations."""
    n_tags: I64
    """``(n_frames,)`` observations (mapped tags) of each frame."""
    by_pnp: NDArray[np.bool_]
    """``(n_frames,)`` frames posed by multi-tag PnP (the others by the fusion)."""
    method: Literal["avg", "lsq", "pnp"]
    """The method applied (``auto`` resolved; ``pnp`` without corners or camera is ``lsq``)."""


def frame_poses(
    world_T_tag: F64,
    cam_T_tag: F64,
    group: I64,
    n_frames: int,
    *,
    corners_px: F64 | None = None,
    size_m: F64 | None = None,
    camera: CameraModel | None = None,
    method: Method,
    loss: LossName,
    f_scale: float,
    rot_weight_m: float,
    ransac_px: float,
) -> FramePoses:
    """``world_T_cam`` of each frame from its tag observations (Eq. 3.8), batched over frames.

    One row per observation: ``world_T_tag (N, 4, 4)`` of the observed (mapped) tag, its
    ``cam_T_tag (N, 4, 4)`` (the best IPPE solution), ``group (N,)`` its frame in
    ``[0, n_frames)`` (rows of a frame contiguous, in the order PnP sees their corners);
    ``corners_px (N, 4, 2)`` distorted pixels, SPEC corner order (NaN rows: no corners) and
    ``size_m (N,)`` (m) for multi-tag PnP with ``camera``.

    ``method``: ``avg`` (:func:`fuse_mean`), ``lsq`` (:func:`fuse_robust` with ``loss``,
    ``f_scale`` (m), ``rot_weight_m``), ``pnp`` (frames with >= 2 tags having corners and a size
    > 0: :func:`multi_tag_pnp` over all their corners, RANSAC threshold ``ransac_px`` (px) over the
    mean focal length; other frames and PnP failures keep ``lsq``), ``auto`` = ``pnp`` when
    corners and a camera are given, else ``lsq``. The fusion runs over all frames at once.
    """
    group = np.asarray(group, dtype=np.int64)
    est = camera_estimates(world_T_tag, cam_T_tag)
    has_pix = corners_px is not None and camera is not None
    if method == "auto":
        method = "pnp" if has_pix else "lsq"
    T = np.full((n_frames, 4, 4), np.nan)
    used = np.zeros(n_frames, dtype=bool)
    if method == "pnp" and corners_px is not None and camera is not None:
        size = np.full(len(group), np.nan) if size_m is None else np.asarray(size_m, np.float64)
        T, used = pnp_frames(T, world_T_tag, group, corners_px, size, camera, ransac_px)
    elif method == "pnp":
        method = "lsq"
    rest = ~used[group]  # the fusion only where PnP did not pose the frame (half the live time)
    if rest.any():
        g, e = group[rest], est[rest]
        if method == "avg":
            fused = fuse_mean(e, g, n_frames)
        else:
            fused = fuse_robust(
                e, g, n_frames, loss=loss, f_scale=f_scale, rot_weight_m=rot_weight_m
            )
        T[~used] = fused[~used]
    n_tags = np.bincount(group, minlength=n_frames)
    T[n_tags == 0] = np.nan
    return FramePoses(T, n_tags, used, method)


def pnp_frames(
    T: F64,
    world_T_tag: F64,
    group: I64,
    corners_px: F64,
    size: F64,
    camera: CameraModel,
    ransac_px: float,
) -> tuple[F64, NDArray[np.bool_]]:
    """``T`` with the frames that have >= 2 usable tags replaced by multi-tag PnP poses, and
    which frames were (:func:`frame_poses`' ``pnp`` without the fusion)."""
    px = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    ok = np.isfinite(px).all(axis=(1, 2)) & np.isfinite(size) & (size > 0)
    n_ok = np.bincount(group[ok], minlength=len(T))
    thresh = ransac_px / (0.5 * (camera.K[0, 0] + camera.K[1, 1]))
    sel = ok & (n_ok[group] >= 2)
    out, used = T.copy(), np.zeros(len(T), dtype=bool)
    if not sel.any():
        return out, used
    norm = camera.undistort(px[sel])
    pts_w = transform_points(world_T_tag[sel][:, None], tag_corners(size[sel]))
    g = group[sel]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    ends = np.r_[starts[1:], len(g)]
    for s, e in zip(starts, ends, strict=True):
        pose, _ = multi_tag_pnp(
            pts_w[s:e].reshape(-1, 3), norm[s:e].reshape(-1, 2), ransac_thresh=thresh
        )
        if pose is not None:
            out[g[s]], used[g[s]] = pose, True
    return out, used
