"""Benchmark: stage optimize on a 50-tag / 20,000-edge graph vs the 2 s target.

A synthetic room: 50 tags at random poses in a 10 x 3 x 10 m box; each edge observation joins a
tag and one of its 6 nearest neighbours, ``i_T_j`` with 1 cm / 0.5 deg Gaussian noise and 2 %
gross outliers (30 deg, 30 cm). Times ``tagtrail.stages.optimize.run`` end to end (spanning-tree
initialisation, robust trf solve, output tables), default parameters (soft_l1, f_scale 0.1),
and prints the median of ``--repeats`` runs, the ratio to the target and the map error.
Run: ``.venv/bin/python bench/bench_optimize.py [--repeats 5] [--tags 50] [--edges 20000]``.

Most of the time is LSMR's sparse products and vector norms; on a busy machine OpenBLAS's threads
slow those short BLAS-1 calls down ~2x. Like the ``tagtrail`` command, the benchmark runs with one
BLAS thread unless ``OPENBLAS_NUM_THREADS`` is set (printed below).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # as tagtrail.cli.main_entry does, before numpy loads

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from bench_gtsam import make_graph  # noqa: E402

from tagtrail.geometry.se3 import make_T, pose_error, quat_xyzw_from_R  # noqa: E402
from tagtrail.schemas.documents import TagGraph  # noqa: E402
from tagtrail.stages import optimize  # noqa: E402

POSE = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]
TARGET_S = 2.0


def graph(n_tags: int, n_edges: int, seed: int = 0) -> tuple[pd.DataFrame, TagGraph, np.ndarray]:
    """Edges frame, graph dict and ground-truth ``anchor_T_tag`` ``(n, 4, 4)`` (anchor = 0)."""
    g, R, t = make_graph(n_tags, n_edges, seed)  # the scene bench_gtsam compares on
    i, j, R_obs, t_obs = g.idx_i, g.idx_j, g.R_obs, g.t_obs
    edges = pd.DataFrame(
        {
            "t_ns": np.arange(n_edges, dtype=np.int64),
            "tag_i": i.astype(np.int32),
            "tag_j": j.astype(np.int32),
        }
    )
    edges[POSE] = np.concatenate([t_obs, quat_xyzw_from_R(R_obs)], axis=1)
    edges["weight"] = 1.0
    ids = sorted(set(i.tolist()) | set(j.tolist()))
    doc = TagGraph(anchor_id=0, tags=ids, dropped=[], n_components=1, weak_links=[])
    return edges, doc, make_T(R, t)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tags", type=int, default=50)
    ap.add_argument("--edges", type=int, default=20_000)
    args = ap.parse_args()
    edges, g, truth = graph(args.tags, args.edges)
    obs = pd.DataFrame({"tag_id": edges["tag_i"], "size_m": 0.16})
    times, out = [], None
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        out = optimize.run(edges, g, obs, optimize.Params())
        times.append(time.perf_counter() - t0)
    assert out is not None
    tm = out["tag_map"]
    T = make_T(np.eye(3), tm[POSE[:3]].to_numpy())
    dt, _ = pose_error(T, truth[tm["tag_id"].to_numpy()])
    med = statistics.median(times)
    rep = out["report"]
    print(
        f"optimize {len(g['tags'])} tags / {len(edges)} edges: median {med:.3f} s over "
        f"{args.repeats} runs (min {min(times):.3f}, max {max(times):.3f}); "
        f"target {TARGET_S:.1f} s -> ratio {med / TARGET_S:.2f}"
    )
    print(
        f"  nfev {rep['nfev']}, status {rep['status']}, mean tag position error "
        f"{dt.mean() * 1000:.2f} mm (max {dt.max() * 1000:.2f} mm); "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}"
    )


if __name__ == "__main__":
    main()
