"""Pose graph (Eq. 3.2-3.7): analytic Jacobian, per-edge robust loss, exact and noisy recovery."""

from __future__ import annotations

import numpy as np
import pytest

from tagtrail.errors import DataError
from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.posegraph import (
    CornerObservations,
    PoseGraph,
    _Problem,
    _same_frame_pairs,
    block_loss,
    bundle_adjust,
    initial_guess,
    relative_residuals,
    solve,
)
from tagtrail.geometry.robust import rho
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import R_from_rotvec, inv, make_T
from tests.stages.mapping_scene import ring_scene


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


# --- bundle adjustment on tag corners ------------------------------------------------------------

FOCAL_PX = 500.0


def corner_problem(
    noise_px: float = 0.0, seed: int = 0
) -> tuple[CornerObservations, np.ndarray, np.ndarray, int]:
    """The ring scene's corners as normalised image coordinates (+ Gaussian noise in px)."""
    scene = ring_scene(n_tags=12, r_cam=1.0, half_fov_deg=50.0, n_frames=180)
    pts_tag = tag_corners(np.full(len(scene.frame), scene.size_m))
    cam_T_tag = scene.cam_T_tag()
    p = np.einsum("oij,okj->oki", cam_T_tag[:, :3, :3], pts_tag) + cam_T_tag[:, None, :3, 3]
    uv = p[..., :2] / p[..., 2:]
    uv = uv + np.random.default_rng(seed).normal(scale=noise_px / FOCAL_PX, size=uv.shape)
    frames, f = np.unique(scene.frame, return_inverse=True)
    a_T_w = inv(scene.world_T_tag[0])  # anchor (tag 0) frame = world of the problem
    return (CornerObservations(f, scene.tag.astype(np.int64), pts_tag, uv),
            a_T_w @ scene.world_T_tag, inv(a_T_w @ scene.world_T_cam[frames]), 0)


def perturbed(T: np.ndarray, seed: int, rot: float, trans: float, keep: int | None = None
              ) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = make_T(R_from_rotvec(rng.normal(scale=rot, size=(len(T), 3))) @ T[:, :3, :3],
                 T[:, :3, 3] + rng.normal(scale=trans, size=(len(T), 3)))
    if keep is not None:
        out[keep] = T[keep]
    return out


def test_same_frame_pairs_are_all_ordered_pairs_within_each_frame() -> None:
    frame = np.array([2, 0, 2, 1, 2, 0])
    a, b = _same_frame_pairs(frame)
    got = sorted(zip(a.tolist(), b.tolist(), strict=True))
    want = sorted((i, j) for i in range(6) for j in range(6) if frame[i] == frame[j])
    assert got == want


def test_bundle_adjust_recovers_exact_poses_from_a_perturbed_start() -> None:
    ob, W, C, anchor = corner_problem()
    W0 = perturbed(W, 1, 0.02, 0.03, keep=anchor)
    C0 = perturbed(C, 2, 0.02, 0.03)
    res = bundle_adjust(W0[:, :3, :3], W0[:, :3, 3], C0[:, :3, :3], C0[:, :3, 3], ob, anchor,
                        px_per_unit=FOCAL_PX)
    assert res.converged and res.res_px.max() < 1e-6
    assert np.abs(res.t_tag - W[:, :3, 3]).max() < 1e-8
    assert np.rad2deg(geodesic_angle(res.R_tag, W[:, :3, :3])).max() < 1e-6
    assert np.abs(res.t_cam - C[:, :3, 3]).max() < 1e-8
    assert np.array_equal(res.R_tag[anchor], np.eye(3)) and not res.t_tag[anchor].any()


def test_bundle_adjust_with_noise_and_an_outlier_detection() -> None:
    """0.1 px corner noise: a cm-level map (its error is mostly the anchor tag's own orientation,
    levered over the 6 m ring); one detection 15 px off moves the robust solution less than half
    as far as the plain least squares."""
    ob, W, C, anchor = corner_problem(noise_px=0.1, seed=3)
    uv = ob.uv.copy()
    uv[7] += 15.0 / FOCAL_PX
    ob_bad = CornerObservations(ob.frame, ob.tag, ob.pts_tag, uv)
    W0 = perturbed(W, 4, 0.01, 0.02, keep=anchor)
    t = {}
    for name, obs, loss in (("clean", ob, "huber"), ("huber", ob_bad, "huber"),
                            ("linear", ob_bad, "linear")):
        res = bundle_adjust(W0[:, :3, :3], W0[:, :3, 3], C[:, :3, :3], C[:, :3, 3], obs, anchor,
                            px_per_unit=FOCAL_PX, loss=loss, f_scale_px=1.0)
        assert res.converged
        t[name] = res.t_tag
    assert np.linalg.norm(t["clean"] - W[:, :3, 3], axis=1).max() < 0.015
    shift = {k: np.linalg.norm(t[k] - t["clean"], axis=1).max() for k in ("huber", "linear")}
    assert shift["huber"] < 0.5 * shift["linear"]
