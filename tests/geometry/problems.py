"""Joint-solve problems shared by the geometry tests: the ring scene's corners as a corner
problem, perturbed starting poses, and a camera driving a tilted floor."""

from __future__ import annotations

import numpy as np

from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.joint import CornerObservations
from tagtrail.geometry.se3 import R_from_rotvec, inv, make_T
from tests.stages.mapping_scene import ring_scene

FOCAL_PX = 500.0


def corner_problem(
    noise_px: float = 0.0,
    seed: int = 0,
    n_frames: int = 180,
) -> tuple[CornerObservations, np.ndarray, np.ndarray, int, np.ndarray]:
    """The ring scene's corners as normalised image coordinates (+ Gaussian noise in px), its
    tags and cameras (``cam_T_world``) in the anchor's frame, the anchor and frame stamps (s)."""
    scene = ring_scene(n_tags=12, r_cam=1.0, half_fov_deg=50.0, n_frames=n_frames)
    pts_tag = tag_corners(np.full(len(scene.frame), scene.size_m))
    cam_T_tag = scene.cam_T_tag()
    p = np.einsum("oij,okj->oki", cam_T_tag[:, :3, :3], pts_tag) + cam_T_tag[:, None, :3, 3]
    uv = p[..., :2] / p[..., 2:]
    uv = uv + np.random.default_rng(seed).normal(scale=noise_px / FOCAL_PX, size=uv.shape)
    frames, f = np.unique(scene.frame, return_inverse=True)
    a_T_w = inv(scene.world_T_tag[0])  # anchor (tag 0) frame = world of the problem
    t_s = (scene.t_ns[frames] - scene.t_ns[0]) * 1e-9
    return (
        CornerObservations(f, scene.tag.astype(np.int64), pts_tag, uv),
        a_T_w @ scene.world_T_tag,
        inv(a_T_w @ scene.world_T_cam[frames]),
        0,
        t_s,
    )


def perturbed(
    T: np.ndarray, seed: int, rot: float, trans: float, keep: int | None = None
) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = make_T(
        R_from_rotvec(rng.normal(scale=rot, size=(len(T), 3))) @ T[:, :3, :3],
        T[:, :3, 3] + rng.normal(scale=trans, size=(len(T), 3)),
    )
    if keep is not None:
        out[keep] = T[keep]
    return out


def planar_cameras(n: int = 40, seed: int = 0, tilt_deg: float = 12.0) -> np.ndarray:
    """``cam_T_world (n, 4, 4)`` of a camera pitched down ``tilt_deg`` driving a random path on
    a plane whose normal is tilted from the world's y axis (the anchor need not be level)."""
    rng = np.random.default_rng(seed)
    level = R_from_rotvec(np.array([[0.3, 0.0, -0.2]]))[0]  # world_R_floor
    yaw = np.cumsum(rng.normal(scale=0.2, size=n))
    xy = np.cumsum(rng.normal(scale=0.2, size=(n, 2)), axis=0)
    # floor frame: y up; camera: z forward, y down, pitched down by tilt about its x axis
    base = np.stack([R_from_rotvec(np.array([[0.0, a, 0.0]]))[0] for a in yaw])
    flip = np.diag([1.0, -1.0, -1.0])  # camera y down, z forward
    pitch = R_from_rotvec(np.array([[np.radians(tilt_deg), 0.0, 0.0]]))[0]
    floor_R_cam = base @ flip @ pitch
    pos = np.stack([xy[:, 0], np.full(n, 0.17), xy[:, 1]], axis=1)
    world_T_cam = make_T(level @ floor_R_cam, pos @ level.T + np.array([0.5, -0.2, 1.0]))
    return inv(world_T_cam)
