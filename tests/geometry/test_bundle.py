"""The joint solve (geometry.joint): exact recovery, robustness, the motion prior's Jacobian and
its effect, the IPPE choice by continuity, and standard deviations that match the scatter."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.ippe import solve_ippe
from tagtrail.geometry.joint import (
    SHIFT_SIGMA_BOUND,
    CornerObservations,
    Corners,
    MotionPrior,
    frame_evidence,
    initial_cameras,
    link_tags,
    solve_joint,
)
from tagtrail.geometry.joint.problem import left_update, same_frame_pairs
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import R_from_rotvec, inv, make_T
from tests.geometry.problems import FOCAL_PX, corner_problem, perturbed


def solve(
    ob: CornerObservations,
    W: np.ndarray,
    C: np.ndarray,
    anchor: int,  # type: ignore[no-untyped-def]
    prior: MotionPrior | None = None,
    covariance: bool = False,
    **kw: object,
):
    """The joint solve of the map (all but the anchor free) from ``W``, ``C``; ``kw``: the
    :class:`Corners` settings."""
    free = np.arange(len(W)) != anchor
    return solve_joint(
        W[:, :3, :3],
        W[:, :3, 3],
        C[:, :3, :3],
        C[:, :3, 3],
        ob,
        free,
        Corners(FOCAL_PX, **kw),
        [] if prior is None else [prior],  # type: ignore[arg-type]
        covariance=covariance,
    )


def test_same_frame_pairs_are_all_ordered_pairs_within_each_frame() -> None:
    frame = np.array([2, 0, 2, 1, 2, 0])
    a, b = same_frame_pairs(frame)
    got = sorted(zip(a.tolist(), b.tolist(), strict=True))
    want = sorted((i, j) for i in range(6) for j in range(6) if frame[i] == frame[j])
    assert got == want


def test_motion_prior_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(0)
    n = 7
    R, t = R_from_rotvec(rng.normal(size=(n, 3)) * 0.4), rng.normal(size=(n, 3))
    t_s = np.cumsum(rng.uniform(0.02, 0.06, n))
    t_s[4:] += 2.0  # a gap: frames 3 and 4 are not linked
    pr = MotionPrior(t_s, 0.5, 0.7, 1.0)
    assert pr.k.tolist() == [1, 2, 5]
    m, J = pr.residuals(R, t)
    eps = 1e-7
    for f in range(n):
        for c in range(6):
            d = np.zeros((n, 6))
            d[f, c] = eps
            num = (pr.residuals(*left_update(R, t, d))[0] - m) / eps
            ana = sum(
                np.where(((pr.k - 1 + i) == f)[:, None], J[:, i, :, c], 0.0) for i in range(3)
            )
            np.testing.assert_allclose(num, ana, atol=2e-5)


def test_motion_prior_is_zero_on_constant_velocity_motion() -> None:
    t_s = np.array([0.0, 0.1, 0.3, 0.4])  # non-uniform steps
    w, v = np.array([0.1, -0.3, 0.2]), np.array([0.5, 0.0, -0.2])
    world_T_cam = make_T(R_from_rotvec(t_s[:, None] * w), t_s[:, None] * v)
    cam_T_world = inv(world_T_cam)
    m, _ = MotionPrior(t_s, 1.0, 1.0, 1.0).residuals(cam_T_world[:, :3, :3], cam_T_world[:, :3, 3])
    # constant body rate and constant world velocity of the centre: no acceleration
    assert np.abs(m[:, :3]).max() < 1e-12 and np.abs(m[:, 3:]).max() < 1e-9


def test_camera_frame_motion_prior_jacobian_matches_central_differences() -> None:
    rng = np.random.default_rng(3)
    n = 7
    R, t = R_from_rotvec(rng.normal(size=(n, 3)) * 0.4), rng.normal(size=(n, 3))
    t_s = np.cumsum(rng.uniform(0.02, 0.06, n))
    pr = MotionPrior(t_s, 0.5, 0.7, 1.0, frame="camera")
    _, J = pr.residuals(R, t)
    eps = 1e-6
    for f in range(n):
        for c in range(6):
            d = np.zeros((n, 6))
            d[f, c] = eps
            hi, lo = pr.residuals(*left_update(R, t, d))[0], pr.residuals(*left_update(R, t, -d))[0]
            num = (hi - lo) / (2 * eps)
            ana = sum(
                np.where(((pr.k - 1 + i) == f)[:, None], J[:, i, :, c], 0.0) for i in range(3)
            )
            np.testing.assert_allclose(num, ana, rtol=1e-6, atol=1e-6)


def test_camera_frame_motion_prior_is_zero_on_a_steady_arc() -> None:
    """A robot driving a circle at constant speed and turn rate: no acceleration in the
    camera's frame; the world-frame form sees its centripetal v w (the live lag on curves)."""
    t_s = np.arange(6) / 30.0
    yaw = 1.2 * t_s  # rad, 1.2 rad/s on a circle of 0.5 m: 0.6 m/s
    xy = 0.5 * np.stack([np.sin(yaw), 1.0 - np.cos(yaw)], axis=1)
    Rz = R_from_rotvec(np.stack([np.zeros(6), np.zeros(6), yaw], axis=1))
    world_T_cam = make_T(Rz @ R_from_rotvec([np.pi / 2, 0.0, 0.0]), np.c_[xy, np.full(6, 0.2)])
    cam_T_world = inv(world_T_cam)
    R, t = cam_T_world[:, :3, :3], cam_T_world[:, :3, 3]
    body = MotionPrior(t_s, 1.0, 1.0, 1.0, frame="camera").residuals(R, t)[0]
    world = MotionPrior(t_s, 1.0, 1.0, 1.0).residuals(R, t)[0]
    assert np.abs(body).max() < 1e-9
    whitened = np.sqrt(0.75 * 2 / 30.0) * 0.6 * 1.2  # the centripetal 0.72 m/s^2, whitened
    assert np.abs(np.linalg.norm(world[:, 3:], axis=1) - whitened).max() < 1e-3 * whitened


def test_exact_poses_recovered_from_a_perturbed_start() -> None:
    ob, W, C, anchor, _ = corner_problem()
    W0 = perturbed(W, 1, 0.02, 0.03, keep=anchor)
    C0 = perturbed(C, 2, 0.02, 0.03)
    res = solve(ob, W0, C0, anchor)
    assert res.converged and res.res_px.max() < 1e-6
    assert np.abs(res.t_tag - W[:, :3, 3]).max() < 1e-8
    assert np.rad2deg(geodesic_angle(res.R_tag, W[:, :3, :3])).max() < 1e-6
    assert np.abs(res.t_cam - C[:, :3, 3]).max() < 1e-8
    assert np.array_equal(res.R_tag[anchor], np.eye(3)) and not res.t_tag[anchor].any()


def test_fixed_map_solves_the_cameras_only() -> None:
    ob, W, C, _, t_s = corner_problem()
    C0 = perturbed(C, 2, 0.02, 0.03)
    res = solve_joint(
        W[:, :3, :3],
        W[:, :3, 3],
        C0[:, :3, :3],
        C0[:, :3, 3],
        ob,
        np.zeros(len(W), bool),
        Corners(FOCAL_PX),
        [MotionPrior(t_s, 1.0, 1.0, 1.0)],
    )
    assert np.array_equal(res.t_tag, W[:, :3, 3])
    # the ring's constant-rate path is nearly constant velocity: the prior barely moves it
    assert np.abs(res.t_cam - C[:, :3, 3]).max() < 1e-3


def test_noise_and_an_outlier_detection() -> None:
    """0.1 px corner noise: a cm-level map (its error is mostly the anchor tag's own orientation,
    levered over the 6 m ring); one detection 15 px off moves the robust solution less than half
    as far as the plain least squares."""
    ob, W, C, anchor, _ = corner_problem(noise_px=0.1, seed=3)
    uv = ob.uv.copy()
    uv[7] += 15.0 / FOCAL_PX
    ob_bad = CornerObservations(ob.frame, ob.tag, ob.pts_tag, uv)
    W0 = perturbed(W, 4, 0.01, 0.02, keep=anchor)
    t = {}
    for name, obs, loss in (
        ("clean", ob, "huber"),
        ("huber", ob_bad, "huber"),
        ("linear", ob_bad, "linear"),
    ):
        res = solve(obs, W0, C, anchor, loss=loss, f_scale_px=1.0)
        assert res.converged
        t[name] = res.t_tag
    assert np.linalg.norm(t["clean"] - W[:, :3, 3], axis=1).max() < 0.015
    shift = {k: np.linalg.norm(t[k] - t["clean"], axis=1).max() for k in ("huber", "linear")}
    assert shift["huber"] < 0.5 * shift["linear"]


@pytest.mark.slow  # 24 noise draws, each a full bundle adjustment (~7 s): make test-all
def test_standard_deviations_match_the_scatter_over_noise_draws() -> None:
    """The reported per-tag and per-frame standard deviations agree with the spread of the
    solutions over 24 independent 0.5 px noise draws (within the sampling error of 24 draws),
    and a tag whose observations are thinned out to a few frames is reported less certain."""
    sigma = 0.5
    errs_t, errs_c, std_t, std_c = [], [], [], []
    for seed in range(24):
        ob, W, C, anchor, t_s = corner_problem(noise_px=sigma, seed=10 + seed, n_frames=120)
        res = solve(
            ob,
            W,
            C,
            anchor,
            sigma_px=sigma,
            loss="linear",
            covariance=True,
            prior=MotionPrior(t_s, 1.0, 1.0, 1.0),
        )
        errs_t.append(res.t_tag - W[:, :3, 3])
        centre = -np.einsum("fji,fj->fi", res.R_cam, res.t_cam)
        centre_true = -np.einsum("fji,fj->fi", C[:, :3, :3], C[:, :3, 3])
        errs_c.append(centre - centre_true)
        assert res.tag_std is not None and res.cam_std is not None
        std_t.append(res.tag_std[:, 0])
        std_c.append(res.cam_std[:, 0])
    et, ec = np.array(errs_t), np.array(errs_c)
    emp_t = np.sqrt(np.mean(np.sum(et**2, -1), 0) / 3)[1:]  # RMS per axis, free tags
    emp_c = np.sqrt(np.mean(np.sum(ec**2, -1), 0) / 3)
    ratio_t = emp_t / np.mean(std_t, 0)[1:]
    ratio_c = emp_c / np.mean(std_c, 0)
    assert 0.75 < np.median(ratio_t) < 1.33
    assert 0.75 < np.median(ratio_c) < 1.33

    # fewer frames: tag 6 kept in one frame of 6 is less certain in orientation (its position
    # is dominated by the anchor's lever); farther from the anchor (round the ring): less certain
    ob, W, C, anchor, t_s = corner_problem(noise_px=sigma, seed=1, n_frames=120)
    sparse_tag = 6
    keep = ~((ob.tag == sparse_tag) & (ob.frame % 6 != 0))
    ob_thin = CornerObservations(ob.frame[keep], ob.tag[keep], ob.pts_tag[keep], ob.uv[keep])
    full = solve(ob, W, C, anchor, sigma_px=sigma, covariance=True)
    thin = solve(ob_thin, W, C, anchor, sigma_px=sigma, covariance=True)
    assert full.tag_std is not None and thin.tag_std is not None
    assert thin.tag_std[sparse_tag, 1] > 1.3 * full.tag_std[sparse_tag, 1]
    others = np.arange(len(W)) != sparse_tag
    assert np.allclose(thin.tag_std[others, 1], full.tag_std[others, 1], rtol=0.1)
    assert np.all(np.diff(full.tag_std[:7, 0]) > 0)  # tags 0..6: ever farther from the anchor


def test_single_tag_stretch_is_held_by_its_neighbours() -> None:
    """Two tags seen together at both ends of a pass, one alone for the 80 frames between (16 cm
    tags, 1.8 m away, nearly face-on, 0.3 px corner noise): per-frame IPPE puts single-tag frames
    up to metres off (the flip), the joint solve without the prior still ~14 cm on average; with
    the motion prior the stretch stays within the sparse-scene bounds (mean <= 2.5 cm, max <=
    10 cm) on every noise draw."""
    cam = CameraModel(
        640, 480, np.array([[FOCAL_PX, 0, 320], [0, FOCAL_PX, 240], [0, 0, 1]]), [], "none"
    )
    n = 120
    t_s = np.arange(n) / 30.0
    W = make_T(np.repeat(np.eye(3)[None], 2, 0), np.array([[0, 0, 0], [0.9, 0.1, 0.0]]))
    yaw = np.radians(6.0) * np.sin(2 * t_s)
    R_wc = R_from_rotvec(np.stack([np.zeros(n), np.pi + yaw, np.zeros(n)], 1))
    centre = np.stack([np.linspace(-0.05, 0.95, n), np.zeros(n), np.full(n, 1.8)], 1)
    world_T_cam = make_T(R_wc, centre)
    both = (np.arange(n) < 20) | (np.arange(n) >= 100)
    frame = np.r_[np.arange(n), np.flatnonzero(both)]
    tag = np.r_[np.zeros(n, np.int64), np.ones(both.sum(), np.int64)]
    cam_T_tag = inv(world_T_cam[frame]) @ W[tag]
    pts = tag_corners(np.full(len(frame), 0.16))
    p = np.einsum("oij,okj->oki", cam_T_tag[:, :3, :3], pts) + cam_T_tag[:, None, :3, 3]
    prior = MotionPrior(t_s, 0.3, np.radians(30.0), 0.5)
    for seed in range(3):
        uv = p[..., :2] / p[..., 2:] + np.random.default_rng(seed).normal(
            scale=0.3 / FOCAL_PX, size=p[..., :2].shape
        )
        sol, _ = solve_ippe(
            uv * FOCAL_PX + np.array([320.0, 240.0]), np.full(len(frame), 0.16), cam
        )
        ob = CornerObservations(frame, tag, pts, uv)
        per_frame = np.linalg.norm((W[tag] @ inv(sol[:, 0]))[:, :3, 3] - centre[frame], axis=1)
        assert per_frame.max() > 1.0
        start, _, _ = initial_cameras(W[tag], sol, ob, t_s, px_per_unit=FOCAL_PX, max_gap_s=0.5)
        err = {}
        for name, pr in (("none", None), ("prior", prior)):
            res = solve_joint(
                W[:, :3, :3],
                W[:, :3, 3],
                start[:, :3, :3],
                start[:, :3, 3],
                ob,
                np.zeros(2, bool),
                Corners(FOCAL_PX, 0.3),
                [] if pr is None else [pr],
            )
            c = -np.einsum("fji,fj->fi", res.R_cam, res.t_cam)
            err[name] = np.linalg.norm(c - centre, axis=1)
        assert err["prior"].mean() <= 0.025 and err["prior"].max() <= 0.10
        assert err["none"].mean() > 3 * err["prior"].mean()


def test_tags_never_seen_together_are_linked_through_the_trajectory() -> None:
    """Tag 0 alone for 2 s, then tag 1 alone for 2 s (never in one frame: no pose-graph edge):
    ``link_tags`` places tag 1 from the camera path extrapolated across the hand-over, and the
    joint solve with the motion prior puts it within 3 cm of the truth (per-frame IPPE alone
    cannot place it at all). A hand-over after a gap longer than ``max_gap_s`` links nothing."""
    cam = CameraModel(
        640, 480, np.array([[FOCAL_PX, 0, 320], [0, FOCAL_PX, 240], [0, 0, 1]]), [], "none"
    )
    n = 120
    t_s = np.arange(n) / 30.0
    W = make_T(
        R_from_rotvec(np.array([[0, 0, 0], [0, 0.3, 0]])), np.array([[0, 0, 0], [1.2, 0.1, 0.1]])
    )
    R_wc = R_from_rotvec(np.stack([np.zeros(n), np.full(n, np.pi), np.zeros(n)], 1))
    centre = np.stack([np.linspace(-0.3, 1.5, n), np.zeros(n), np.full(n, 1.5)], 1)
    world_T_cam = make_T(R_wc, centre)
    tag = (np.arange(n) >= 60).astype(np.int64)
    cam_T_tag = inv(world_T_cam) @ W[tag]
    pts = tag_corners(np.full(n, 0.16))
    p = np.einsum("oij,okj->oki", cam_T_tag[:, :3, :3], pts) + cam_T_tag[:, None, :3, 3]
    uv = p[..., :2] / p[..., 2:] + np.random.default_rng(2).normal(
        scale=0.2 / FOCAL_PX, size=p[..., :2].shape
    )
    sol, _ = solve_ippe(uv * FOCAL_PX + np.array([320.0, 240.0]), np.full(n, 0.16), cam)
    ob = CornerObservations(np.arange(n), tag, pts, uv)
    start = W.copy()
    start[1] = np.nan
    for gap, linked in ((0.0, True), (1.0, False)):
        ts = t_s + np.where(np.arange(n) >= 60, gap, 0.0)
        Wl, known = link_tags(
            start, np.array([True, False]), sol, ob, ts, px_per_unit=FOCAL_PX, max_gap_s=0.5
        )
        assert bool(known[1]) is linked
    Wl, known = link_tags(
        start, np.array([True, False]), sol, ob, t_s, px_per_unit=FOCAL_PX, max_gap_s=0.5
    )
    C0, _, _ = initial_cameras(Wl[tag], sol, ob, t_s, px_per_unit=FOCAL_PX, max_gap_s=0.5)
    res = solve_joint(
        Wl[:, :3, :3],
        Wl[:, :3, 3],
        C0[:, :3, :3],
        C0[:, :3, 3],
        ob,
        np.array([False, True]),
        Corners(FOCAL_PX, 0.2),
        [MotionPrior(t_s, 0.1, np.radians(30.0), 0.5)],
    )
    assert np.linalg.norm(res.t_tag[1] - W[1, :3, 3]) < 0.03


def test_corner_noise_is_estimated_from_the_residuals() -> None:
    """Started from a corner noise 4x too large, ``estimate_noise`` finds the 0.5 px it is."""
    ob, W, C, anchor, t_s = corner_problem(noise_px=0.5, seed=7, n_frames=120)
    res = solve(
        ob, W, C, anchor, sigma_px=2.0, estimate_noise=True, prior=MotionPrior(t_s, 1.0, 1.0, 1.0)
    )
    given = solve(ob, W, C, anchor, sigma_px=2.0, prior=MotionPrior(t_s, 1.0, 1.0, 1.0))
    assert given.sigma_px == 2.0 and abs(res.sigma_px - 0.5) < 0.05


def test_frame_evidence_measures_a_move_in_the_frames_own_standard_deviations() -> None:
    """Frames of a solution displaced from their own corners' optimum by a known number of their
    standard deviations (along each frame's own covariance) read back as that many; the others
    as nothing; the displaced frames' corner RMS grows, the per-frame solution's does not."""
    ob, W, C, _, _ = corner_problem(noise_px=0.3, n_frames=60)
    fixed = np.zeros(len(W), bool)
    alone = solve_joint(
        W[:, :3, :3],
        W[:, :3, 3],
        C[:, :3, :3],
        C[:, :3, 3],
        ob,
        fixed,
        Corners(FOCAL_PX, 0.3),
        covariance=True,
    )
    assert alone.cam_cov is not None
    moved, k_sigma = np.arange(0, 60, 7), 8.0
    rng = np.random.default_rng(3)
    d = np.zeros((60, 6))
    for f in moved:  # a random direction scaled to k_sigma under that frame's covariance
        u = rng.normal(size=6)
        L = np.linalg.cholesky(alone.cam_cov[f])
        d[f] = k_sigma * (L @ u) / np.linalg.norm(u)
    Rc, tc = left_update(alone.R_cam, alone.t_cam, d)
    res = dataclasses.replace(
        alone,
        R_cam=Rc,
        t_cam=tc,
        res_px=solve_joint(
            W[:, :3, :3], W[:, :3, 3], Rc, tc, ob, fixed, Corners(FOCAL_PX, 0.3), max_iter=0
        ).res_px,
    )
    ev = frame_evidence(res, ob, Corners(FOCAL_PX, 0.3, "huber", 1.0))
    rest = np.setdiff1d(np.arange(60), moved)
    np.testing.assert_allclose(ev.shift_sigma[moved], k_sigma, rtol=0.1)
    assert (ev.shift_sigma[moved] > SHIFT_SIGMA_BOUND).all()
    assert ev.shift_sigma[rest].max() < 0.05 and ev.shift_m[rest].max() < 1e-5
    assert (ev.reproj_px[moved] > ev.alone_reproj_px[moved]).all()
    np.testing.assert_allclose(
        ev.alone_reproj_px,
        np.sqrt(np.bincount(ob.frame, alone.res_px**2) / np.bincount(ob.frame)),
        rtol=1e-3,
    )
