"""SO(3) helpers: log/exp round trips, Jacobians against finite differences, rotation means."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.geometry.rotations import (
    geodesic_angle,
    grouped_chordal_mean,
    grouped_median,
    grouped_rotation_mean,
    hat,
    log_so3,
    project_to_so3,
    right_jacobian,
    right_jacobian_inv,
    wrap_angle,
)
from tagtrail.geometry.se3 import R_from_rotvec, rotvec_from_R


def random_rotvecs(rng: np.random.Generator, n: int, max_angle: float = np.pi) -> np.ndarray:
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * rng.uniform(0, max_angle, size=(n, 1))


def test_hat_is_cross_product() -> None:
    rng = np.random.default_rng(0)
    v, w = rng.normal(size=(2, 5, 3))
    assert np.allclose(np.einsum("nij,nj->ni", hat(v), w), np.cross(v, w))
    assert np.allclose(hat(v), -np.swapaxes(hat(v), -1, -2))


def test_log_exp_round_trip_including_zero_and_pi() -> None:
    rng = np.random.default_rng(1)
    rv = random_rotvecs(rng, 500)
    rv[:3] *= 1e-10  # near identity
    rv[3] = 0.0
    rv[4:8] *= (np.pi - 1e-9) / np.linalg.norm(rv[4:8], axis=1, keepdims=True)  # near pi
    rv[8:12] *= (np.pi - 0.03) / np.linalg.norm(rv[8:12], axis=1, keepdims=True)
    R = R_from_rotvec(rv)
    assert np.allclose(log_so3(R), rv, atol=1e-12)
    assert np.allclose(log_so3(R), rotvec_from_R(R), atol=1e-12)
    # batch shape preserved, and at exactly pi either sign is the same rotation
    assert log_so3(R[:6].reshape(2, 3, 3, 3)).shape == (2, 3, 3)
    Rpi = Rotation.from_rotvec([0.0, np.pi, 0.0]).as_matrix()
    assert np.allclose(R_from_rotvec(log_so3(Rpi)), Rpi, atol=1e-14)


@pytest.mark.parametrize("scale", [1e-7, 0.5, 2.5])
def test_right_jacobians_match_finite_differences(scale: float) -> None:
    """Exp(phi + d) = Exp(phi) Exp(J_r d);  Log(Exp(phi) Exp(d)) = phi + J_r^-1 d."""
    rng = np.random.default_rng(2)
    phi = random_rotvecs(rng, 4) * scale / np.pi
    eps = 1e-6
    for p in phi:
        Jr, Jinv = right_jacobian(p), right_jacobian_inv(p)
        num = np.zeros((3, 3))
        num_inv = np.zeros((3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            R0 = R_from_rotvec(p)
            num[:, k] = log_so3(R0.T @ R_from_rotvec(p + d)) / eps
            num_inv[:, k] = (log_so3(R0 @ R_from_rotvec(d)) - p) / eps
        assert np.allclose(Jr, num, atol=1e-5)
        assert np.allclose(Jinv, num_inv, atol=1e-5)
        assert np.allclose(Jr @ Jinv, np.eye(3), atol=1e-12)


def test_geodesic_angle_and_wrap() -> None:
    Ra = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    Rb = Rotation.from_euler("z", -170, degrees=True).as_matrix()
    assert np.rad2deg(geodesic_angle(Ra, Rb)) == pytest.approx(180.0)
    a = np.deg2rad([179.0, 181.0, -180.0, 540.0, 0.0])
    assert np.allclose(np.rad2deg(wrap_angle(a)), [179.0, -179.0, 180.0, 180.0, 0.0])


def test_project_to_so3() -> None:
    rng = np.random.default_rng(3)
    R = R_from_rotvec(random_rotvecs(rng, 10))
    assert np.allclose(project_to_so3(R), R)
    P = project_to_so3(R + 0.05 * rng.normal(size=R.shape))
    assert np.allclose(P @ np.swapaxes(P, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(P), 1.0)


def test_means_exact_on_identical_rotations_and_batch_matches_loop() -> None:
    rng = np.random.default_rng(4)
    centres = R_from_rotvec(random_rotvecs(rng, 5))
    group = np.repeat(np.arange(5), 7)
    noisy = centres[group] @ R_from_rotvec(rng.normal(scale=0.05, size=(35, 3)))
    assert np.allclose(grouped_chordal_mean(centres[group], group, 5), centres, atol=1e-12)
    assert np.allclose(grouped_rotation_mean(centres[group], group, 5), centres, atol=1e-9)
    batch = grouped_rotation_mean(noisy, group, 5, robust=False)
    for g in range(5):
        one = grouped_rotation_mean(noisy[group == g], np.zeros(7, int), 1, robust=False)[0]
        assert np.allclose(batch[g], one, atol=1e-12)
        chordal = grouped_chordal_mean(noisy, group, 5)[g]
        # scipy's Rotation.mean is the chordal L2 mean too
        assert np.allclose(chordal, Rotation.from_matrix(noisy[group == g]).mean().as_matrix())


def test_robust_mean_ignores_flipped_minority() -> None:
    """Perturb-and-recover: 3 of 11 rotations flipped by 60 deg barely move the L1 median."""
    rng = np.random.default_rng(5)
    truth = R_from_rotvec([0.3, -1.0, 0.4])
    R = truth @ R_from_rotvec(rng.normal(scale=0.01, size=(11, 3)))
    R[:3] = R[:3] @ Rotation.from_euler("x", 60, degrees=True).as_matrix()
    g = np.zeros(11, dtype=int)
    err_robust = np.rad2deg(geodesic_angle(grouped_rotation_mean(R, g, 1)[0], truth))
    err_l2 = np.rad2deg(geodesic_angle(Rotation.from_matrix(R).mean().as_matrix(), truth))
    assert err_robust < 1.5 < 10.0 < err_l2


def test_grouped_median() -> None:
    x = np.array([[1.0], [5.0], [3.0], [10.0], [20.0], [7.0]])
    g = np.array([0, 0, 0, 2, 2, 2])
    med = grouped_median(x, g, 3)
    assert med[0, 0] == 3.0 and np.isnan(med[1, 0]) and med[2, 0] == 10.0
    med2 = grouped_median(x[:5], g[:5], 3)
    assert med2[2, 0] == 15.0  # even count -> mean of the middle two
