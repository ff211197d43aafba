"""Exact nearest reference sample for one query, fast on long paths (Eq. 3.12).

A k-d tree over the samples of a *path* is slow for queries on the concave side of a loop —
the usual place of a robot that drifted inside its reference loop: the boxes of the tree's inner
nodes span arcs and reach towards the loop's centre, so little is pruned (scipy's ``cKDTree``,
1,000,000 samples on a 3 × 2 m ellipse: 40 µs for a query outside it, 0.9 ms at 0.3 m inside,
10 ms at its centre). :class:`PathIndex` uses the path's order instead: blocks of consecutive
samples (compact along a trajectory), each bounded by its chord (first → last sample) and the
farthest any of its samples lies from that chord — a tight bound on a smooth path, unlike a box
— and sub-blocks of 32 samples bounded by their boxes. A query takes as upper bound the nearer of
the previous answer's sample (live poses are consecutive) and the middle sample of the block with
the nearest chord, keeps the blocks — and, when there are many, the sub-blocks — whose bound does
not exceed it, and scans their samples in one pass. The result is the brute-force ``argmin``
over every sample (the same ``du² + dv²``; ties → the lowest index).

A query is ~30 numpy calls on arrays of ~√N elements; the fixed cost of a call (~0.5 µs, a few
µs when the live node wakes up with cold caches) is a large part of it, so the block test is
done on squared distances (``dist(q, chord)² ≤ (√ub + e)²``: no per-block square root) and the
slower calls (``np.clip``, Python-float operands) are avoided.

It answers ``query((u, v)) -> (distance, index)`` like the tree it stands in for
(:class:`~tagtrail.geometry.reference_path.ReferencePath` ``.tree``).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tagtrail.geometry.arrays import F64

SUB = 32  # samples per sub-block
DIRECT = 4  # up to this many candidate blocks, scan them whole (fewer numpy calls)


def _boxes(u: NDArray[np.float64], v: NDArray[np.float64], size: int) -> tuple[F64, ...]:
    """``(u_lo, v_lo, −u_hi, −v_hi)``, each ``(n_boxes,)``, of consecutive runs of ``size``
    samples (an empty run: +inf everywhere, never a candidate)."""
    U, V = u.reshape(-1, size), v.reshape(-1, size)
    fin = np.isfinite(U)
    return tuple(np.ascontiguousarray(np.where(fin, X, np.inf).min(1)) for X in (U, V, -U, -V))


def _chords(u: NDArray[np.float64], v: NDArray[np.float64], n: int, size: int) -> tuple[F64, ...]:
    """Per block of ``size`` samples: its chord (first → last sample) ``a_u, a_v, d_u, d_v``,
    ``1/|d|²`` (0 for a point) and ``e`` = the farthest any of its samples lies from the chord."""
    starts = np.arange(0, len(u), size)
    last = np.minimum(starts + size, n) - 1
    a_u, a_v = u[starts], v[starts]
    d_u, d_v = u[last] - a_u, v[last] - a_v
    len2 = d_u * d_u + d_v * d_v
    inv = np.divide(1.0, len2, out=np.zeros_like(len2), where=len2 > 0)
    U, V = u.reshape(-1, size), v.reshape(-1, size)
    pu, pv = U - a_u[:, None], V - a_v[:, None]
    with np.errstate(invalid="ignore"):  # the +inf padding of the last block
        t = np.clip((pu * d_u[:, None] + pv * d_v[:, None]) * inv[:, None], 0.0, 1.0)
        dev = np.hypot(pu - t * d_u[:, None], pv - t * d_v[:, None])
    e = np.where(np.isfinite(U), dev, 0.0).max(axis=1)
    return a_u, a_v, d_u, d_v, inv, e * (1 + 1e-12) + 1e-12


def _chord_d2(ch: tuple[F64, ...], u: F64, v: F64) -> F64:
    """Squared distance from ``(u, v)`` (0-d arrays: numpy calls with Python floats are slower)
    to the chord of each block."""
    a_u, a_v, d_u, d_v, inv, _ = ch
    qu, qv = u - a_u, v - a_v
    t = qu * d_u
    t += qv * d_v
    t *= inv
    np.maximum(t, 0.0, out=t)  # = np.clip, which costs several µs more on arrays this small
    np.minimum(t, 1.0, out=t)
    qu -= t * d_u
    qv -= t * d_v
    qu *= qu
    qv *= qv
    qu += qv
    return qu


def _lower_bound(box: tuple[F64, ...], u: float, v: float) -> F64:
    """Squared distance from ``(u, v)`` to each box (0 inside)."""
    lo_u, lo_v, nhi_u, nhi_v = box
    du = np.maximum(lo_u - u, nhi_u + u)
    np.maximum(du, 0.0, out=du)
    dv = np.maximum(lo_v - v, nhi_v + v)
    np.maximum(dv, 0.0, out=dv)
    du *= du
    dv *= dv
    du += dv
    return du


class PathIndex:
    """Nearest of ``uv (N, 2)`` (m) samples; blocks of ``block`` consecutive samples (a
    multiple of 32; default ≈ √N). Keeps the last answer as a starting bound for the next query
    (consecutive live poses are close), so it is not thread-safe."""

    def __init__(self, uv: ArrayLike, block: int | None = None) -> None:
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        n = len(uv)
        if n == 0:
            raise ValueError("PathIndex needs at least one sample")
        b = block or math.isqrt(n)
        self.block = max(SUB, -(-int(b) // SUB) * SUB)
        self.n = n
        padded = -(-n // self.block) * self.block
        self._u = np.full(padded, np.inf)
        self._v = np.full(padded, np.inf)
        self._u[:n], self._v[:n] = uv[:, 0], uv[:, 1]
        self._chord1 = _chords(self._u, self._v, n, self.block)
        self._box2 = _boxes(self._u, self._v, SUB)
        self._U = self._u.reshape(-1, self.block)
        self._V = self._v.reshape(-1, self.block)
        self._subs_of = np.arange(padded // SUB).reshape(-1, self.block // SUB)
        self._in_sub = np.arange(SUB)
        self._hint = 0

    def __len__(self) -> int:
        return self.n

    def query_one(self, u: float, v: float) -> tuple[float, int]:
        """``(distance (m), index)`` of the sample nearest ``(u, v)``."""
        qu, qv = np.array(u), np.array(v)
        c2 = _chord_d2(self._chord1, qu, qv)
        # an upper bound of the answer: the nearer of the previous answer's sample (consecutive
        # poses are close) and the middle sample of the block with the nearest chord
        ub = math.inf
        for h in (self._hint, min(int(c2.argmin()) * self.block + self.block // 2, self.n - 1)):
            du, dv = float(self._u[h]) - u, float(self._v[h]) - v
            ub = min(ub, du * du + dv * dv)
        ub += ub * 1e-9 + 1e-300  # slack: the bounds' rounding must never exclude the answer
        # a block may hold a sample within √ub if its chord is within √ub + e (squared: no sqrt
        # per block)
        lim = self._chord1[5] + math.sqrt(ub)
        lim *= lim
        blocks = (c2 <= lim).nonzero()[0]
        if len(blocks) <= DIRECT:  # few candidate blocks: scan all their samples at once
            d2, pv = self._U[blocks], self._V[blocks]  # (b, block) copies, ascending indices
            d2 -= qu
            pv -= qv
            d2 *= d2
            pv *= pv
            d2 += pv
            j = int(d2.argmin())  # first minimum: ties → lowest index
            k = int(blocks[j // self.block]) * self.block + j % self.block
        else:
            subs = self._subs_of[blocks].ravel()
            subs = subs[_lower_bound(tuple(b[subs] for b in self._box2), u, v) <= ub]
            idx = (subs[:, None] * SUB + self._in_sub).ravel()  # ascending
            d2, pv = self._u[idx], self._v[idx]
            d2 -= qu
            pv -= qv
            d2 *= d2
            pv *= pv
            d2 += pv
            j = int(d2.argmin())
            k = int(idx[j])
        self._hint = k
        return math.sqrt(float(d2.flat[j])), k

    def query(self, x: ArrayLike) -> tuple[float | NDArray[np.float64], int | NDArray[np.int64]]:
        """``cKDTree.query`` for one point ``(2,)`` or a batch ``(M, 2)``."""
        q = np.asarray(x, dtype=np.float64)
        if q.ndim == 1:
            return self.query_one(float(q[0]), float(q[1]))
        res = [self.query_one(float(a), float(b)) for a, b in q.reshape(-1, 2).tolist()]
        return (np.array([r[0] for r in res]), np.array([r[1] for r in res], dtype=np.int64))
