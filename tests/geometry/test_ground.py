"""The ground-plane prior (geometry.joint.ground): its Jacobians, the plane fit, the planarity
test that decides ``auto``, and what it buys the joint solve on a robot's planar path."""

from __future__ import annotations

import numpy as np

from tagtrail.geometry.joint import Corners, MotionPrior, solve_grounded, solve_joint
from tagtrail.geometry.joint.ground import (
    PLANAR_BOUND,
    GroundLevel,
    GroundPrior,
    Plane,
    fit_plane,
    level_terms,
    planarity,
    plane_terms,
)
from tagtrail.geometry.joint.problem import centres, left_update
from tagtrail.geometry.registration import umeyama
from tagtrail.geometry.robust import rho
from tagtrail.geometry.se3 import R_from_rotvec, make_T
from tests.geometry.problems import FOCAL_PX, corner_problem, perturbed, planar_cameras

PRIOR = GroundPrior(0.01, np.radians(1.0))


def test_plane_terms_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(1)
    C = perturbed(planar_cameras(6), 2, 0.05, 0.05)
    R, t = C[:, :3, :3], C[:, :3, 3]
    n = rng.normal(size=3)
    plane = Plane(n / np.linalg.norm(n), 0.3, rng.normal(size=3))
    p, Jc, Jg = plane_terms(R, t, plane, PRIOR)
    eps = 1e-7
    for f in range(len(R)):
        for c in range(6):
            d = np.zeros((len(R), 6))
            d[f, c] = eps
            num = (plane_terms(*left_update(R, t, d), plane, PRIOR)[0] - p) / eps
            np.testing.assert_allclose(num[f], Jc[f, :, c], atol=1e-4 * np.abs(Jc).max())
            assert np.abs(np.delete(num, f, axis=0)).max() == 0.0  # one frame's terms only
    for c in range(6):
        step = np.zeros(6)
        step[c] = eps
        num = (plane_terms(R, t, plane.update(step), PRIOR)[0] - p) / eps
        np.testing.assert_allclose(num, Jg[:, :, c], atol=1e-4 * np.abs(Jg).max())


def test_level_terms_jacobians_match_finite_differences() -> None:
    """The level term's whitened height change between consecutive frames: its Jacobians on
    both cameras and on the plane's normal; a gap beyond ``max_gap_s`` has no term."""
    rng = np.random.default_rng(2)
    C = perturbed(planar_cameras(6), 2, 0.05, 0.05)
    R, t = C[:, :3, :3], C[:, :3, 3]
    n = rng.normal(size=3)
    plane = Plane(n / np.linalg.norm(n), 0.3, rng.normal(size=3))
    prior = GroundPrior.of(0.01, 1.0, 1000.0)  # loose: the robust loss in its quadratic part
    t_s = np.array([0.0, 0.03, 0.07, 0.1, 0.9, 0.95])  # a 0.8 s gap: frames 3 and 4 not tied
    part = GroundLevel(prior, t_s, 0.5)
    assert part.uses == ("ground",) and GroundLevel(prior, t_s, 0.5, plane).uses == ()
    terms = part.terms(R, t, {"ground": plane})
    np.testing.assert_array_equal(terms.first, [0, 1, 2, 4])
    c = centres(R, t)
    j = terms.first
    q = (c[j + 1] - c[j]) @ plane.n / (1000.0 * np.sqrt(t_s[j + 1] - t_s[j]))
    _, w = rho(prior.loss, q * q / prior.f_scale**2)
    np.testing.assert_allclose(terms.r[:, 0], q * np.sqrt(w), rtol=1e-12)
    eps = 1e-7
    for f in range(len(R)):
        for k in range(6):
            d = np.zeros((len(R), 6))
            d[f, k] = eps
            num = level_terms(*left_update(R, t, d), t_s, j, plane, prior, True).r - terms.r
            for m, first in enumerate(j):
                want = terms.Jc[m, f - first, 0, k] if f in (first, first + 1) else 0.0
                np.testing.assert_allclose(
                    num[m, 0] / eps, want, atol=1e-4 * np.abs(terms.Jc).max()
                )
    for k in range(6):
        step = np.zeros(6)
        step[k] = eps
        num = (level_terms(R, t, t_s, j, plane.update(step), prior, True).r - terms.r) / eps
        np.testing.assert_allclose(
            num, terms.Jg[:, :, k], atol=1e-4 * np.abs(terms.Jg).max() + 1e-9
        )


def _noisy_ring():  # type: ignore[no-untyped-def]
    """The noisy ring's problem: its truth, the plane its cameras ride, its motion prior and
    ``solve(priors)``, the joint solve from the truth with the motion prior and ``priors``."""
    ob, W, C, anchor, t_s = corner_problem(noise_px=1.0, seed=5)
    free = np.arange(len(W)) != anchor
    truth = fit_plane(C[:, :3, :3], C[:, :3, 3], PRIOR)
    motion = MotionPrior(t_s, 0.3, 1.0, 1.0)

    def solve(priors=()):  # type: ignore[no-untyped-def]
        return solve_joint(
            W[:, :3, :3],
            W[:, :3, 3],
            C[:, :3, :3],
            C[:, :3, 3],
            ob,
            free,
            Corners(FOCAL_PX),
            [motion, *priors],
            covariance=True,
        )

    return W, C, truth, motion, solve


def test_level_term_steadies_the_height_of_a_noisy_ring() -> None:
    """With the level term beside the per-frame one (the motion prior's steps), the ring's
    camera heights come out steadier than with the per-frame term alone."""
    W, C, truth, motion, solve = _noisy_ring()
    free_res = solve()
    heights = []
    for prior in (PRIOR, GroundPrior.of(0.01, 1.0, 0.005)):
        res, block = solve_grounded(
            free_res, lambda r, priors: solve(priors), prior, "plane", motion=motion
        )
        assert block.applied
        assert ("level" in res.terms) == np.isfinite(prior.level_sigma)
        _, Rf, tf = umeyama(res.t_tag, W[:, :3, 3], with_scale=False)
        cam = centres(res.R_cam, res.t_cam) @ Rf.T + tf - centres(C[:, :3, :3], C[:, :3, 3])
        h = cam @ truth.n
        heights.append(float(np.std(np.diff(h))))
    assert heights[1] < 0.7 * heights[0]


def test_fit_plane_recovers_the_floor_and_the_mount() -> None:
    C = planar_cameras()
    plane = fit_plane(C[:, :3, :3], C[:, :3, 3], PRIOR)
    p, _, _ = plane_terms(C[:, :3, :3], C[:, :3, 3], plane, PRIOR)
    assert np.abs(p).max() < 1e-9  # every frame on the plane, at the same tilt
    level = R_from_rotvec(np.array([[0.3, 0.0, -0.2]]))[0]
    assert abs(abs(plane.n @ level[:, 1]) - 1.0) < 1e-12  # the floor's normal
    u = plane.u / np.linalg.norm(plane.u)
    np.testing.assert_allclose(np.degrees(np.arccos(abs(u[1]))), 12.0, atol=1e-9)


def test_planarity_tells_a_robot_from_a_hand_held_camera() -> None:
    rng = np.random.default_rng(3)
    C = planar_cameras(200)
    cov = np.broadcast_to(np.diag([1e-4] * 3 + [1e-5] * 3), (200, 6, 6))  # 0.6 deg, 3 mm
    robot = perturbed(C, 4, np.radians(0.5), 0.005)  # 5 mm / 0.5 deg off the plane
    assert planarity(robot[:, :3, :3], robot[:, :3, 3], cov, PRIOR)[1] < PLANAR_BOUND
    # a hand-held camera: +-10 cm up and down and +-5 deg of roll and pitch
    hand = make_T(
        R_from_rotvec(rng.normal(scale=np.radians(5.0), size=(200, 3))) @ C[:, :3, :3],
        C[:, :3, 3] + rng.normal(scale=0.1, size=(200, 3)),
    )
    assert planarity(hand[:, :3, :3], hand[:, :3, 3], cov, PRIOR)[1] > 5 * PLANAR_BOUND


def test_ground_prior_holds_a_noisy_ring_in_its_plane() -> None:
    """The ring's camera rides a plane: with the prior (cameras, tags and plane solved together)
    the cameras' height error drops several-fold, the tags follow, and the plane found is the
    true one -- all after the best rigid fit of the tags to the truth (the anchor's own error
    tilts the whole solution; it is no error of the prior's)."""
    W, C, truth, _, solve = _noisy_ring()

    free_res = solve()
    res, block = solve_grounded(free_res, lambda r, priors: solve(priors), PRIOR, "auto")
    assert block.applied and block.planarity < PLANAR_BOUND
    plane = res.unknowns["ground"]

    def errors(r):  # type: ignore[no-untyped-def]
        _, Rf, tf = umeyama(r.t_tag, W[:, :3, 3], with_scale=False)
        cam = centres(r.R_cam, r.t_cam) @ Rf.T + tf - centres(C[:, :3, :3], C[:, :3, 3])
        tags = r.t_tag @ Rf.T + tf - W[:, :3, 3]
        return (
            float(np.sqrt(np.mean((cam @ truth.n) ** 2))),
            float(np.sqrt(np.mean(np.sum(tags**2, axis=1)))),
            Rf,
        )

    h0, tags0, _ = errors(free_res)
    h1, tags1, Rf = errors(res)
    assert h1 < 0.4 * h0
    assert tags1 < tags0
    assert np.degrees(np.arccos(abs((Rf @ plane.n) @ truth.n))) < 0.5


def test_auto_leaves_a_hand_held_path_alone() -> None:
    ob, W, C, anchor, t_s = corner_problem(noise_px=0.3, seed=6)
    rng = np.random.default_rng(7)
    # lift the cameras +-15 cm and tip them +-6 deg: the corners come from those poses
    C2 = make_T(
        R_from_rotvec(rng.normal(scale=np.radians(6.0), size=(len(C), 3))) @ C[:, :3, :3],
        C[:, :3, 3] + rng.normal(scale=0.15, size=(len(C), 3)),
    )
    pts_w = np.einsum("oij,okj->oki", W[ob.tag, :3, :3], ob.pts_tag) + W[ob.tag, None, :3, 3]
    pc = np.einsum("oij,okj->oki", C2[ob.frame, :3, :3], pts_w) + C2[ob.frame, None, :3, 3]
    ok = (pc[..., 2] > 0.05).all(axis=1)
    uv = pc[..., :2] / pc[..., 2:]
    ob2 = type(ob)(ob.frame[ok], ob.tag[ok], ob.pts_tag[ok], uv[ok])
    free = np.arange(len(W)) != anchor
    res = solve_joint(
        W[:, :3, :3],
        W[:, :3, 3],
        C2[:, :3, :3],
        C2[:, :3, 3],
        ob2,
        free,
        Corners(FOCAL_PX),
        covariance=True,
    )
    out, block = solve_grounded(
        res,
        lambda r, priors: solve_joint(
            r.R_tag, r.t_tag, r.R_cam, r.t_cam, ob2, free, Corners(FOCAL_PX), priors
        ),
        PRIOR,
        "auto",
    )
    assert not block.applied and block.planarity > 5 * PLANAR_BOUND
    assert out is res
