"""Progress-aware association and the path tracker's quantities (geometry.association).

The reference is a lemniscate of Bernoulli built here from its analytic formula (not tagtrail
code): ``x = a cos t / (1 + sin² t)``, ``y = a sin t cos t / (1 + sin² t)``, through the origin
twice, its branches crossing there at right angles. Its signed curvature comes from the
analytic derivatives (``(x' y'' − y' x'') / |v|³``), not from tagtrail.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tagtrail.geometry.association import PathTracker, TrackParams, arc_length
from tagtrail.geometry.reference_path import ReferencePath, resolve_plane

A_M = 1.5  # the lemniscate's half-width


def lemniscate(t: np.ndarray, left_m: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points ``(N, 2)`` ``left_m`` to the left of the lemniscate at parameters ``t``, the path's
    heading there (rad) and its signed curvature (1/m, > 0 turning left), all analytic."""
    s, c = np.sin(t), np.cos(t)
    den = 1 + s * s
    x, y = A_M * c / den, A_M * s * c / den
    dx = -A_M * s * (1 + s * s + 2 * c * c) / den**2
    dy = A_M * ((c * c - s * s) * den - 2 * s * s * c * c) / den**2
    speed = np.hypot(dx, dy)
    nx, ny = -dy / speed, dx / speed  # the left normal (counter-clockwise)
    # signed curvature from the analytic derivatives: (x' y'' − y' x'') / |v|³, with the
    # second derivatives by a centred difference of the analytic first ones
    h = 1e-6
    s2, c2 = np.sin(t + h), np.cos(t + h)
    den2 = 1 + s2 * s2
    dx2 = -A_M * s2 * (1 + s2 * s2 + 2 * c2 * c2) / den2**2
    dy2 = A_M * ((c2 * c2 - s2 * s2) * den2 - 2 * s2 * s2 * c2 * c2) / den2**2
    ddx, ddy = (dx2 - dx) / h, (dy2 - dy) / h
    kappa = (dx * ddy - dy * ddx) / speed**3
    pts = np.column_stack([x + left_m * nx, y + left_m * ny])
    return pts, np.arctan2(dy, dx), kappa


def xy_path(n: int = 2000) -> ReferencePath:
    """The lemniscate as a reference in the world's xy plane (z = 0.1 m)."""
    uv, _, _ = lemniscate(np.linspace(0.0, 2 * np.pi, n))
    return ReferencePath(np.column_stack([uv, np.full(n, 0.1)]), resolve_plane("xy"))


def drive(tracker: PathTracker, left_m: float, m: int = 700) -> list:
    t = np.linspace(0.01, 2 * np.pi - 0.01, m)  # not the reference's samples
    uv, heading, _ = lemniscate(t, left_m)
    return [tracker.track(u, v, h) for (u, v), h in zip(uv.tolist(), heading.tolist(), strict=True)]


def test_figure_eight_progress_follows_the_branch() -> None:
    path = xy_path()
    tracks = drive(PathTracker(path, TrackParams(association="progress")), 0.04)
    phi = np.degrees([tk.phi_rad for tk in tracks])
    cross = np.array([tk.cross_track_m for tk in tracks])
    k = np.array([tk.ref_idx for tk in tracks])
    assert np.abs(phi).max() <= 1.0
    np.testing.assert_allclose(cross, 0.04, atol=1e-3, rtol=0)
    # k* moves forward only and by small steps: never to the other branch at the crossing
    assert (np.diff(k) >= 0).all() and np.diff(k).max() < 20
    assert not any(tk.lost for tk in tracks)


def test_figure_eight_nearest_jumps_branch_at_the_crossing() -> None:
    """Eq. 3.12 reproduces the failure the progress association removes."""
    tracks = drive(PathTracker(xy_path(), TrackParams(association="nearest")), 0.04)
    phi = np.degrees([tk.phi_rad for tk in tracks])
    k = np.array([tk.ref_idx for tk in tracks])
    near_90 = np.abs(np.abs(phi) - 90.0) < 5.0
    assert near_90.sum() >= 2 and (np.diff(k) < 0).any()


@pytest.mark.parametrize("side", [+1, -1])
@pytest.mark.parametrize("plane", ["xy", "xz"])
def test_cross_track_sign_is_left_seen_from_the_normal(plane: str, side: int) -> None:
    """Plane xy (z up, n = +z): left as seen from above is +y. Plane xz (SPEC's original,
    n = −y): left of a path along +x, seen from n, is n × x = +z. A query to the right < 0."""
    pl = resolve_plane(plane)
    s = np.linspace(0.0, 3.0, 301)
    P = np.outer(s, [1.0, 0.0, 0.0])  # along world +x
    path = ReferencePath(P, pl)
    left = np.cross(pl.n, [1.0, 0.0, 0.0])  # n × direction of travel
    q = np.array([1.23, 0.0, 0.0]) + side * 0.05 * left
    u, v = pl.to_uv(q)
    tk = PathTracker(path).track(float(u), float(v), 0.0)
    assert tk.cross_track_m == pytest.approx(side * 0.05, abs=1e-12)
    assert tk.progress_m == pytest.approx(1.23, abs=1e-12)
    if plane == "xz":  # n = −y: left of +x is +z, so a query at z < 0 is to the right
        assert pl.n @ [0, -1, 0] == pytest.approx(1.0) and left @ [0, 0, 1] == pytest.approx(1.0)


def test_curvature_progress_and_lookahead_against_the_formula() -> None:
    path = xy_path(4000)
    tracker = PathTracker(path, TrackParams(lookahead_m=0.3))
    t = np.linspace(0.05, 2 * np.pi - 0.6, 400)
    uv, heading, kappa = lemniscate(t, 0.02)
    s_ref = arc_length(path.uv)
    fine_t = np.linspace(0.0, 2 * np.pi, 200_001)
    fine, _, _ = lemniscate(fine_t)
    fine_s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(fine, axis=0).T))])
    for (u, v), h, kap, ti in zip(uv.tolist(), heading.tolist(), kappa, t, strict=True):
        tk = tracker.track(u, v, h)
        assert tk.curvature_1pm == pytest.approx(kap, abs=0.02 + 0.01 * abs(kap))
        s_true = float(np.interp(ti, fine_t, fine_s))  # arc length of the foot point
        assert tk.progress_m == pytest.approx(s_true, abs=2e-3)
        la_true = np.array([np.interp(s_true + 0.3, fine_s, fine[:, i]) for i in (0, 1)])
        assert math.dist((tk.lookahead_u, tk.lookahead_v), la_true) < 3e-3
    assert s_ref[-1] == pytest.approx(fine_s[-1], rel=1e-5)


def test_lost_and_reacquired() -> None:
    """A pose far from the path is lost; a pose that jumps to another part of the path
    re-acquires there (flagged lost once), then follows it again."""
    s = np.linspace(0.0, 10.0, 1001)
    path = ReferencePath(
        np.column_stack([s, np.zeros_like(s), np.zeros_like(s)]), resolve_plane("xy")
    )
    tr = PathTracker(path, TrackParams(lost_m=0.5, reacquire_m=0.25))
    assert not tr.track(1.0, 0.1, 0.0).lost
    far = tr.track(1.1, 0.9, 0.0)
    assert far.lost and far.distance_m > 0.5
    jump = tr.track(7.0, 0.05, 0.0)  # 6 m ahead: outside the window
    assert jump.lost and jump.ref_idx == 700
    after = tr.track(7.01, 0.05, 0.0)
    assert not after.lost and after.ref_idx == 701


def test_closed_loop_runs_on_from_end_to_start() -> None:
    """A loop driven twice: progress passes from the last sample to the first (no lost)."""
    a = np.linspace(0.0, 2 * np.pi, 629)
    P = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])
    tr = PathTracker(ReferencePath(P, resolve_plane("xy")))
    assert tr.closed
    b = np.linspace(0.0, 4 * np.pi, 900)[1:]
    tracks = [tr.track(1.03 * math.cos(x), 1.03 * math.sin(x), x + math.pi / 2) for x in b]
    assert not any(tk.lost for tk in tracks)
    np.testing.assert_allclose([tk.cross_track_m for tk in tracks], -0.03, atol=1e-4)


def test_long_windows_scan_exactly() -> None:
    """A dense reference (windows of tens of thousands of samples, scanned by bounding boxes of
    runs): the window's nearest sample equals the brute-force argmin over the same samples."""
    rng = np.random.default_rng(3)
    uv, _, _ = lemniscate(np.linspace(0.0, 2 * np.pi, 300_001))
    path = ReferencePath(np.column_stack([uv, np.zeros(len(uv))]), resolve_plane("xy"))
    tr = PathTracker(path)
    for _ in range(200):
        lo = int(rng.integers(0, len(uv) - 50_000))
        hi = lo + int(rng.integers(3000, 50_000))
        hint = int(rng.integers(lo, hi))
        q = uv[int(rng.integers(0, len(uv)))] + rng.normal(0, 0.3, 2)
        d2, k = tr._nearest_in(float(q[0]), float(q[1]), lo, hi, hint)
        brute = ((uv[lo:hi] - q) ** 2).sum(axis=1)
        assert k == lo + int(brute.argmin()) and d2 == pytest.approx(brute.min(), rel=1e-12)
