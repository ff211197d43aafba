"""The wheeled-drive prior (geometry.joint.drive): its Jacobians, the mount fit, the test that
decides ``auto`` (a wheeled robot from one that slides sideways), and what it buys the joint
solve."""

from __future__ import annotations

import numpy as np
import pytest

from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.joint import (
    CornerObservations,
    Corners,
    MotionPrior,
    solve_grounded,
    solve_joint,
)
from tagtrail.geometry.joint.drive import (
    WHEELED_BOUND,
    DrivePrior,
    Mount,
    drive_terms,
    fit_mount,
    steps,
    strain,
)
from tagtrail.geometry.joint.ground import GroundPrior, Plane, fit_plane
from tagtrail.geometry.joint.problem import centres, left_update
from tagtrail.geometry.registration import umeyama
from tagtrail.geometry.se3 import R_from_rotvec, inv, make_T
from tests.geometry.problems import FOCAL_PX, corner_problem, perturbed, planar_cameras

GROUND = GroundPrior(0.01, np.radians(1.0))
DRIVE = DrivePrior(0.01)
LEVEL = R_from_rotvec(np.array([[0.3, 0.0, -0.2]]))[0]  # world_R_floor: the anchor is not level


def _d(a: np.ndarray) -> np.ndarray:
    """Horizontal unit vectors ``(N, 3)`` of the floor frame (y up) at headings ``a``: what a
    camera of :func:`planar_cameras` at yaw ``a`` looks along."""
    return np.stack([-np.sin(a), np.zeros_like(a), -np.cos(a)], axis=1)


def drive_cameras(
    n: int = 300,
    lever_m: float = 0.084,
    yaw_deg: float = 10.0,
    crab_mps: float = 0.0,
    fps: float = 30.0,
) -> tuple[np.ndarray, np.ndarray]:
    """``cam_T_world (n, 4, 4)`` and stamps (s) of a camera on a robot driving a weaving path at
    0.3 m/s on a tilted floor: mounted ``lever_m`` ahead of the point between the wheels, turned
    ``yaw_deg`` to the left of the robot's heading and pitched down 12 deg; ``crab_mps``: the
    robot also slides sideways (to its left) at that speed times a slow sine, as a mecanum base."""
    t = np.arange(n) / fps

    def heading(t: np.ndarray) -> np.ndarray:
        return 0.6 * np.sin(0.4 * t) + 0.15 * t

    # each step along the heading halfway through it (the chord of the arc the axle drives)
    mid = heading(t - 0.5 / fps)
    side = crab_mps * np.sin(0.8 * t + 0.5)
    vel = 0.3 * _d(mid) + side[:, None] * _d(mid + np.pi / 2)  # left = forward turned 90 deg
    base = np.cumsum(vel, axis=0) / fps
    heading = heading(t)
    pos = base + lever_m * _d(heading) + np.array([0.0, 0.17, 0.0])
    flip = np.diag([1.0, -1.0, -1.0])  # camera y down, z forward
    pitch = R_from_rotvec(np.array([[np.radians(12.0), 0.0, 0.0]]))[0]
    yaw = heading + np.radians(yaw_deg)
    floor_R_cam = R_from_rotvec(np.stack([np.zeros(n), yaw, np.zeros(n)], axis=1)) @ flip @ pitch
    world_T_cam = make_T(LEVEL @ floor_R_cam, pos @ LEVEL.T + np.array([0.5, -0.2, 1.0]))
    return inv(world_T_cam), t


def test_drive_terms_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(1)
    C = perturbed(planar_cameras(6), 2, 0.05, 0.05)
    R, t = C[:, :3, :3], C[:, :3, 3]
    n = rng.normal(size=3)
    plane = Plane(n / np.linalg.norm(n), 0.3, rng.normal(size=3))
    g = rng.normal(size=3)
    mount = Mount(g / np.linalg.norm(g), 0.2)
    t_s = np.arange(6) * 0.1
    j = steps(t_s, 1.0)
    q, Jc, Jg = drive_terms(R, t, t_s, j, plane, mount, DRIVE)
    eps = 1e-7
    for f in range(len(R)):
        for c in range(6):
            d = np.zeros((len(R), 6))
            d[f, c] = eps
            num = (drive_terms(*left_update(R, t, d), t_s, j, plane, mount, DRIVE)[0] - q) / eps
            ana = np.where(j == f, Jc[:, 0, c], 0.0) + np.where(j + 1 == f, Jc[:, 1, c], 0.0)
            np.testing.assert_allclose(num, ana, atol=1e-6 * np.abs(Jc).max())
    for c in range(6):
        step = np.zeros(6)
        step[c] = eps
        num = (drive_terms(R, t, t_s, j, plane.update(step), mount, DRIVE)[0] - q) / eps
        np.testing.assert_allclose(num, Jg[:, c], atol=1e-6 * np.abs(Jg).max())
    for c in range(2):
        step = np.zeros(2)
        step[c] = eps
        num = (drive_terms(R, t, t_s, j, plane, mount.update(step, plane.u), DRIVE)[0] - q) / eps
        np.testing.assert_allclose(num, Jg[:, 6 + c], atol=1e-6 * np.abs(Jg).max())


def wall_tags(C: np.ndarray, spacing_m: float = 0.5, offset_m: float = 1.0) -> np.ndarray:
    """``world_T_tag`` of 16 cm tags on both sides of the cameras' path, ``offset_m`` from it
    every ``spacing_m``, at 0.3-0.4 m, each turned 40 deg from the wall towards the start."""
    floor = (centres(C[:, :3, :3], C[:, :3, 3]) - np.array([0.5, -0.2, 1.0])) @ LEVEL
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(floor, axis=0), axis=1))]
    poses = []
    for k, a in enumerate(np.arange(0.0, arc[-1] + 1.0, spacing_m)):
        i = min(int(np.searchsorted(arc, a)), len(floor) - 2)
        fwd = floor[i + 1] - floor[i]
        fwd = np.array([fwd[0], 0.0, fwd[2]]) / np.hypot(fwd[0], fwd[2])
        left = np.cross([0.0, 1.0, 0.0], fwd)
        for side in (1.0, -1.0):
            face = -side * left * np.cos(np.radians(40.0)) - fwd * np.sin(np.radians(40.0))
            c = floor[i] + fwd * 0.8 + side * offset_m * left
            c[1] = 0.3 + 0.1 * (k % 2)
            R = np.stack([np.cross([0.0, 1.0, 0.0], face), [0.0, 1.0, 0.0], face], axis=1)
            poses.append(make_T(LEVEL @ R, LEVEL @ c + np.array([0.5, -0.2, 1.0])))
    return np.stack(poses)


def corners(
    C: np.ndarray, W: np.ndarray, noise_px: float, seed: int = 0, half_fov_deg: float = 40.0
) -> CornerObservations:
    """The tags ``W`` each camera ``C`` (cam_T_world) sees within its field of view and 70 deg
    of incidence, as normalised coordinates with Gaussian noise (px at ``FOCAL_PX``)."""
    pts = tag_corners(np.full(len(W), 0.16))
    p_w = np.einsum("tij,tkj->tki", W[:, :3, :3], pts) + W[:, None, :3, 3]  # (T, 4, 3)
    p_c = np.einsum("fij,tkj->ftki", C[:, :3, :3], p_w) + C[:, None, None, :3, 3]
    centre = p_c.mean(axis=2)
    ang = np.degrees(np.arccos(np.clip(centre[..., 2] / np.linalg.norm(centre, axis=-1), -1, 1)))
    to_cam = centres(C[:, :3, :3], C[:, :3, 3])[:, None] - W[None, :, :3, 3]
    inc = np.einsum("ftk,tk->ft", to_cam, W[:, :3, 2]) / np.linalg.norm(to_cam, axis=-1)
    seen = (ang < half_fov_deg) & (inc > np.cos(np.radians(70.0))) & (p_c[..., 2] > 0.2).all(-1)
    f, t = np.nonzero(seen)
    uv = p_c[f, t, :, :2] / p_c[f, t, :, 2:]
    uv = uv + np.random.default_rng(seed).normal(scale=noise_px / FOCAL_PX, size=uv.shape)
    return CornerObservations(f.astype(np.int64), t.astype(np.int64), pts[t], uv)


def grounded_and_driven(
    C: np.ndarray, t_s: np.ndarray, W: np.ndarray, ob: CornerObservations, drive_mode: str = "auto"
):  # type: ignore[no-untyped-def]
    """The joint solve from the truth with the ground prior, then ``solve_grounded`` with the
    drive prior (``drive_mode``): the grounded solution, the final one and the report block."""
    free = np.arange(len(W)) != 0
    motion = MotionPrior(t_s, 0.1, 1.0, 0.5)

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

    grounded, _ = solve_grounded(solve(), lambda r, priors: solve(priors), GROUND, "plane")
    out, block = solve_grounded(
        solve(), lambda r, priors: solve(priors), GROUND, "plane", DRIVE, drive_mode, motion
    )
    return grounded, out, block.drive


def across_rms(r, W: np.ndarray, C: np.ndarray) -> float:  # type: ignore[no-untyped-def]
    """RMS camera error across the true direction of travel (m), after the best rigid fit of
    the tags to the truth."""
    true_c = centres(C[:, :3, :3], C[:, :3, 3])
    along = np.gradient(true_c, axis=0)
    along /= np.linalg.norm(along, axis=1)[:, None]
    _, Rf, tf = umeyama(r.t_tag, W[:, :3, 3], with_scale=False)
    e = centres(r.R_cam, r.t_cam) @ Rf.T + tf - true_c
    e -= np.sum(e * along, axis=1)[:, None] * along
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def test_fit_mount_recovers_the_lever_arm_and_the_camera_yaw() -> None:
    C, t_s = drive_cameras(lever_m=0.084, yaw_deg=10.0)
    R, t = C[:, :3, :3], C[:, :3, 3]
    plane = fit_plane(R, t, GROUND)
    j = steps(t_s, 0.5)
    mount = fit_mount(R, t, t_s, j, plane)
    q, _, _ = drive_terms(R, t, t_s, j, plane, mount, DRIVE)
    # the robot's forward axis seen from the camera: 10 deg to the right of the camera's
    u = plane.u / np.linalg.norm(plane.u)
    z = np.array([0.0, 0.0, 1.0]) - u[2] * u
    yaw = np.degrees(np.arctan2(np.cross(mount.g, z) @ u, mount.g @ z))
    assert abs(abs(yaw) - 10.0) < 0.05
    # a camera moving by finite steps is the model up to the steps' curvature (1/30 s)
    assert abs(mount.lever_m - 0.084) < 2e-3
    assert np.abs(q).max() * DRIVE.lateral_sigma * np.sqrt(1 / 30) < 2e-5  # 20 um a step


def test_a_known_lever_arm_is_held_and_the_yaw_fitted_on_a_steady_arc() -> None:
    """On a steady arc the lever arm and the camera's yaw are one unknown (both turn the steps
    by the same angle): fitted together they trade off; with the mount's lever arm given
    (``lever_m``) it is held and the yaw comes out right, even on a short history."""
    n = 90  # 3 s of a steady arc (0.3 m/s, radius 0.6 m)
    k, lever, yaw_deg = 0.5, 0.084, 3.0
    t = np.arange(n) / 30.0
    heading = k * t
    mid = heading - 0.5 * k / 30.0
    base = np.cumsum(0.3 * _d(mid), axis=0) / 30.0
    pos = base + lever * _d(heading) + np.array([0.0, 0.17, 0.0])
    flip = np.diag([1.0, -1.0, -1.0])
    yaw = heading + np.radians(yaw_deg)
    floor_R_cam = R_from_rotvec(np.stack([np.zeros(n), yaw, np.zeros(n)], axis=1)) @ flip
    C = inv(make_T(floor_R_cam, pos))
    R, tc = C[:, :3, :3], C[:, :3, 3]
    plane = fit_plane(R, tc, GROUND)
    j = steps(t, 0.5)
    u = plane.u / np.linalg.norm(plane.u)
    z = np.array([0.0, 0.0, 1.0]) - u[2] * u

    def yaw_of(m: Mount) -> float:
        return float(np.degrees(np.arctan2(np.cross(m.g, z) @ u, m.g @ z)))

    held = fit_mount(R, tc, t, j, plane, 0.5, lever_m=lever)
    assert held.lever_m == lever
    assert abs(abs(yaw_of(held)) - yaw_deg) < 0.02
    free = fit_mount(R, tc, t, j, plane, 0.5)  # the arc turned 1.5 rad: both fitted, traded
    assert abs(abs(yaw_of(free)) - yaw_deg) > 0.5 or abs(free.lever_m - lever) > 0.01


def test_strain_is_the_robust_chi2_per_step_in_the_variance_factor() -> None:
    q = np.array([1.0, -1.0, 0.0, 0.0])
    assert np.isclose(strain(q, DrivePrior(0.01, f_scale=1e9), 0.5), 1.0)  # 0.5 a step, / 0.5
    assert np.isclose(strain(q, DRIVE, 0.5), 0.9)  # Cauchy at 3 sigma weighs 1 sigma by 0.9
    assert np.isnan(strain(np.zeros(0), DRIVE, 1.0))


def test_drive_prior_holds_a_wheeled_camera_to_its_heading() -> None:
    """A camera on a wheeled robot, mounted 8.4 cm ahead of the axle and turned 10 deg, sees
    wall tags at 1 px noise: ``auto`` finds the prior costs the corners nothing, applies it,
    recovers the mount, and the cameras' error across their direction of travel drops."""
    C, t_s = drive_cameras()
    W = wall_tags(C)
    ob = corners(C, W, 1.0)
    grounded, driven, block = grounded_and_driven(C, t_s, W, ob)
    assert block.applied and block.strain < 0.5 * WHEELED_BOUND
    assert abs(block.lever_m - 0.084) < 0.02 and abs(abs(block.camera_yaw_deg) - 10) < 1.0
    assert across_rms(driven, W, C) < 0.8 * across_rms(grounded, W, C)  # 6.0 vs 8.5 mm


@pytest.mark.slow  # five joint solves of two drives (~10 s): make test-all
def test_auto_leaves_a_sliding_robot_and_a_panning_camera_alone() -> None:
    """A mecanum base sliding sideways at up to 20 cm/s, and the ring's camera that pans +-15
    deg as it goes round: the prior would cost every step several times the corners' variance
    factor, so ``auto`` leaves the solution as it was; forcing it (``wheeled``) bends it."""
    C, t_s = drive_cameras(crab_mps=0.2)
    W = wall_tags(C)
    ob = corners(C, W, 1.0)
    grounded, out, block = grounded_and_driven(C, t_s, W, ob)
    assert not block.applied and block.strain > 2 * WHEELED_BOUND
    assert out is grounded or np.allclose(out.t_cam, grounded.t_cam)
    _, forced, _ = grounded_and_driven(C, t_s, W, ob, "wheeled")
    assert across_rms(forced, W, C) > 1.5 * across_rms(grounded, W, C)  # 13.0 vs 2.6 mm

    ob, W, C, _, t_s = corner_problem(noise_px=1.0, seed=5)
    grounded, out, block = grounded_and_driven(C, t_s, W, ob)
    assert not block.applied and block.strain > 2 * WHEELED_BOUND
