"""Planes, headings and ReferencePath against hand computations (Eqs. 3.12–3.15)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tagtrail.errors import DataError
from tagtrail.geometry.reference_path import (
    ReferencePath,
    capture_radius_p95,
    circular_mean,
    path_headings,
    reduce_to_point,
    resolve_plane,
    wrap_angle,
)

XZ = resolve_plane("xz")


def cam_R(heading_deg: float) -> np.ndarray:
    """world_R_cam of an upright camera (y = world −y, down) with that heading in the xz plane."""
    h = math.radians(heading_deg)
    z = np.array([math.cos(h), 0.0, math.sin(h)])  # θ = atan2(f·z, f·x)
    y = np.array([0.0, -1.0, 0.0])
    return np.stack([np.cross(y, z), y, z], axis=1)


def xz_points(uv: list[tuple[float, float]], y: float = 0.03) -> np.ndarray:
    return np.array([[u, y, v] for u, v in uv])


def test_fixed_planes_are_right_handed() -> None:
    for name, (e1, e2) in {"xz": (0, 2), "xy": (0, 1), "yz": (1, 2)}.items():
        p = resolve_plane(name)
        np.testing.assert_array_equal(p.e1, np.eye(3)[e1])
        np.testing.assert_array_equal(p.e2, np.eye(3)[e2])
        np.testing.assert_allclose(p.n, np.cross(p.e1, p.e2))
    np.testing.assert_array_equal(XZ.n, [0.0, -1.0, 0.0])
    with pytest.raises(DataError, match="unknown plane"):
        resolve_plane("zx")


def test_wrap_angle_interval() -> None:
    a = np.array([0.0, math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 2 * math.pi, 1.0, -4.0])
    w = wrap_angle(a)
    assert w[1] == pytest.approx(math.pi) and w[2] == pytest.approx(math.pi)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)


def test_heading_of_camera() -> None:
    for h in (-179.0, -90.0, 0.0, 37.5, 180.0):
        assert math.degrees(XZ.heading(cam_R(h))) == pytest.approx(h if h != 180 else 180.0)


def test_straight_line() -> None:
    path = ReferencePath(xz_points([(0.1 * k, 0.0) for k in range(11)]), XZ)
    m = path.query(xz_points([(0.33, 0.2)]), cam_R(30.0)[None])
    assert m.ref_idx[0] == 3
    assert m.distance_m[0] == pytest.approx(math.hypot(0.03, 0.2), abs=1e-9)
    assert math.degrees(m.phi_rad[0]) == pytest.approx(30.0, abs=1e-9)
    np.testing.assert_allclose(m.ref_uv[0], [0.3, 0.0], atol=1e-12)


def test_circle_centred_difference_is_the_tangent() -> None:
    a = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    path = ReferencePath(xz_points(list(zip(np.cos(a), np.sin(a), strict=True))), XZ)
    # symmetric chord p[k+1] - p[k-1] is parallel to the tangent at a_k (Eq. 3.14)
    np.testing.assert_allclose(
        np.cos(path.heading_rad[1:-1] - (a[1:-1] + np.pi / 2)), 1.0, atol=1e-12
    )
    k = 7
    q = xz_points([(1.3 * np.cos(a[k]), 1.3 * np.sin(a[k]))])
    m = path.query(q, cam_R(100.0)[None])
    assert m.ref_idx[0] == k
    assert m.distance_m[0] == pytest.approx(0.3, abs=1e-9)
    expected = math.remainder(math.radians(100.0) - (a[k] + math.pi / 2), 2 * math.pi)
    assert m.phi_rad[0] == pytest.approx(expected, abs=1e-9)


def test_path_crossing_plus_minus_180() -> None:
    # heading of the path ≈ −π + 0.01 (moving along −x, slightly towards −z)
    path = ReferencePath(xz_points([(-0.1 * k, -0.001 * k) for k in range(10)]), XZ)
    theta_ref = math.atan2(-0.002, -0.2)
    assert path.heading_rad[4] == pytest.approx(theta_ref, abs=1e-12)
    q_heading = 179.0
    m = path.query(xz_points([(-0.4, 0.0)]), cam_R(q_heading)[None])
    expected = math.radians(q_heading) - theta_ref - 2 * math.pi  # wrapped by hand
    assert -math.pi < expected <= math.pi
    assert m.phi_rad[0] == pytest.approx(expected, abs=1e-9)
    assert abs(math.degrees(m.phi_rad[0])) < 2.0


def test_ends_of_the_path_use_one_sided_differences() -> None:
    uv = [(0.0, 0.0), (1.0, 0.0), (2.0, 1.0)]
    np.testing.assert_allclose(path_headings(uv), [0.0, math.atan2(1, 2), math.pi / 4])
    path = ReferencePath(xz_points(uv), XZ)
    m = path.query(xz_points([(2.5, 1.2), (-0.4, 0.1)]), np.stack([cam_R(50.0), cam_R(-10.0)]))
    np.testing.assert_array_equal(m.ref_idx, [2, 0])
    np.testing.assert_allclose(
        m.distance_m, [math.hypot(0.5, 0.2), math.hypot(0.4, 0.1)], atol=1e-9
    )
    np.testing.assert_allclose(np.degrees(m.phi_rad), [5.0, -10.0], atol=1e-9)


def test_query_exactly_on_a_sample() -> None:
    path = ReferencePath(xz_points([(0.0, 0.0), (1.0, 0.0), (2.0, 1.0)]), XZ)
    m = path.query(xz_points([(1.0, 0.0)]), cam_R(0.0)[None])
    assert m.ref_idx[0] == 1 and m.distance_m[0] == pytest.approx(0.0, abs=1e-12)
    assert m.phi_rad[0] == pytest.approx(-math.atan2(1, 2), abs=1e-9)


def test_pauses_keep_the_previous_heading() -> None:
    h = path_headings([(0, 0), (0, 0), (1, 0), (1, 0), (1, 0), (1, 1)])
    np.testing.assert_allclose(h, [0, 0, 0, 0, math.pi / 2, math.pi / 2])
    np.testing.assert_array_equal(path_headings([(1, 1), (1, 1)]), [0.0, 0.0])


def test_point_mode_between_two_samples() -> None:
    path = ReferencePath(xz_points([(0.0, 0.0), (2.0, 0.0), (4.0, 2.0)]), XZ)
    m = path.query_polyline([[1.0, 0.3]], [math.radians(20.0)])
    assert m.ref_idx[0] == 0
    assert m.distance_m[0] == pytest.approx(0.3, abs=1e-9)  # the nearest sample is 1.04 m away
    np.testing.assert_allclose(m.ref_uv[0], [1.0, 0.0], atol=1e-12)
    assert math.degrees(m.phi_rad[0]) == pytest.approx(20.0, abs=1e-9)
    m = path.query_polyline([[2.0, 2.0]], [0.0])  # projects onto the sloped segment at (3, 1)
    assert m.ref_idx[0] == 1
    assert m.distance_m[0] == pytest.approx(math.sqrt(2.0), abs=1e-9)
    assert math.degrees(m.phi_rad[0]) == pytest.approx(-45.0, abs=1e-9)
    assert path.query_uv([[1.0, 0.3]], [0.0]).distance_m[0] == pytest.approx(math.hypot(1, 0.3))


def test_point_mode_vertex_tie_goes_to_the_earlier_segment() -> None:
    path = ReferencePath(xz_points([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]), XZ)
    m = path.query_polyline([[1.5, -0.5]], [0.0])
    assert m.ref_idx[0] == 0 and m.ref_heading_rad[0] == 0.0
    assert m.distance_m[0] == pytest.approx(math.hypot(0.5, 0.5), abs=1e-12)


def test_batch_single_and_polyline_chunks_agree() -> None:
    rng = np.random.default_rng(3)
    a = np.cumsum(rng.normal(0, 0.2, 300))
    ref = xz_points(
        list(zip(np.cumsum(np.cos(a)) * 0.05, np.cumsum(np.sin(a)) * 0.05, strict=True))
    )
    path = ReferencePath(ref, XZ)
    P = ref[rng.integers(0, 300, 50)] + rng.normal(0, 0.3, (50, 3))
    R = np.stack([cam_R(h) for h in rng.uniform(-180, 180, 50)])
    m = path.query(P, R)
    for i in range(50):
        one = path.query_one(P[i], R[i])
        assert one.ref_idx == m.ref_idx[i]
        assert one.distance_m == pytest.approx(m.distance_m[i], abs=1e-12)
        assert one.phi_rad == pytest.approx(m.phi_rad[i], abs=1e-12)
        assert (one.ref_u, one.ref_v) == tuple(m.ref_uv[i])
    # brute force over all samples (Eq. 3.12) and over every segment
    d = np.linalg.norm(path.uv[None] - m.query_uv[:, None], axis=2)
    np.testing.assert_allclose(m.distance_m, d.min(axis=1), atol=1e-12)
    poly = path.query_polyline(m.query_uv, m.query_heading_rad)
    for i in range(0, 50, 7):
        single = path.query_polyline(m.query_uv[i], m.query_heading_rad[i])
        assert single.ref_idx[0] == poly.ref_idx[i]
        assert single.distance_m[0] == pytest.approx(poly.distance_m[i], abs=1e-12)
    assert np.all(poly.distance_m <= m.distance_m + 1e-12)


def test_degenerate_reference_raises() -> None:
    with pytest.raises(DataError, match="2 distinct"):
        ReferencePath(xz_points([(1.0, 1.0)]), XZ)
    with pytest.raises(DataError, match="2 distinct"):
        ReferencePath(xz_points([(1.0, 1.0)] * 5), XZ)


def test_auto_plane_recovers_a_tilted_floor() -> None:
    rng = np.random.default_rng(0)
    tilt = np.array([0.2, -1.0, 0.1]) / np.linalg.norm([0.2, -1.0, 0.1])  # the floor's "down"
    b1 = np.cross(tilt, [0.0, 0.0, 1.0])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(tilt, b1)
    t = rng.uniform(0, 2 * np.pi, 80)
    P = np.outer(2 * np.cos(t), b1) + np.outer(np.sin(t), b2)
    P += 0.002 * rng.normal(size=(80, 1)) * tilt
    R = np.stack([np.stack([np.cross(tilt, b1), tilt, b1], axis=1)] * 80)  # y axis = down
    p = resolve_plane("auto", P, R)
    assert p.n @ tilt > 0.9999
    np.testing.assert_allclose(np.cross(p.e1, p.e2), p.n, atol=1e-12)
    x_in_plane = np.eye(3)[0] - (np.eye(3)[0] @ p.n) * p.n
    np.testing.assert_allclose(p.e1, x_in_plane / np.linalg.norm(x_in_plane), atol=1e-12)
    # a straight run defines no plane: the normal falls back to the cameras' mean y axis
    line = np.outer(np.linspace(0, 3, 20), b1)
    np.testing.assert_allclose(resolve_plane("auto", line, R[:20]).n, tilt, atol=1e-12)


def test_auto_plane_in_a_z_up_world() -> None:
    # SPEC: e2 = n × e1 with n = "down" = −z, so auto gives (x, −y) there (use xy for yaw)
    t = np.linspace(0, 2 * np.pi, 40)
    P = np.stack([np.cos(t), np.sin(t), np.full_like(t, 0.2)], axis=1)
    R = np.stack([np.stack([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]], axis=1)] * 40)
    p = resolve_plane("auto", P, R)
    np.testing.assert_allclose([p.e1, p.e2, p.n], [[1, 0, 0], [0, -1, 0], [0, 0, -1]], atol=1e-9)


def test_reduce_to_point_and_capture_radius() -> None:
    uv = np.array([[0.0, 0.0], [1.0, 0.1], [0.2, 0.0], [0.1, 0.05], [5.0, 5.0]])
    med, h, i = reduce_to_point(uv, np.radians([179.0, -179.0, 178.0, -178.0, 180.0]))
    np.testing.assert_allclose(med, [0.2, 0.05])
    assert abs(math.remainder(h - math.pi, 2 * math.pi)) < 1e-12  # circular mean across ±180°
    assert i == 2
    assert circular_mean(np.radians([10.0, 30.0])) == pytest.approx(math.radians(20.0))
    ring = np.stack([np.cos(np.arange(100)), np.sin(np.arange(100))], axis=1) * 0.15 + 3.0
    assert capture_radius_p95(ring) == pytest.approx(0.15, abs=1e-3)
    assert capture_radius_p95(ring[:1]) == 0.0


def test_degenerate_inputs_raise_no_runtime_warning() -> None:
    """Empty, non-finite, pausing and straight references: a clear DataError or a finite result,
    never a numpy RuntimeWarning (they reached users' stderr)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails the test
        with pytest.raises(DataError, match="has no poses"):
            resolve_plane("auto", np.zeros((0, 3)), np.zeros((0, 3, 3)))
        with pytest.raises(DataError, match="non-finite poses"):
            resolve_plane("auto", np.full((4, 3), np.nan), np.stack([cam_R(0)] * 4))
        with pytest.raises(DataError, match="circular mean of no angles"):
            circular_mean([])
        with pytest.raises(DataError, match="non-finite positions"):
            ReferencePath(xz_points([(0.0, 0.0), (math.nan, 1.0), (1.0, 1.0)]), XZ)
        still = xz_points([(1.0, 1.0)] * 6)  # a parked run: no plane, no heading
        assert resolve_plane("auto", still, np.stack([cam_R(30)] * 6)).n @ [0, -1, 0] > 0.9999
        # a reference that pauses: zero-length segments, repeated samples
        path = ReferencePath(xz_points([(0, 0), (0, 0), (1, 0), (1, 0), (1, 0), (1, 1)]), XZ)
        assert np.isfinite(path.heading_rad).all()
        poly = path.query_polyline([[0.0, 0.0], [1.0, 0.0], [0.5, 0.2]], [0.0, 0.0, 0.0])
        assert np.isfinite(poly.distance_m).all() and np.isfinite(poly.ref_heading_rad).all()
        np.testing.assert_allclose(poly.distance_m, [0.0, 0.0, 0.2], atol=1e-12)
        m = path.query_uv(np.zeros((0, 2)), np.zeros(0))
        assert len(m.ref_idx) == 0
        assert path_headings(np.zeros((0, 2))).shape == (0,)
