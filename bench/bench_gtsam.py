"""Benchmark: tagtrail's pairwise pose graph (Eq. 3.4-3.7) vs GTSAM on the same graph.

The graph is bench_optimize's synthetic room (tags at random poses in a 10 x 3 x 10 m box, each
edge observation joins a tag and one of its 6 nearest neighbours, ``i_T_j`` with 1 cm / 0.5 deg
Gaussian noise and 2 % gross outliers of 30 deg / 30 cm). Both solvers start from the same
spanning-tree guess (``posegraph.initial_guess``, timed on both sides) and hold the anchor fixed:

- tagtrail: ``posegraph.solve`` with optimize's defaults (soft_l1, f_scale 0.1);
- GTSAM: ``BetweenFactorPose3`` per edge with ``noiseModel.Robust(Huber(0.1), Isotropic(1))`` --
  GTSAM has no soft-l1 kernel; Huber is the one of the same shape (quadratic, then linear
  beyond 0.1) -- a ``PriorFactorPose3`` with a constrained noise model on the anchor, and
  ``LevenbergMarquardtOptimizer`` with its default parameters. Its time includes building the
  factor graph from the arrays (a Python loop: what a Python user pays); the LM alone is
  reported too.

Error = mean tag position error against the generating ground truth (and the rotation error);
the same-kernel figure solves tagtrail's graph with ``loss="huber"`` too. Repeats alternate the
two solvers. Run: ``.venv/bin/python bench/bench_gtsam.py [--repeats 3]``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # as tagtrail.cli.main_entry does, before numpy loads

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

from tagtrail.geometry.posegraph import PoseGraph, initial_guess, solve  # noqa: E402
from tagtrail.geometry.rotations import geodesic_angle  # noqa: E402
from tagtrail.geometry.se3 import R_from_rotvec  # noqa: E402

SIZES = ((50, 20_000), (200, 80_000), (500, 200_000))
F_SCALE = 0.1


def make_graph(
    n_tags: int, n_edges: int, seed: int = 0
) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """The graph and its ground truth ``anchor_T_tag`` as ``R (n, 3, 3)``, ``t (n, 3)``
    (anchor = tag 0; the same scene as bench_optimize.graph)."""
    rng = np.random.default_rng(seed)
    R = R_from_rotvec(rng.normal(scale=1.0, size=(n_tags, 3)))
    t = rng.uniform([-5, -1.5, -5], [5, 1.5, 5], size=(n_tags, 3))
    R[0], t[0] = np.eye(3), 0.0
    d = np.linalg.norm(t[:, None] - t[None], axis=-1)
    near = np.argsort(d, axis=1)[:, 1:7]
    i = rng.integers(0, n_tags, n_edges)
    j = near[i, rng.integers(0, 6, n_edges)]
    i, j = np.minimum(i, j), np.maximum(i, j)
    dR = R_from_rotvec(rng.normal(scale=np.deg2rad(0.5), size=(n_edges, 3)))
    R_obs = np.swapaxes(R[i], -1, -2) @ R[j] @ dR
    t_obs = np.einsum("eba,eb->ea", R[i], t[j] - t[i]) + rng.normal(scale=0.01, size=(n_edges, 3))
    bad = rng.random(n_edges) < 0.02
    axis = rng.normal(size=(bad.sum(), 3))
    axis *= np.deg2rad(30) / np.linalg.norm(axis, axis=1, keepdims=True)
    R_obs[bad] = R_obs[bad] @ R_from_rotvec(axis)
    t_obs[bad] += rng.normal(scale=0.3, size=(bad.sum(), 3))
    g = PoseGraph(n_tags, 0, i.astype(np.int64), j.astype(np.int64), R_obs, t_obs, np.ones(n_edges))
    return g, R, t


def map_error(
    R: np.ndarray, t: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray
) -> tuple[float, float]:
    """Mean position error (m) and mean rotation error (deg) over the non-anchor tags."""
    return (
        float(np.linalg.norm(t - t_gt, axis=1)[1:].mean()),
        float(np.rad2deg(geodesic_angle(R, R_gt))[1:].mean()),
    )


def run_gtsam(g: PoseGraph, k: float = F_SCALE) -> tuple[np.ndarray, np.ndarray, float, float, int]:
    """GTSAM's LM from the spanning-tree guess: ``R, t``, total s, LM-only s, iterations."""
    try:
        import gtsam
    except ImportError as err:
        raise SystemExit("bench_gtsam needs GTSAM: pip install -e '.[bench]'") from err

    t0 = time.perf_counter()
    R0, t0_ = initial_guess(g)
    graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(k), gtsam.noiseModel.Isotropic.Sigma(6, 1.0)
    )
    for a, b, R_ab, t_ab in zip(g.idx_i.tolist(), g.idx_j.tolist(), g.R_obs, g.t_obs, strict=True):
        graph.add(gtsam.BetweenFactorPose3(a, b, gtsam.Pose3(gtsam.Rot3(R_ab), t_ab), noise))
    graph.add(gtsam.PriorFactorPose3(g.anchor, gtsam.Pose3(), gtsam.noiseModel.Constrained.All(6)))
    values = gtsam.Values()
    for k_ in range(g.n_tags):
        values.insert(k_, gtsam.Pose3(gtsam.Rot3(R0[k_]), t0_[k_]))
    t1 = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams())
    res = opt.optimize()
    t2 = time.perf_counter()
    R = np.stack([res.atPose3(k_).rotation().matrix() for k_ in range(g.n_tags)])
    t = np.stack([res.atPose3(k_).translation() for k_ in range(g.n_tags)])
    return R, t, t2 - t0, t2 - t1, int(opt.iterations())


@dataclass
class Comparison:
    """Medians of one size: seconds, errors (m, deg), tagtrail's evaluations, GTSAM's LM."""

    n_tags: int
    n_edges: int
    repeats: int
    ours_s: float
    gtsam_s: float
    gtsam_lm_s: float
    ours_err_m: float
    gtsam_err_m: float
    ours_err_deg: float
    gtsam_err_deg: float
    huber_err_m: float
    nfev: int
    gtsam_iters: int

    @property
    def time_ratio(self) -> float:
        return self.ours_s / self.gtsam_s

    @property
    def error_ratio(self) -> float:
        return self.ours_err_m / self.gtsam_err_m

    @property
    def same_kernel_error_ratio(self) -> float:
        return self.huber_err_m / self.gtsam_err_m


def compare(n_tags: int, n_edges: int, repeats: int = 3) -> Comparison:
    """One graph size, the two solvers alternated ``repeats`` times (results are deterministic,
    so the errors come from the last repeat)."""
    g, R_gt, t_gt = make_graph(n_tags, n_edges)
    ours_s, gt_s, gt_lm = [], [], []
    ours = gt = None
    iters = 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        ours = solve(g, loss="soft_l1", f_scale=F_SCALE)
        ours_s.append(time.perf_counter() - t0)
        R, t, total, lm, iters = run_gtsam(g)
        gt = (R, t)
        gt_s.append(total)
        gt_lm.append(lm)
    assert ours is not None and gt is not None
    huber = solve(g, loss="huber", f_scale=F_SCALE)
    e_ours, e_gt = map_error(ours.R, ours.t, R_gt, t_gt), map_error(*gt, R_gt, t_gt)
    return Comparison(
        n_tags,
        n_edges,
        repeats,
        statistics.median(ours_s),
        statistics.median(gt_s),
        statistics.median(gt_lm),
        e_ours[0],
        e_gt[0],
        e_ours[1],
        e_gt[1],
        map_error(huber.R, huber.t, R_gt, t_gt)[0],
        ours.nfev,
        iters,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    for n, e in SIZES:
        c = compare(n, e, args.repeats)
        print(
            f"{n} tags / {e:,} edges (median of {c.repeats}): tagtrail {c.ours_s:.3f} s "
            f"({c.nfev} evaluations), GTSAM {c.gtsam_s:.3f} s (LM alone {c.gtsam_lm_s:.3f} s, "
            f"{c.gtsam_iters} iterations) -> time {c.time_ratio:.2f}x; mean position error "
            f"{c.ours_err_m * 1e3:.3f} vs {c.gtsam_err_m * 1e3:.3f} mm -> {c.error_ratio:.3f}x "
            f"(same Huber kernel: {c.same_kernel_error_ratio:.3f}x); rotation "
            f"{c.ours_err_deg:.4f} vs {c.gtsam_err_deg:.4f} deg",
            flush=True,
        )


if __name__ == "__main__":
    main()
