"""PathIndex = the brute-force argmin (ties → lowest index): random walks, loops (queries at
their centre), out-and-back paths, a parked robot's jitter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tagtrail.geometry.pathindex import PathIndex


def _brute(uv: np.ndarray, q: np.ndarray) -> tuple[float, int]:
    du, dv = uv[:, 0] - q[0], uv[:, 1] - q[1]
    d2 = du * du
    d2 += dv * dv
    k = int(d2.argmin())
    return math.sqrt(float(d2[k])), k


@pytest.mark.parametrize("n", [1, 31, 1000, 20_001])
def test_equals_brute_force(n: int) -> None:
    rng = np.random.default_rng(n)
    walk = np.cumsum(rng.normal(0, 0.01, (n, 2)), axis=0)
    if n > 120:
        walk[100:110] = walk[5]  # repeated samples: ties
    s = np.linspace(0, 2 * np.pi, n, endpoint=False)
    loop = np.c_[1.5 * np.cos(s), np.sin(s)]
    back = np.c_[np.abs(np.linspace(-1, 1, n)), np.zeros(n)]  # out and back: folded blocks
    parked = rng.normal(0, 0.002, (n, 2))  # jitter about one place: chords of nothing
    for uv in (walk, loop, back, parked):
        ix = PathIndex(uv)
        Q = rng.uniform(uv.min(0) - 0.5, uv.max(0) + 0.5, (200, 2))
        Q[:3] = [uv[min(5, n - 1)], uv[-1], uv.mean(0)]  # on samples, at the loop's centre
        for q in Q:
            assert ix.query(q) == _brute(uv, q)
        d, k = ix.query(Q[:4])
        assert [(float(a), int(b)) for a, b in zip(d, k, strict=True)] == [
            _brute(uv, q) for q in Q[:4]
        ]
