"""Trajectory smoother on SO(3) x R^3: analytic Jacobian and segment handling."""

from __future__ import annotations

import numpy as np

from tagtrail.geometry.se3 import R_from_rotvec
from tagtrail.geometry.smoothing import _Smoother, segment_triples, smooth_poses


def test_segment_triples_break_at_gaps_and_repeated_stamps() -> None:
    t = np.array([0.0, 0.1, 0.2, 0.3, 2.0, 2.1, 2.2, 2.2, 2.3])
    assert segment_triples(t, 1.0).tolist() == [1, 2, 5]
    assert segment_triples(t[:2], 1.0).tolist() == []


def test_analytic_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(0)
    n = 12
    t = np.cumsum(rng.uniform(0.02, 0.1, n))
    R = R_from_rotvec(np.c_[np.zeros(n), np.pi - 0.2 + 0.4 * np.arange(n) / n, np.zeros(n)])
    p = rng.normal(size=(n, 3))
    prob = _Smoother(t, R, p, segment_triples(t, 1.0), (0.02, 0.03, 1.0, 2.0))
    x = rng.normal(scale=0.1, size=6 * n)
    J = prob.jac(x).toarray()
    num = np.zeros_like(J)
    for k in range(6 * n):
        d = np.zeros_like(x)
        d[k] = 1e-6
        num[:, k] = (prob.fun(x + d) - prob.fun(x - d)) / 2e-6
    assert np.abs(J - num).max() < 1e-7 * max(1.0, np.abs(J).max())


def test_too_short_passes_through() -> None:
    R = R_from_rotvec(np.zeros((2, 3)))
    p = np.zeros((2, 3))
    R2, p2 = smooth_poses(
        np.array([0.0, 0.1]), R, p, pos_sigma_m=0.01, rot_sigma_rad=0.01, pos_acc=1.0, rot_acc=1.0
    )
    assert np.array_equal(R2, R) and np.array_equal(p2, p)
