"""Association with the reference and the quantities a path tracker steers on (issue 28).

Eq. 3.12 takes the nearest reference sample over the whole path. Where the path crosses or comes
close to itself (a figure eight, an "exclamation" shape) the nearest sample can lie on the other
branch, and D and phi jump (phi ≈ ±90° at a right-angle crossing). ``progress`` association
follows the path instead: the nearest sample within a window of arc length around the previous
match — ``search_back_m`` behind, ``search_ahead_m`` ahead (forward-biased: a robot drives on) —
and re-acquires over the whole path (Eq. 3.12) when the window's match is farther than ``lost_m``
or more than ``reacquire_m`` farther than the nearest sample elsewhere. A closed reference (its
ends within ``reacquire_m``) is a loop: the window runs on from its end to its start.
``nearest`` is Eq. 3.12.

Given the matched sample ``k*`` the tracker also gives, in the plane (u, v) of
:mod:`tagtrail.geometry.reference_path`:

- ``cross_track_m``: the signed distance to the nearest point of the two segments beside ``k*``,
  positive when the query lies to the left of the direction of travel seen from the plane's
  normal n = e1 × e2 (counter-clockwise about n, as headings are measured): ``(d × (q − p))·n``
  for the segment direction d and the nearest point p. Example: plane ``xy`` (n = +z, seen from
  above), a path along +x, a query at y = +0.04 → +0.04 m;
- ``progress_m``: the arc length of that nearest point along the reference polyline;
- ``curvature_1pm``: the signed curvature (1/m, > 0 turning left, as above) of the path there —
  the Menger curvature of the points ``curvature_window_m`` behind and ahead along the path
  (computed per sample once, interpolated), so that a noisy recording does not give noisy
  curvature;
- the lookahead point ``lookahead_m`` ahead of the match along the path (the path's end at most);
- ``lost``: no reference sample within ``lost_m``, or the association re-acquired (jumped) at
  this pose.

:class:`PathTracker` keeps the previous match (the state of ``progress``) and answers one pose
at a time; the offline report stage and the live node both call :meth:`PathTracker.track`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.pathindex import SUB, _boxes, _lower_bound
from tagtrail.geometry.reference_path import ReferencePath

Association = Literal["progress", "nearest"]
ASSOCIATIONS: tuple[str, ...] = ("progress", "nearest")
_BRUTE_WINDOW = 2048  # windows up to this many samples are scanned whole


@dataclass(frozen=True)
class TrackParams:
    """Association and tracker settings (lengths in m); see the module docstring."""

    association: Association = "progress"
    lookahead_m: float = 0.3
    search_back_m: float = 0.2
    search_ahead_m: float = 1.0
    reacquire_m: float = 0.25
    lost_m: float = 0.5
    curvature_window_m: float = 0.1


class Track(NamedTuple):
    """One pose against the reference (angles in rad, lengths in m, planar (u, v))."""

    ref_idx: int  # k*: the matched reference sample
    distance_m: float  # D = |p_q − p_ref[k*]| (Eq. 3.13)
    phi_rad: float  # wrap(θq − θref[k*]) (Eq. 3.15)
    ref_heading_rad: float  # θref[k*] (Eq. 3.14)
    cross_track_m: float
    progress_m: float
    curvature_1pm: float
    lookahead_u: float
    lookahead_v: float
    lookahead_seg: int  # the lookahead point lies on segment [j, j+1] …
    lookahead_t: float  # … at this fraction of it
    lost: bool


def _wrap(a: float) -> float:
    return math.pi - (math.pi - a) % (2.0 * math.pi)


def arc_length(uv: F64) -> F64:
    """Cumulative arc length ``(N,)`` (m) of a polyline ``uv (N, 2)`` (m), 0 at the first sample."""
    seg = np.hypot(*np.diff(uv, axis=0).T)
    return np.concatenate([[0.0], np.cumsum(seg)])


def point_at(uv: F64, s: F64, at_m: F64) -> F64:
    """Points ``(M, 2)`` of the polyline ``uv (N, 2)`` (arc lengths ``s (N,)``) at arc lengths
    ``at_m (M,)`` (clamped to the path)."""
    return np.stack([np.interp(at_m, s, uv[:, 0]), np.interp(at_m, s, uv[:, 1])], axis=1)


def path_curvature(uv: F64, s: F64, window_m: float) -> F64:
    """Signed curvature ``(N,)`` (1/m, > 0 turning counter-clockwise in (u, v)) at each sample:
    the Menger curvature ``2 (b − a) × (c − b) / (|b − a| |c − b| |c − a|)`` of the path's points
    ``window_m`` behind (a), at (b) and ahead (c) along the path; near the ends the window is
    shifted inside the path; 0 on a path shorter than two windows."""
    total = float(s[-1])
    if total < 2 * window_m or window_m <= 0:
        return np.zeros(len(uv))
    mid = np.clip(s, window_m, total - window_m)
    a, b, c = (point_at(uv, s, mid + d) for d in (-window_m, 0.0, window_m))
    ab, bc, ac = b - a, c - b, c - a
    cross = ab[:, 0] * bc[:, 1] - ab[:, 1] * bc[:, 0]
    den = np.hypot(*ab.T) * np.hypot(*bc.T) * np.hypot(*ac.T)
    kappa: F64 = np.divide(2.0 * cross, den, out=np.zeros(len(uv)), where=den > 1e-15)
    return kappa


class PathTracker:
    """Progress-aware (or Eq. 3.12) association and tracker quantities, one pose at a time.

    ``path``: the :class:`ReferencePath`; ``params``: :class:`TrackParams`. Holds the previous
    match (``progress``), so one tracker follows one pose stream; :meth:`reset` starts over.
    """

    def __init__(self, path: ReferencePath, params: TrackParams | None = None) -> None:
        self.path = path
        self.params = params or TrackParams()
        self.s = arc_length(path.uv)
        self.curvature = path_curvature(path.uv, self.s, self.params.curvature_window_m)
        self._s = self.s.tolist()
        self._seg_len = np.sqrt(path.seg_len2).tolist()
        self._uv = path.uv.tolist()
        self._prev: int | None = None
        self._boxes: tuple[F64, ...] | None = None  # built on the first long window
        self._in_sub = np.arange(SUB)
        # a loop (ends within reacquire_m): progress goes on from the end to the start
        self.closed = bool(np.hypot(*(path.uv[-1] - path.uv[0])) <= self.params.reacquire_m)

    def reset(self) -> None:
        """Forget the previous match: the next pose is associated over the whole path."""
        self._prev = None

    def associate(self, u: float, v: float) -> tuple[int, float, bool]:
        """``(k*, D (m), re-acquired)`` for the planar point ``(u, v)`` (m): ``nearest`` =
        Eq. 3.12; ``progress`` = the nearest sample in the window around the previous match, or
        over the whole path (re-acquired) when that one is lost or far (module docstring)."""
        p = self.params
        if p.association == "nearest" or self._prev is None:
            d, k = self.path.nearest_sample(u, v)
            self._prev = k
            return k, d, False
        s0 = self._s[self._prev]
        lo = int(np.searchsorted(self.s, s0 - p.search_back_m, "left"))
        hi = int(np.searchsorted(self.s, s0 + p.search_ahead_m, "right"))
        lo, hi = min(lo, self._prev), max(hi, self._prev + 1)
        d2, k = self._nearest_in(u, v, lo, hi, self._prev)
        over = s0 + p.search_ahead_m - self._s[-1]
        if over > 0 and self.closed and lo > 0:  # a loop: the window goes on from the start
            wrap = min(int(np.searchsorted(self.s, over, "right")), lo)
            d2w, kw = self._nearest_in(u, v, 0, wrap, 0) if wrap > 0 else (math.inf, 0)
            if d2w < d2:  # a tie keeps this lap's end before the next lap's start
                d2, k = d2w, kw
        d = math.sqrt(d2)
        again = False
        if d > p.reacquire_m:  # else no sample elsewhere can be reacquire_m nearer
            dg, kg = self.path.nearest_sample(u, v)
            if d > p.lost_m or d - dg > p.reacquire_m:
                k, d, again = kg, dg, kg != k
        self._prev = k
        return k, d, again

    def _nearest_in(self, u: float, v: float, lo: int, hi: int, hint: int) -> tuple[float, int]:
        """``(D², k)`` of the sample nearest ``(u, v)`` among ``lo … hi−1`` (ties → the lowest
        index); ``hint`` (in the range) bounds the answer. Long ranges (a dense reference) scan
        only the runs of ``SUB`` samples whose bounding box can beat the hint (exact)."""
        path = self.path
        if hi - lo <= _BRUTE_WINDOW:
            d2 = path._u[lo:hi] - u
            dv = path._v[lo:hi] - v
            d2 *= d2
            dv *= dv
            d2 += dv
            j = int(d2.argmin())
            return float(d2[j]), lo + j
        if self._boxes is None:
            n = len(path._u)
            pad = -(-n // SUB) * SUB
            pu, pv = np.full(pad, np.inf), np.full(pad, np.inf)
            pu[:n], pv[:n] = path._u, path._v
            self._boxes = _boxes(pu, pv, SUB)
        hu, hv = self._uv[hint]
        ub = (hu - u) ** 2 + (hv - v) ** 2
        ub += ub * 1e-9 + 1e-300  # the boxes' rounding must never exclude the answer
        b0, b1 = lo // SUB, (hi - 1) // SUB + 1
        lb = _lower_bound(tuple(b[b0:b1] for b in self._boxes), u, v)
        runs = (lb <= ub).nonzero()[0] + b0
        idx = (runs[:, None] * SUB + self._in_sub).ravel()  # ascending
        idx = idx[(idx >= lo) & (idx < hi)]
        d2 = path._u[idx] - u
        dv = path._v[idx] - v
        d2 *= d2
        dv *= dv
        d2 += dv
        j = int(d2.argmin())
        return float(d2[j]), int(idx[j])

    def track(self, u: float, v: float, heading_rad: float, k: int | None = None) -> Track:
        """The pose at ``(u, v)`` (m) with heading ``heading_rad`` against the reference:
        associated by :meth:`associate`, or with the sample ``k`` when given (the offline
        batch of Eq. 3.12)."""
        again = False
        if k is None:
            k, d, again = self.associate(u, v)
        else:
            ru, rv = self._uv[k]
            d = math.hypot(u - ru, v - rv)
            self._prev = k
        href = float(self.path.heading_rad[k])
        j, t, cross = self._nearest_on_segments(u, v, (k - 1, k), href, k)
        return self._track(
            k, d, _wrap(heading_rad - href), href, j, t, cross, again or d > self.params.lost_m
        )

    def track_segment(self, u: float, v: float, heading_rad: float, seg: int) -> Track:
        """As :meth:`track` for point mode: the match is the nearest point of segment ``seg``
        (``[seg, seg+1]``), D the distance to it, phi against that segment's heading."""
        href = float(self.path.seg_heading_rad[seg])
        j, t, cross = self._nearest_on_segments(u, v, (seg,), href, seg)
        d = abs(cross)
        return self._track(
            seg, d, _wrap(heading_rad - href), href, j, t, cross, d > self.params.lost_m
        )

    def _nearest_on_segments(
        self, u: float, v: float, segs: tuple[int, ...], href: float, k: int
    ) -> tuple[int, float, float]:
        """``(segment, fraction along it, signed distance)`` of the nearest point of the
        non-degenerate segments ``segs``; with none, the sample ``k`` itself (side by the
        heading ``href``)."""
        best: tuple[float, int, float, float] | None = None
        n_seg = len(self._seg_len)
        for j in segs:
            if not 0 <= j < n_seg or self._seg_len[j] <= 1e-12:
                continue
            (au, av), (bu, bv) = self._uv[j], self._uv[j + 1]
            du, dv = bu - au, bv - av
            t = ((u - au) * du + (v - av) * dv) / (du * du + dv * dv)
            t = min(1.0, max(0.0, t))
            qu, qv = u - (au + t * du), v - (av + t * dv)
            dist = math.hypot(qu, qv)
            side = du * qv - dv * qu  # (d × (q − p))·n
            signed = math.copysign(dist, side) if dist > 0 else 0.0
            if best is None or dist < best[0]:
                best = (dist, j, t, signed)
        if best is None:
            ru, rv = self._uv[k]
            side = math.cos(href) * (v - rv) - math.sin(href) * (u - ru)
            dist = math.hypot(u - ru, v - rv)
            return min(k, n_seg - 1), float(k > n_seg - 1), math.copysign(dist, side)
        return best[1], best[2], best[3]

    def _track(
        self, k: int, d: float, phi: float, href: float, j: int, t: float, cross: float, lost: bool
    ) -> Track:
        progress = self._s[j] + t * self._seg_len[j]
        curv = float(np.interp(progress, self.s, self.curvature))
        la_s = min(progress + self.params.lookahead_m, self._s[-1])
        lj = int(np.searchsorted(self.s, la_s, "right")) - 1
        lj = min(max(lj, 0), len(self._seg_len) - 1)
        seg = self._seg_len[lj]
        lt = min(1.0, max(0.0, (la_s - self._s[lj]) / seg)) if seg > 1e-12 else 0.0
        (au, av), (bu, bv) = self._uv[lj], self._uv[lj + 1]
        return Track(
            k,
            d,
            phi,
            href,
            cross,
            progress,
            curv,
            au + lt * (bu - au),
            av + lt * (bv - av),
            lj,
            lt,
            lost,
        )
