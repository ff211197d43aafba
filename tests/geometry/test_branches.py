"""``geometry.ippe.consistent_branches``: the IPPE solutions of a tag pair that agree across
frames, on a pair whose second solutions are mirrored tags (the normal reflected about the line
of sight, as IPPE's ambiguity does)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from tagtrail.geometry.ippe import consistent_branches, map_branches
from tagtrail.geometry.se3 import R_from_rotvec, inv, make_T, rotation_angle

W_I = make_T(np.eye(3), [0.0, 0.0, 0.0])
W_J = make_T(R_from_rotvec([0.0, np.radians(-70.0), 0.0]), [1.2, 0.0, -0.6])


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``world_T_cam`` at ``centre`` with its z axis through ``target`` (y down)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    return make_T(np.stack([x, np.cross(z, x), z], axis=1), centre)


def mirrored(cam_T_tag: np.ndarray) -> np.ndarray:
    """The tag turned so its normal is reflected about the line of sight to its centre."""
    ray = -cam_T_tag[:3, 3] / np.linalg.norm(cam_T_tag[:3, 3])  # tag -> camera
    n = cam_T_tag[:3, 2]
    axis = np.cross(n, ray)
    ang = 2.0 * np.arctan2(np.linalg.norm(axis), n @ ray)
    turn = R_from_rotvec(axis / np.linalg.norm(axis) * ang)
    return make_T(turn @ cam_T_tag[:3, :3], cam_T_tag[:3, 3])


def frames(centres: np.ndarray, wrong_j: np.ndarray) -> tuple[np.ndarray, ...]:
    """Both solutions of both tags per frame; tag j's lower-reprojection one is the mirror
    where ``wrong_j``; weights: 1 for the best, 0.8 for the second (a close call)."""
    target = (W_I[:3, 3] + W_J[:3, 3]) / 2
    T_i, T_j = [], []
    for c, bad in zip(centres, wrong_j, strict=True):
        cam_T_w = inv(look_at(c, target))
        ci, cj = cam_T_w @ W_I, cam_T_w @ W_J
        T_i.append([ci, mirrored(ci)])
        T_j.append([mirrored(cj), cj] if bad else [cj, mirrored(cj)])
    w = np.tile([1.0, 0.8], (len(centres), 1))
    return np.array(T_i), np.array(T_j), w, w.copy()


def test_a_moving_view_outvotes_a_majority_of_mirrored_solutions() -> None:
    rng = np.random.default_rng(0)
    n = 60
    centres = np.stack([np.linspace(-1.5, 2.5, n), np.zeros(n), np.full(n, 2.5)], axis=1)
    wrong = rng.random(n) < 0.6
    T_i, T_j, w_i, w_j = frames(centres, wrong)
    out = consistent_branches(np.zeros(n, np.int64), T_i, T_j, w_i, w_j)
    true = inv(W_I) @ W_J
    assert (out.choice == np.where(wrong, 1, 0)).all()  # tag j's other solution where it is wrong
    assert np.abs(out.T_ij - true).max() < 1e-9
    assert out.ratio.max() < 0.3  # the mirrored poses move with the view: no close rival


def test_a_still_view_keeps_the_rival_it_cannot_tell_apart() -> None:
    """Seen from (nearly) one place, the mirrored pose agrees with itself too: whichever wins,
    the other is the runner-up with a close ratio, so the joint solve can decide."""
    rng = np.random.default_rng(1)
    n = 40
    centres = np.array([0.5, 0.0, 2.5]) + rng.normal(0.0, 0.005, (n, 3))
    wrong = rng.random(n) < 0.7
    T_i, T_j, w_i, w_j = frames(centres, wrong)
    out = consistent_branches(np.zeros(n, np.int64), T_i, T_j, w_i, w_j)
    true = inv(W_I) @ W_J
    err_win = rotation_angle(inv(true)[None, :3, :3] @ out.T_ij[:, :3, :3])
    err_alt = rotation_angle(inv(true)[None, :3, :3] @ out.alt_T_ij[:, :3, :3])
    assert (np.minimum(err_win, err_alt) < np.radians(1.0)).all()
    assert (np.maximum(err_win, err_alt) > np.radians(10.0)).all()
    assert out.ratio.min() > 0.3


def test_pairs_are_decided_separately() -> None:
    n = 30
    centres = np.stack([np.linspace(-1.0, 2.0, n), np.zeros(n), np.full(n, 2.5)], axis=1)
    a = frames(centres, np.zeros(n, bool))
    b = frames(centres, np.ones(n, bool))
    both = [np.concatenate([x, y]) for x, y in zip(a, b, strict=True)]
    group = np.r_[np.zeros(n, np.int64), np.ones(n, np.int64)]
    out = consistent_branches(group, *both)
    assert (out.choice[:n] == 0).all() and (out.choice[n:] == 1).all()


def test_the_map_picks_each_observations_solution_in_its_frame() -> None:
    """map_branches: tags around a moving camera, a third of the observations with the mirror
    first; every frame of two or more tags gets its true solutions back, from a map a degree off,
    and the frames of one tag (nothing to check against) and solutions missing keep the first."""
    rng = np.random.default_rng(1)
    n_tags = 8
    ang = np.linspace(0.0, 2 * np.pi, n_tags, endpoint=False)
    W = [
        make_T(R_from_rotvec([0.0, a + np.pi / 2, 0.0]), [3 * np.cos(a), 0.0, 3 * np.sin(a)])
        for a in ang
    ]
    frame, tag, both, wrong = [], [], [], []
    for f in range(50):
        c = np.array([rng.uniform(-1, 1), rng.uniform(-0.2, 0.2), rng.uniform(-1, 1)])
        seen = rng.choice(n_tags, rng.integers(1, 5), replace=False)
        cam_T_w = inv(look_at(c, W[seen[0]][:3, 3]))
        for t in seen:
            true = cam_T_w @ W[t]
            pair = [true, mirrored(true)]
            bad = rng.random() < 0.33
            frame.append(f)
            tag.append(t)
            both.append(pair[::-1] if bad else pair)
            wrong.append(bad)
    frame_, tag_, wrong_ = np.array(frame), np.array(tag), np.array(wrong)
    S = np.array(both)[:, :, :3, :3]
    W_map = np.array(
        [w[:3, :3] @ R_from_rotvec(rng.normal(scale=np.radians(1.0), size=3)) for w in W]
    )
    missing = np.zeros(len(frame_), bool)
    missing[::7] = True  # a source that gave one pose: its only solution is the one it has
    S[missing & ~wrong_, 1] = np.nan
    choice = map_branches(frame_, W_map[tag_], S)
    multi = np.bincount(frame_)[frame_] > 1
    assert multi.sum() > 60 and (~multi).sum() > 3 and wrong_[multi].sum() > 20
    assert (choice[multi] == wrong_[multi]).all()
    assert (choice[~multi] == 0).all()
    assert (choice[missing & ~wrong_] == 0).all()


def test_a_frame_the_map_cannot_decide_keeps_the_best_solutions() -> None:
    """Two tags whose mirrors agree with each other as well as the true poses do (a
    near-degenerate view): the lower-reprojection solutions stay."""
    cam = inv(look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3)))
    ti, tj = cam @ W_I, cam @ W_I
    S = np.array([[ti, ti], [tj, tj]])[:, :, :3, :3]
    out = map_branches(np.zeros(2, np.int64), np.array([np.eye(3), np.eye(3)]), S)
    assert (out == 0).all()


def test_a_frame_of_one_tag_keeps_its_lower_reprojection_solution() -> None:
    """2000 frames of one tag, any map orientation and any two solutions: the tag is only
    checked against itself, so its first solution stays. The angle from the trace's arccos
    was off by ~1e-6 deg for a rotation against itself, more than the ties' margin: 94 of
    these frames took the mirror (a 1.4 m jump of a camera 3 m from its tag)."""
    n = 2000
    W = Rotation.random(n, random_state=1).as_matrix()
    S = np.stack([Rotation.random(n, random_state=s).as_matrix() for s in (2, 3)], axis=1)
    assert (map_branches(np.arange(n), W, S) == 0).all()
