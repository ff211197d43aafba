"""TagSLAM's recordings (``../shared/realdata/tagslam_test_*``) for the tests and the bench:
its solution read from ``reference.bag``, trajectories compared with it, and test 16's scene
rebuilt in the simulator (its tags, camera, stamps and path), where ground truth exists."""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from tagtrail.geometry.registration import umeyama
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import R_from_rotvec, T_from_xyz_quat, make_T
from tagtrail.io.camera_files import read_camera_file
from tagtrail.io.layouts import read_trajectory
from tagtrail.schemas.artifacts import POSE_COLS
from tagtrail.sim import bagwrite
from tagtrail.sim.scene import Scene, Tag
from tagtrail.sim.simulate import make_options, write_ground_truth

TAG_SIZES = {"tagslam_test_16": 0.16, "tagslam_test_1": 0.225}


def poses(df: pd.DataFrame) -> np.ndarray:
    """``(N, 4, 4)`` from a frame's pose columns."""
    v = df[POSE_COLS].to_numpy(np.float64)
    return T_from_xyz_quat(v[:, :3], v[:, 3:])


def unpack(root: Path, name: str, dest: Path) -> Path:
    """``root/<name>.bz2`` decompressed into ``dest/<name>``."""
    out = dest / name
    out.write_bytes(bz2.decompress((root / f"{name}.bz2").read_bytes()))
    return out


def tagslam_reference(bag: Path, root: Path) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """TagSLAM's solution in its reference.bag: ``map_T_tag`` per tag (from /tf: map->body,
    body->tag_<id>, the body static: lab, perch, ...) and ``map_T_cam0`` per stamp (the rig's
    odometry @ camera_poses.yaml)."""
    from rosbags.highlevel import AnyReader

    cam = yaml.safe_load((root / "camera_poses.yaml").read_text())["cam0"]["pose"]
    rig_T_cam = make_T(
        R_from_rotvec([cam["rotation"][k] for k in "xyz"]), [cam["position"][k] for k in "xyz"]
    )
    tf: dict[tuple[str, str], np.ndarray] = {}
    cams: dict[int, np.ndarray] = {}
    with AnyReader([bag]) as reader:
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == "nav_msgs/msg/Odometry":
                p = msg.pose.pose
                T = T_from_xyz_quat(
                    [p.position.x, p.position.y, p.position.z],
                    [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w],
                )
                stamp = msg.header.stamp
                cams[stamp.sec * 10**9 + stamp.nanosec] = T @ rig_T_cam
            else:
                for t in msg.transforms:
                    tr, q = t.transform.translation, t.transform.rotation
                    tf[(t.header.frame_id, t.child_frame_id)] = T_from_xyz_quat(
                        [tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w]
                    )
    body = {parent for (parent, child) in tf if child.startswith("tag_")}  # lab, perch, ...
    tags = {
        int(child[4:]): tf[("map", parent)] @ T
        for (parent, child), T in tf.items()
        if parent in body and child.startswith("tag_")
    }
    return tags, cams


def matched(traj_file: Path, cams: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The poses of ``traj_file`` whose stamps ``cams`` has, and those of ``cams``."""
    traj = read_trajectory(traj_file)
    keep = [k for k, s in enumerate(traj["t_ns"].to_numpy()) if int(s) in cams]
    stamps = traj["t_ns"].to_numpy()[keep]
    return poses(traj)[keep], np.array([cams[int(s)] for s in stamps])


def agreement(T: np.ndarray, ref: np.ndarray) -> tuple[float, float, float]:
    """(mean, max position error m, mean rotation error deg) after an SE(3) fit on positions."""
    _, R, t = umeyama(T[:, :3, 3], ref[:, :3, 3], with_scale=False)
    pos = np.linalg.norm(T[:, :3, 3] @ R.T + t - ref[:, :3, 3], axis=1)
    ang = np.degrees(geodesic_angle(R[None] @ T[:, :3, :3], ref[:, :3, :3]))
    return float(pos.mean()), float(pos.max()), float(ang.mean())


def roughness(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Second differences of the positions in the camera frame: RMS (m) and lag-1
    autocorrelation per axis -- about -0.67 for independent per-frame noise, positive for
    smooth motion."""
    p = T[:, :3, 3]
    d2 = np.einsum("nji,nj->ni", T[1:-1, :3, :3], p[2:] - 2 * p[1:-1] + p[:-2])
    ac = np.array([np.corrcoef(d2[1:, a], d2[:-1, a])[0, 1] for a in range(3)])
    return np.sqrt((d2**2).mean(0)), ac


def smooth_path(T: np.ndarray, sigma: float) -> np.ndarray:
    """Low-passed poses (Gaussian of ``sigma`` samples): positions, and rotation vectors about
    the middle frame's rotation."""
    out = T.copy()
    out[:, :3, 3] = gaussian_filter1d(T[:, :3, 3], sigma, axis=0, mode="nearest")
    R0 = Rotation.from_matrix(T[len(T) // 2, :3, :3])
    rv = (R0.inv() * Rotation.from_matrix(T[:, :3, :3])).as_rotvec()
    out[:, :3, :3] = (
        R0 * Rotation.from_rotvec(gaussian_filter1d(rv, sigma, axis=0, mode="nearest"))
    ).as_matrix()
    return out


def shake(n: int, dt: float, density: float, rng: np.random.Generator) -> np.ndarray:
    """Hand shake ``(n, 3)`` m: white acceleration of ``density`` m/s^2/sqrt(Hz) integrated
    twice, its content below about 1 Hz removed (so the camera keeps its path)."""
    acc = rng.normal(0.0, density / np.sqrt(dt), (n, 3))
    p = np.cumsum(np.cumsum(acc, axis=0) * dt, axis=0) * dt
    return p - gaussian_filter1d(p, 1.0 / (2 * np.pi * dt), axis=0, mode="nearest")


def simulate_test_16(
    realdata: Path, out: Path, corner_noise_px: float, shake_density: float, seed: int = 0
) -> tuple[Path, dict[int, np.ndarray]]:
    """Test 16 rebuilt in the simulator, as a detections rosbag2 in ``out``: TagSLAM's five
    collinear tags, the real camera (cameras.yaml), TagSLAM's stamps, and as the true path
    TagSLAM's camera trajectory low-passed (Gaussian, 0.3 s) plus ``shake_density`` of hand
    shake; Gaussian corner noise. Returns the bag and the true ``world_T_cam`` by stamp."""
    root = realdata / "tagslam_test_16"
    out.mkdir(parents=True, exist_ok=True)
    tags_T, cams = tagslam_reference(unpack(root, "reference.bag", out), root)
    stamps = np.array(sorted(cams), dtype=np.int64)
    dt = float(np.median(np.diff(stamps))) * 1e-9
    rng = np.random.default_rng(seed)
    truth = smooth_path(np.array([cams[int(s)] for s in stamps]), 0.3 / dt)
    if shake_density > 0:
        truth[:, :3, 3] += shake(len(truth), dt, shake_density, rng)
    camera = read_camera_file(root / "cameras.yaml")
    size = TAG_SIZES["tagslam_test_16"]
    tags = tuple(Tag(i, size, T) for i, T in sorted(tags_T.items()))
    opts = make_options(
        detections=True,
        corner_noise_px=corner_noise_px,
        max_range_m=20.0,
        max_incidence_deg=85.0,
        camera=camera,
        seed=seed,
    )
    scene = Scene("reference", camera, tags, (), min(tags_T), truth, stamps)
    bag = out / "bag"
    bagwrite.write_bag(bag, scene, opts, rng)
    write_ground_truth(bag / "ground_truth", scene, "tagslam_test_16", opts)
    gt = read_trajectory(bag / "ground_truth/trajectory.csv")
    return bag, {int(s): T for s, T in zip(gt["t_ns"], poses(gt), strict=True)}
