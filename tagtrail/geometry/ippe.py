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

from typing import Any, NamedTuple

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
    rv, tv = _solutions(corners_px, camera)
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


def ippe_solvable(
    corners_px: NDArray[Any], sizes: NDArray[Any], camera: CameraModel
) -> NDArray[np.bool_]:
    """``(n,)``: the tags :func:`solve_ippe` gives a finite best pose and error — usable
    corners with a finite solution, and a size > 0 (the projection of a finite pose is
    finite but for a corner exactly in the camera's plane) — without building the poses and
    projecting them (~0.3 ms of a live frame whose pose comes from elsewhere)."""
    corners_px = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    rv, tv = _solutions(corners_px, camera)
    size = np.asarray(sizes, dtype=np.float64)
    solved = (np.isfinite(rv).all(-1) & np.isfinite(tv).all(-1)).any(-1)
    out: NDArray[np.bool_] = solved & np.isfinite(size) & (size > 0)
    return out


def _solutions(corners_px: F64, camera: CameraModel) -> tuple[F64, F64]:
    """Both IPPE solutions ``rvec, tvec (n, 2, 3)`` of unit squares (NaN: none)."""
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
    return rv, tv


def ambiguity(reproj_px: NDArray[Any], alt_reproj_px: NDArray[Any]) -> NDArray[np.float64]:
    """``reproj_px / alt_reproj_px`` (n,); 1 (ambiguous) where the alternative is not > 0 — both
    solutions exact, or none — instead of a division by zero."""
    alt = np.asarray(alt_reproj_px, dtype=np.float64)
    out: F64 = np.divide(reproj_px, alt, out=np.ones(len(alt)), where=alt > 0)
    return out


def best_pose(
    pose: F64,
    alt_pose: F64 | None = None,
    reproj_px: F64 | None = None,
    alt_reproj_px: F64 | None = None,
) -> F64:
    """``cam_T_tag`` ``(N, 4, 4)`` from ``pose`` ``(N, 7)`` (x, y, z, qx, qy, qz, qw): of the two
    IPPE solutions, the one with the lower reprojection error; without the alternative (poses
    given by a source), the only pose."""
    vals = np.asarray(pose, dtype=np.float64)
    if alt_pose is not None and reproj_px is not None and alt_reproj_px is not None:
        alt = np.asarray(alt_pose, dtype=np.float64)
        use_alt = (np.asarray(alt_reproj_px) < np.asarray(reproj_px)) & np.isfinite(alt).all(1)
        vals = np.where(use_alt[:, None], alt, vals)
    return T_from_xyz_quat(vals[:, :3], vals[:, 3:])


class Branches(NamedTuple):
    """:func:`consistent_branches`' answer per co-observation row: the chosen solution
    combination (``2 * branch_i + branch_j``) and its ``i_T_j``, the same for the runner-up
    hypothesis of the row's pair (``-1`` and NaN where the row has no candidate near it), and the
    pair's support ratio runner-up / winner (0: no runner-up)."""

    choice: NDArray[np.int64]
    T_ij: F64
    alt_choice: NDArray[np.int64]
    alt_T_ij: F64
    ratio: F64


def consistent_branches(
    group: NDArray[np.int64],
    T_i: F64,
    T_j: F64,
    w_i: F64,
    w_j: F64,
    *,
    max_deg: float = 10.0,
    max_rel: float = 0.1,
    max_abs_m: float = 0.05,
    seeds: int = 24,
) -> Branches:
    """The IPPE solutions of co-observed tags that agree across frames.

    A tag pair's relative pose ``i_T_j`` is fixed, but each co-observation offers four: the two
    solutions of each tag. The correct one is the same in every frame; a wrong one (a mirrored
    tag) moves with the viewpoint, so per pair the candidate with the most support wins:
    support = the sum over frames of the best prior weight among that frame's candidates within
    ``max_deg`` and ``max_rel`` x distance + ``max_abs_m`` of it. A solution's prior weight is 1
    for the lower-reprojection one and its ``ambiguity`` for the other (a clear second
    solution counts for little; a parked camera's frames all agree on the best one). Each row
    then takes the candidate nearest the winner; one with none within the bounds keeps both
    best solutions (an outlier either way: the robust loss of the pose graph deals with it).

    When the view hardly changes while both tags are in sight, a mirrored solution agrees with
    itself too: the best-supported candidate outside the winner's bounds is the runner-up, and
    the support ratio says how close the call was (the joint solve decides such pairs on the
    frames' continuity, ``stages.optimize``).

    ``group`` (m,): the pair of each row; ``T_i``, ``T_j`` (m, 2, 4, 4): ``cam_T_tag`` of both
    solutions; ``w_i``, ``w_j`` (m, 2): their prior weights (0 = no such solution). Seeds: up
    to ``seeds`` frames per pair, evenly spaced, propose the candidates.
    """
    m = len(group)
    inv_i = np.linalg.inv(np.where(np.isfinite(T_i), T_i, np.eye(4)))
    Tj = np.where(np.isfinite(T_j), T_j, np.eye(4))
    cand = np.einsum("mbij,mcjk->mbcik", inv_i, Tj).reshape(m, 4, 4, 4)  # combo = 2*bi + bj
    w = (w_i[:, :, None] * w_j[:, None, :]).reshape(m, 4)
    out = Branches(
        np.full(m, -1, np.int64),
        np.full((m, 4, 4), np.nan),
        np.full(m, -1, np.int64),
        np.full((m, 4, 4), np.nan),
        np.zeros(m),
    )
    cos_max = np.cos(np.radians(max_deg))
    order = np.argsort(group, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(group[order]) != 0])
    for rows in np.split(order, starts[1:]):
        C = cand[rows]  # (n, 4, 4, 4)
        R = C[:, :, :3, :3].reshape(-1, 9)
        t = C[:, :, :3, 3].reshape(-1, 3)
        wr = w[rows].reshape(-1)
        valid = wr > 0
        pick = np.unique(np.linspace(0, len(rows) - 1, min(seeds, len(rows))).round().astype(int))
        seed = (pick[:, None] * 4 + np.arange(4)).reshape(-1)
        seed = seed[valid[seed]]

        def near(
            s: NDArray[np.int64], R: F64 = R, t: F64 = t, valid: NDArray[np.bool_] = valid
        ) -> tuple[F64, NDArray[np.bool_]]:
            cos = (R[s] @ R.T - 1.0) / 2.0  # cos of the angle between rotations
            dist = np.linalg.norm(t[s][:, None, :] - t[None, :, :], axis=2)
            scale = max_rel * np.linalg.norm(t[s], axis=1)[:, None] + max_abs_m
            return cos, (cos >= cos_max) & (dist <= scale) & valid[None, :]

        _, ok = near(seed)
        support = (
            np.where(ok, wr[None, :], 0.0).reshape(len(seed), len(rows), 4).max(axis=2).sum(axis=1)
        )
        best = int(np.argmax(support))
        rival = ~ok[best, seed]  # seeds outside the winner's bounds
        for which, s in (("win", best), ("alt", int(np.argmax(np.where(rival, support, -1.0))))):
            if which == "alt":
                if not rival.any():
                    break
                out.ratio[rows] = support[s] / support[best]
            c, k_ok = near(seed[[s]])
            score = np.where(k_ok[0], c[0], -np.inf).reshape(len(rows), 4)
            k = np.argmax(score, axis=1)
            hit = np.isfinite(score[np.arange(len(rows)), k])
            if which == "win":  # rows agreeing with no solution keep the best ones
                k[~hit], hit[:] = 0, True
            ch, T = (out.choice, out.T_ij) if which == "win" else (out.alt_choice, out.alt_T_ij)
            ch[rows[hit]] = k[hit]
            T[rows[hit]] = C[hit, k[hit]]
    return out


def map_branches(
    frame: NDArray[np.int64], world_R_tag: F64, cam_R_tag: F64, *, cap_deg: float = 15.0
) -> NDArray[np.int64]:
    """Per observation, the IPPE solution (0 or 1) a tag map agrees with, frame by frame.

    A mirrored solution of a small or distant tag can have the lower reprojection error and
    still be tens of degrees off; a tag pair seen together in a frame or two cannot outvote it
    (:func:`consistent_branches`), but the map, solved robustly from all the other edges, can.
    Every solution of every tag in a frame proposes the camera's orientation
    ``world_R_cam = world_R_tag cam_R_tag^T``; the proposal the frame's other tags agree with
    best (the sum over them of the angle to their nearer solution, each capped at ``cap_deg``)
    wins, and each observation takes its solution nearer that camera's prediction. Ties go to
    the lower-reprojection (first) solutions. Frames of one tag say nothing and keep 0.

    ``frame`` (n,): frame of each observation; ``world_R_tag`` (n, 3, 3): its tag's orientation
    in the map; ``cam_R_tag`` (n, 2, 3, 3): both solutions (NaN: none).
    """
    n = len(frame)
    choice = np.zeros(n, np.int64)
    if n == 0:
        return choice
    order = np.argsort(frame, kind="stable")
    f = np.asarray(frame)[order]
    starts = np.flatnonzero(np.r_[True, f[1:] != f[:-1]])
    size = np.diff(np.r_[starts, n])
    fid = np.repeat(np.arange(len(starts)), size)  # frame of each sorted row
    Rw, Rc = world_R_tag[order], cam_R_tag[order]
    # every ordered pair (k proposes, m checks) of rows sharing a frame, k == m included
    sq = size * size
    local = np.arange(sq.sum()) - np.repeat(np.cumsum(sq) - sq, sq)
    z = np.repeat(size, sq)
    k = np.repeat(starts, sq) + local // z
    m = np.repeat(starts, sq) + local % z
    pred = Rc[k] @ (np.swapaxes(Rw[k], -1, -2) @ Rw[m])[:, None]  # m's cam_R_tag from k's (p, a)
    # the angle from the chord |A - B|_F = 2 sqrt(2) sin(angle / 2): accurate near 0, where the
    # trace's arccos is off by ~1e-6 deg (more than the ties' margin below: a frame of one tag
    # took its mirror 1 time in 20)
    d = pred[:, :, None] - Rc[m][:, None, :]
    half = np.sqrt(np.einsum("pabij,pabij->pab", d, d)) / (2.0 * np.sqrt(2.0))
    err = np.degrees(2.0 * np.arcsin(np.clip(np.nan_to_num(half, nan=1.0), 0.0, 1.0)))
    err[:, :, 1] += 1e-6  # ties: the first solution
    score = np.zeros((n, 2))
    np.add.at(score, k, np.minimum(err.min(axis=2), cap_deg))
    score[:, 1] += 1e-6
    score[~np.isfinite(Rc[:, :, 0, 0])] = np.inf
    win = np.lexsort((score.min(axis=1), fid))[starts]  # per frame, the best proposer
    win_a = np.argmin(score[win], axis=1)
    sel = k == win[fid[m]]
    out = np.zeros(n, np.int64)
    out[m[sel]] = np.argmin(err[sel, win_a[fid[m[sel]]]], axis=1)
    choice[order] = out
    return choice
