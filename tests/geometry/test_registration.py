"""Umeyama / RANSAC alignment (Eqs. 3.9–3.10): exact recovery, outliers, degenerate input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.errors import DataError
from tagtrail.geometry.registration import ransac_align, umeyama


def rot2(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def test_umeyama_exact_2d_3d_and_batched() -> None:
    rng = np.random.default_rng(0)
    src = rng.uniform(-2, 2, (5, 8, 2))
    s_true, R_true, t_true = 1.07, rot2(-131.0), np.array([0.4, -2.0])
    s, R, t = umeyama(src, s_true * src @ R_true.T + t_true, with_scale=True)
    np.testing.assert_allclose(s, s_true, atol=1e-12)
    np.testing.assert_allclose(R, np.broadcast_to(R_true, (5, 2, 2)), atol=1e-12)
    np.testing.assert_allclose(t, np.broadcast_to(t_true, (5, 2)), atol=1e-12)
    for i in range(5):  # batch == loop
        si, Ri, ti = umeyama(src[i], s_true * src[i] @ R_true.T + t_true, with_scale=True)
        np.testing.assert_allclose([si, *Ri.ravel(), *ti], [s[i], *R[i].ravel(), *t[i]])
    R3 = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    p = rng.normal(size=(10, 3))
    s, R, t = umeyama(p, 0.95 * p @ R3.T + [1, 2, 3], with_scale=True)
    assert s == pytest.approx(0.95) and np.allclose(R, R3) and np.allclose(t, [1, 2, 3])
    s, R, t = umeyama(p, p @ R3.T + [1, 2, 3], with_scale=False)
    assert s == 1.0 and np.allclose(R, R3)


def test_umeyama_never_returns_a_reflection() -> None:
    src = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    _, R, _ = umeyama(src, src * [1.0, -1.0], with_scale=True)  # a mirror image
    assert np.linalg.det(R) == pytest.approx(1.0)


@pytest.mark.parametrize("model", ["similarity", "rigid"])
def test_ransac_recovers_planar_transform_with_30_percent_outliers(model: str) -> None:
    rng = np.random.default_rng(7)
    n = 20
    src = rng.uniform(-3, 3, (n, 2))
    scale = 1.04 if model == "similarity" else 1.0
    R, t = rot2(63.2), np.array([0.07, 1.8])
    dst = scale * src @ R.T + t + rng.normal(0, 2e-4, (n, 2))
    bad = rng.choice(n, 6, replace=False)
    dst[bad] += rng.uniform(0.3, 1.5, (6, 2)) * rng.choice([-1, 1], (6, 2))
    al = ransac_align(src, dst, model, threshold_m=0.10, iterations=300, seed=1)
    assert al.scale == pytest.approx(scale, abs=1e-4)
    assert al.rotation_deg == pytest.approx(63.2, abs=0.01)
    np.testing.assert_allclose(al.t, t, atol=1e-3)
    expected = np.ones(n, bool)
    expected[bad] = False
    np.testing.assert_array_equal(al.inliers, expected)
    assert al.rms_m < 1e-3 and al.n_common == n
    np.testing.assert_allclose(al.apply(src[expected]), dst[expected], atol=1e-3)


def test_ransac_is_seeded_when_it_samples() -> None:
    rng = np.random.default_rng(2)
    src = rng.uniform(-3, 3, (40, 2))  # C(40, 2) = 780 > 50 iterations: random draws
    dst = src @ rot2(10).T
    dst[:12] += 1.0
    a = ransac_align(src, dst, "similarity", iterations=50, seed=5)
    b = ransac_align(src, dst, "similarity", iterations=50, seed=5)
    assert a.scale == b.scale and np.array_equal(a.R, b.R) and np.array_equal(a.inliers, b.inliers)
    assert a.inliers.sum() == 28 and a.rotation_deg == pytest.approx(10.0, abs=1e-9)


def test_sim3_with_outliers() -> None:
    rng = np.random.default_rng(4)
    src = rng.uniform(-2, 2, (15, 3))
    R = Rotation.from_rotvec([0.1, 0.9, -0.2]).as_matrix()
    dst = 1.02 * src @ R.T + [0.5, -0.1, 2.0]
    dst[:4] += [0.8, 0.0, -0.5]
    al = ransac_align(src, dst, "sim3", seed=0)
    assert al.inliers.sum() == 11 and al.scale == pytest.approx(1.02)
    np.testing.assert_allclose(al.R, R, atol=1e-9)
    assert al.rotation_deg == pytest.approx(math.degrees(np.linalg.norm([0.1, 0.9, -0.2])))


def test_scale_check() -> None:
    src = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]])
    al = ransac_align(src, 1.5 * src, "similarity")
    with pytest.raises(DataError, match=r"scale 1\.5000 is outside \[0\.900, 1\.100\]"):
        al.check_scale()
    assert al.check_scale(allow=True) is al


def test_bad_input() -> None:
    with pytest.raises(DataError, match="at least 2 common tags, found 1"):
        ransac_align([[0.0, 0.0]], [[1.0, 1.0]], "similarity")
    with pytest.raises(DataError, match="at least 3 common tags"):
        ransac_align(np.zeros((2, 3)), np.zeros((2, 3)), "se3")
    with pytest.raises(DataError):  # all common tags at one place: no rotation, no scale
        ransac_align(np.ones((4, 2)), np.ones((4, 2)) * 2, "similarity")
    with pytest.raises(DataError, match="agree"):  # rigid: the two tags' distances differ by 1 m
        ransac_align([[0.0, 0.0], [1.0, 0.0]], [[0.0, 0.0], [2.0, 0.0]], "rigid")
    with pytest.raises(DataError, match="unknown alignment model"):
        ransac_align(np.zeros((3, 2)), np.zeros((3, 2)), "affine")
