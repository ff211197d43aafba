"""se3: round trips, batch vs loop, frame cancellation."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from tagtrail.geometry import se3


def random_T(rng: np.random.Generator, n: int) -> np.ndarray:
    R = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    return se3.make_T(R, rng.normal(size=(n, 3)))


def test_inverse_round_trip_batched() -> None:
    T = random_T(np.random.default_rng(0), 50)
    assert np.allclose(se3.inv(T) @ T, np.eye(4), atol=1e-12)
    assert np.allclose(se3.inv(T), np.linalg.inv(T), atol=1e-12)


def test_frames_cancel() -> None:
    rng = np.random.default_rng(1)
    world_T_tag, cam_T_tag = random_T(rng, 1)[0], random_T(rng, 1)[0]
    world_T_cam = se3.compose(world_T_tag, se3.inv(cam_T_tag))
    p_tag = rng.normal(size=3)
    p_cam = se3.transform_points(cam_T_tag, p_tag)
    assert np.allclose(
        se3.transform_points(world_T_cam, p_cam), se3.transform_points(world_T_tag, p_tag)
    )


def test_quaternion_and_rotvec_round_trips_match_loop() -> None:
    T = random_T(np.random.default_rng(2), 20).reshape(4, 5, 4, 4)
    xyz, q = se3.xyz_quat_from_T(T)
    assert q.shape == (4, 5, 4) and np.all(q[..., 3] >= 0)
    assert np.allclose(se3.T_from_xyz_quat(xyz, q), T, atol=1e-12)
    rv = se3.rotvec_from_R(T[..., :3, :3])
    for i in range(4):
        for j in range(5):
            assert np.allclose(rv[i, j], Rotation.from_matrix(T[i, j, :3, :3]).as_rotvec())
    assert np.allclose(se3.T_from_rotvec_t(rv, xyz), T, atol=1e-12)


def test_pose_error() -> None:
    T = random_T(np.random.default_rng(3), 1)[0]
    d = se3.make_T(Rotation.from_rotvec([0, 0, 0.1]).as_matrix(), [0.3, 0, 0.4])
    dt, dr = se3.pose_error(T @ d, T)
    assert np.isclose(dt, np.linalg.norm(T[:3, :3] @ [0.3, 0, 0.4]))
    assert np.isclose(dr, 0.1)


def test_read_only_inputs_as_loaded_from_parquet() -> None:
    T = random_T(np.random.default_rng(4), 3)
    xyz, q = se3.xyz_quat_from_T(T)
    for a in (T, xyz, q):
        a.setflags(write=False)
    assert np.allclose(se3.T_from_xyz_quat(xyz, q), T)
    assert np.allclose(se3.R_from_rotvec(se3.rotvec_from_R(T[:, :3, :3])), T[:, :3, :3])


def test_one_matrix_quaternion_is_scipys() -> None:
    """``quat_xyzw_of`` (a live pose's, plain floats) gives ``quat_xyzw_from_R``'s quaternion,
    sign included: random rotations, and those where the branch or the sign is decided by
    ties (identity, half turns about axes and diagonals, qw = 0)."""
    from tagtrail.geometry.se3 import R_from_rotvec, quat_xyzw_from_R, quat_xyzw_of

    rng = np.random.default_rng(3)
    rv = rng.normal(size=(500, 3))
    rv *= rng.uniform(0, np.pi, (500, 1)) / np.linalg.norm(rv, axis=1, keepdims=True)
    axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, -1, 1], [1, 1, 1]], float)
    special = np.concatenate(
        [np.zeros((1, 3)), np.pi * axes / np.linalg.norm(axes, axis=1)[:, None]]
    )
    R = R_from_rotvec(np.concatenate([rv, special, -special]))
    want = quat_xyzw_from_R(R)
    got = np.array([quat_xyzw_of(r) for r in R])
    assert np.abs(got - want).max() < 1e-15


def test_one_rotation_vector_matrix_is_scipys() -> None:
    """``R_of_rotvec`` (a live pose's, plain floats) gives ``R_from_rotvec``'s matrix: random
    vectors up to a half turn and beyond, and tiny ones (the series' side of its threshold and
    just past it, where 1 - cos would cancel)."""
    from tagtrail.geometry.se3 import R_from_rotvec, R_of_rotvec

    rng = np.random.default_rng(4)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    th = np.concatenate([rng.uniform(0, 2 * np.pi, 300), 10.0 ** rng.uniform(-12, -3, 100)])
    rv = np.concatenate([d * th[:, None], np.zeros((1, 3)), [[np.pi, 0, 0], [1e-8, 0, 0]]])
    want = R_from_rotvec(rv)
    got = np.stack([R_of_rotvec(v) for v in rv])
    assert np.abs(got - want).max() < 1e-15 * 8
    assert np.abs(got @ np.swapaxes(got, 1, 2) - np.eye(3)).max() < 1e-14
