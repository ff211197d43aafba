"""Pose graph (Eq. 3.2-3.7): analytic Jacobian, per-edge robust loss, exact and noisy recovery."""

from __future__ import annotations

import numpy as np
import pytest

from tagtrail.errors import DataError
from tagtrail.geometry.posegraph import (
    PoseGraph,
    _Problem,
    block_loss,
    initial_guess,
    relative_residuals,
    solve,
)
from tagtrail.geometry.robust import rho
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import R_from_rotvec


def random_graph(
    seed: int, n: int = 8, n_edges: int = 300, noise_t: float = 0.0, noise_r: float = 0.0
) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    R = R_from_rotvec(rng.normal(scale=0.8, size=(n, 3)))
    t = rng.uniform(-2, 2, size=(n, 3))
    R[0], t[0] = np.eye(3), 0.0
    i = rng.integers(0, n, n_edges)
    j = (i + rng.integers(1, 3, n_edges)) % n
    dR = R_from_rotvec(rng.normal(scale=noise_r, size=(n_edges, 3)))
    R_obs = np.swapaxes(R[i], -1, -2) @ R[j] @ dR
    dt = rng.normal(scale=noise_t, size=(n_edges, 3))
    t_obs = np.einsum("eba,eb->ea", R[i], t[j] - t[i]) + dt
    g = PoseGraph(n, 0, i, j, R_obs, t_obs, rng.uniform(0.5, 2.0, n_edges), rot_weight_m=0.7)
    return g, R, t


def test_analytic_jacobian_matches_finite_differences() -> None:
    g, _, _ = random_graph(0, n_edges=60, noise_t=0.05, noise_r=0.05)
    R0, _ = initial_guess(g)
    prob = _Problem(g, R0)
    x = np.random.default_rng(1).normal(scale=0.3, size=prob.n_params)
    J = prob.jac(x).toarray()
    num = np.zeros_like(J)
    for k in range(prob.n_params):
        d = np.zeros_like(x)
        d[k] = 1e-6
        num[:, k] = (prob.fun(x + d) - prob.fun(x - d)) / 2e-6
    assert np.abs(J - num).max() < 1e-6


def test_block_loss_sums_rho_of_edge_norms() -> None:
    f = np.random.default_rng(2).normal(size=(5, 6))
    z = (f**2).reshape(-1)
    out = block_loss("cauchy")(z)
    s = (f**2).sum(axis=1)
    assert out[0].sum() == pytest.approx(rho("cauchy", s)[0].sum())
    assert np.allclose(out[1].reshape(5, 6), rho("cauchy", s)[1][:, None])
    assert block_loss("linear") == "linear"


def test_exact_graph_recovered_exactly() -> None:
    g, R, t = random_graph(3)
    res = solve(g)
    assert np.abs(res.t - t).max() < 1e-9
    assert np.rad2deg(geodesic_angle(res.R, R)).max() < 1e-8
    assert np.abs(res.res_t).max() < 1e-9


def test_perturbed_start_recovers_noisy_graph() -> None:
    """From a start 20 deg / 0.5 m off, the solver lands on the same optimum as from the tree."""
    g, R, t = random_graph(4, noise_t=0.02, noise_r=0.01)
    ref = solve(g, loss="linear")
    rng = np.random.default_rng(5)
    R0 = R @ R_from_rotvec(rng.normal(scale=0.2, size=R.shape[:1] + (3,)))
    t0 = t + rng.normal(scale=0.3, size=t.shape)
    res = solve(g, loss="linear", init=(R0, t0))
    assert np.abs(res.t - ref.t).max() < 1e-5  # both stop at ftol = 1e-8 (relative cost)
    assert np.abs(res.t - t).max() < 0.05
    r_t, _ = relative_residuals(res.R, res.t, g)
    assert np.allclose(r_t, res.res_t)


def test_unreachable_tag_is_a_data_error() -> None:
    g, _, _ = random_graph(6, n=4, n_edges=20)
    lonely = PoseGraph(5, 0, g.idx_i, g.idx_j, g.R_obs, g.t_obs, g.weight)
    with pytest.raises(DataError, match="not connected"):
        solve(lonely)
