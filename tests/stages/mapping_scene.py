"""A synthetic mapping scene built from rigid transforms only (the paper's Sec. 4.1 set-up).

Tags upright on a ring facing its centre, a camera on a smaller concentric circle looking outward
(optical frame: x right, y down, z forward; world: y up, floor = x-z plane). Observations are
``cam_T_tag = (world_T_cam)^-1 world_T_tag`` for every tag in the field of view and facing the
camera; detections are the tag corners projected by a distortion-free pinhole camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.joint import JointSettings
from tagtrail.geometry.se3 import (
    inv,
    make_T,
    quat_xyzw_from_R,
    transform_points,
    xyz_quat_from_T,
)
from tagtrail.schemas.documents import OptimizeReport

POSE = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]
ALT = [f"alt_{c}" for c in POSE]
T0_NS = 1_700_000_000_000_000_000
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
CAMERA = CameraModel(640, 480, K, [], "none")


@dataclass
class Scene:
    world_T_tag: np.ndarray  # (n, 4, 4), tag ids 0..n-1
    world_T_cam: np.ndarray  # (F, 4, 4)
    t_ns: np.ndarray  # (F,)
    frame: np.ndarray  # (M,) observation -> frame index
    tag: np.ndarray  # (M,) observation -> tag id
    size_m: float = 0.16

    def anchor_frame(self, anchor: int) -> tuple[np.ndarray, np.ndarray]:
        """Ground truth expressed in ``anchor``'s frame: (tags, cameras)."""
        a_T_w = inv(self.world_T_tag[anchor])
        return a_T_w @ self.world_T_tag, a_T_w @ self.world_T_cam

    def cam_T_tag(self) -> np.ndarray:
        return inv(self.world_T_cam[self.frame]) @ self.world_T_tag[self.tag]


def _frame(z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Rotation (..., 3, 3) with columns x = y cross z, y, z."""
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def ring_scene(
    n_tags: int = 12,
    n_frames: int = 240,
    r_tags: float = 3.0,
    r_cam: float = 1.5,
    half_fov_deg: float = 38.0,
    max_incidence_deg: float = 70.0,
    yaw_wobble_deg: float = 15.0,
) -> Scene:
    a = 2 * np.pi * np.arange(n_tags) / n_tags
    radial = np.stack([np.cos(a), np.zeros_like(a), np.sin(a)], axis=1)
    up = np.broadcast_to([0.0, 1.0, 0.0], radial.shape)
    # Tags alternate heights a little so the map is not degenerate in y.
    h = 0.15 * np.where(np.arange(n_tags) % 2 == 0, 1.0, -1.0)
    world_T_tag = make_T(_frame(-radial, up), r_tags * radial + h[:, None] * up)

    b = 2 * np.pi * np.arange(n_frames) / n_frames
    yaw = np.deg2rad(yaw_wobble_deg) * np.sin(3 * b)
    look = np.stack([np.cos(b + yaw), np.zeros_like(b), np.sin(b + yaw)], axis=1)
    pos = r_cam * np.stack([np.cos(b), np.zeros_like(b), np.sin(b)], axis=1)
    down = np.broadcast_to([0.0, -1.0, 0.0], look.shape)
    world_T_cam = make_T(_frame(look, down), pos)

    p_cam = transform_points(inv(world_T_cam)[:, None], world_T_tag[None, :, :3, 3])  # (F, n, 3)
    in_fov = np.degrees(np.arccos(p_cam[..., 2] / np.linalg.norm(p_cam, axis=-1))) < half_fov_deg
    to_cam = pos[:, None, :] - world_T_tag[None, :, :3, 3]
    cos_inc = np.einsum("fnk,nk->fn", to_cam, world_T_tag[:, :3, 2])
    cos_inc /= np.linalg.norm(to_cam, axis=-1)
    vis = in_fov & (cos_inc > np.cos(np.deg2rad(max_incidence_deg)))
    frame, tag = np.nonzero(vis)
    t_ns = T0_NS + np.arange(n_frames, dtype=np.int64) * 100_000_000
    return Scene(world_T_tag, world_T_cam, t_ns, frame, tag)


def observations(
    scene: Scene,
    cam_T_tag: np.ndarray | None = None,
    *,
    noise_t_m: float = 0.0,
    seed: int = 0,
    ambiguity: np.ndarray | None = None,
    alt_cam_T_tag: np.ndarray | None = None,
) -> pd.DataFrame:
    """A ``pnp.observations`` frame of the scene (optionally with translation noise)."""
    T = scene.cam_T_tag() if cam_T_tag is None else cam_T_tag
    xyz, q = xyz_quat_from_T(T)
    if noise_t_m:
        xyz = xyz + np.random.default_rng(seed).normal(scale=noise_t_m, size=xyz.shape)
    m = len(xyz)
    df = pd.DataFrame(
        {
            "t_ns": scene.t_ns[scene.frame],
            "frame_idx": scene.frame.astype(np.int32),
            "tag_id": scene.tag.astype(np.int32),
            "size_m": np.full(m, scene.size_m),
        }
    )
    df[POSE] = np.concatenate([xyz, q], axis=1)
    df["reproj_px"] = np.nan if ambiguity is None else 0.1
    if alt_cam_T_tag is None:
        df[ALT] = np.nan
        df["alt_reproj_px"] = np.nan
    else:
        a_xyz, a_q = xyz_quat_from_T(alt_cam_T_tag)
        df[ALT] = np.concatenate([a_xyz, a_q], axis=1)
        df["alt_reproj_px"] = 0.1 / np.where(ambiguity > 0, ambiguity, 1.0)
    df["ambiguity"] = np.nan if ambiguity is None else ambiguity
    return df


def detections(scene: Scene) -> pd.DataFrame:
    """Tag corners projected by the pinhole ``K`` (OpenCV pixel convention), detector order."""
    s = scene.size_m / 2
    corners_tag = np.array([[-s, -s, 0.0], [s, -s, 0.0], [s, s, 0.0], [-s, s, 0.0]])
    p = transform_points(scene.cam_T_tag()[:, None], corners_tag)  # (M, 4, 3)
    px = np.einsum("ij,mkj->mki", K, p / p[..., 2:])[..., :2]
    df = pd.DataFrame(
        {
            "t_ns": scene.t_ns[scene.frame],
            "frame_idx": scene.frame.astype(np.int32),
            "tag_id": scene.tag.astype(np.int32),
            "hamming": np.zeros(len(px), np.int32),
            "decision_margin": np.full(len(px), 80.0),
        }
    )
    df[[f"c{k}{a}" for k in range(4) for a in "xy"]] = px.reshape(len(px), 8)
    return df


def tag_map_frame(world_T_tag: np.ndarray, ids: np.ndarray | None = None) -> pd.DataFrame:
    """An ``optimize.tag_map``-like frame from poses (n_obs 1, size 0.16)."""
    ids = np.arange(len(world_T_tag)) if ids is None else ids
    df = pd.DataFrame({"tag_id": np.asarray(ids, dtype=np.int32)})
    df[POSE] = np.concatenate([world_T_tag[:, :3, 3], quat_xyzw_from_R(world_T_tag[:, :3, :3])], 1)
    df["n_obs"] = 1
    df["size_m"] = 0.16
    return df


def map_report(**joint: object) -> OptimizeReport:
    """An ``optimize.report`` of a pose-graph map made under the joint settings ``joint``: what
    ``trajectory`` takes its settings from (its ``map_report`` input)."""
    return OptimizeReport(
        anchor_id=0,
        loss="soft_l1",
        f_scale=0.1,
        cost=0.0,
        nfev=1,
        status=1,
        rms_t_m=0.0,
        rms_r_deg=0.0,
        method="pairwise",
        bundle=None,
        joint=JointSettings.model_validate(joint),
    )
