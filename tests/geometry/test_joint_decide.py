"""The ground-plane and wheeled-drive ``auto`` decisions are not taken on data that cannot
support them (geometry.joint.decide): a parked camera, or a few seconds."""

from __future__ import annotations

import numpy as np

from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.joint import (
    CornerObservations,
    Corners,
    DrivePrior,
    GroundPrior,
    JointResult,
    MotionPrior,
    solve_grounded,
    solve_joint,
    travel,
)
from tagtrail.geometry.joint.decide import MIN_DURATION_S, MIN_TRAVEL_M
from tagtrail.geometry.joint.ground import PLANAR_BOUND
from tagtrail.geometry.se3 import R_from_rotvec, inv, make_T

FOCAL_PX = 500.0
GROUND = GroundPrior.of(0.01, 1.0)
DRIVE = DrivePrior(0.01)


def parked(
    n: int = 30, fps: float = 30.0, seed: int = 0
) -> tuple[CornerObservations, np.ndarray, np.ndarray, np.ndarray]:
    """A camera standing still 1.5 m before four 16 cm tags for ``n`` frames, corners with
    0.3 px of noise: the observations, ``world_T_tag``, ``cam_T_world`` and stamps (s)."""
    W = make_T(
        np.repeat(np.eye(3)[None], 4, 0),
        np.array([[-0.4, 0.0, 0.0], [0.4, 0.0, 0.0], [-0.4, 0.3, 0.0], [0.4, 0.3, 0.0]]),
    )
    C = np.repeat(
        inv(make_T(R_from_rotvec(np.array([[0.1, 0.05, 0.0]])), np.array([[0.0, 0.15, -1.5]])))[
            None, 0
        ],
        n,
        0,
    )
    frame, tag = np.repeat(np.arange(n), 4), np.tile(np.arange(4), n)
    pts = tag_corners(np.full(len(frame), 0.16))
    pw = np.einsum("oij,okj->oki", W[tag, :3, :3], pts) + W[tag, None, :3, 3]
    pc = np.einsum("oij,okj->oki", C[frame, :3, :3], pw) + C[frame, None, :3, 3]
    uv = pc[..., :2] / pc[..., 2:] + np.random.default_rng(seed).normal(
        scale=0.3 / FOCAL_PX, size=pc[..., :2].shape
    )
    return CornerObservations(frame, tag, pts, uv), W, C, np.arange(n) / fps


def decide(fallback: tuple[bool, bool] | None = None):  # type: ignore[no-untyped-def]
    ob, W, C, t_s = parked()
    motion = MotionPrior(t_s, 0.1, np.radians(30.0), 0.5)
    fixed = np.zeros(len(W), bool)

    def solve(start: JointResult | None = None, priors=()):  # type: ignore[no-untyped-def]
        return solve_joint(
            W[:, :3, :3],
            W[:, :3, 3],
            C[:, :3, :3],
            C[:, :3, 3],
            ob,
            fixed,
            Corners(FOCAL_PX, 0.3),
            [motion, *priors],
            covariance=True,
        )

    res = solve()
    return res, *solve_grounded(res, solve, GROUND, "auto", DRIVE, "auto", motion, fallback)


def test_a_parked_camera_gets_neither_prior_and_says_why() -> None:
    """Still frames fit any plane through their one pose (the planarity figure is below the
    bound: the rule alone would apply the prior, and find the camera at any tilt), and no
    mount: auto is not decided on them, and the report says so in words."""
    res, out, rep = decide()
    assert rep.planarity < PLANAR_BOUND  # what the planarity rule alone would have applied
    assert not rep.applied and rep.drive is None and out is res
    assert "parked" in rep.note and "too little to decide on" in rep.note
    assert "moved" in rep.note and "cm" in rep.note


def test_a_parked_camera_takes_the_references_decision() -> None:
    _, out, rep = decide(fallback=(True, False))
    assert rep.applied and "the reference's decision" in rep.note
    assert rep.drive is not None and not rep.drive.applied
    assert "ground" in out.unknowns and "drive" not in out.unknowns


def test_travel_tells_parked_and_short_data_from_a_drive() -> None:
    ob, W, C, t_s = parked(n=300)
    still = travel(C[:, :3, :3], C[:, :3, 3], t_s)
    assert still.extent_m < 1e-9 and still.duration_s > MIN_DURATION_S and not still.enough
    # 1 m along x in 1 s: moves, but too short; the same over 4 s: enough
    world_T_cam = inv(C)
    world_T_cam[:, 0, 3] += np.linspace(0.0, 1.0, 300)
    moving = inv(world_T_cam)
    short = travel(moving[:, :3, :3], moving[:, :3, 3], t_s / 10)
    assert short.extent_m > MIN_TRAVEL_M and not short.enough and "too short" in short.words()
    assert travel(moving[:, :3, :3], moving[:, :3, 3], t_s * 0.4).enough
