"""A wheeled robot with a camera and wheel odometry among tags, for the odometry prior's tests:
the true base path, the tags' corners the camera sees (with stretches where it sees none) and
the odometry the LIMO's wheels would report (tagtrail.sim.limo.WheelOdometry's error model,
its stamps the publication time, a given latency later than the state they describe)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.joint import CornerRows, JointSettings, corner_problem
from tagtrail.geometry.joint.odometry import OdometryData
from tagtrail.geometry.joint.setup import CornerProblem
from tagtrail.geometry.se3 import inv, make_T, quat_xyzw_from_R
from tagtrail.sim.odometry import WheelOdometry
from tagtrail.sim.scene import Mount, scene_T_cam_planar

FOCAL_PX = 500.0
CAMERA = CameraModel(
    640, 480, np.array([[FOCAL_PX, 0, 320.0], [0, FOCAL_PX, 240.0], [0, 0, 1]]), np.zeros(5)
)
MOUNT = Mount()  # 0.084 m ahead of the rear axle, 0.17 m up, looking along the heading


@dataclass(frozen=True)
class Drive:
    """The truth: frame stamps ``t_ns (F,)``, ``world_T_cam (F, 4, 4)``, the tags' ``world_T_tag
    (T, 4, 4)`` (size ``size_m``), the observations (``frame (O,)`` indices into the frames,
    ``tag (O,)``, corners ``(O, 4, 2)`` px) and the odometry as ``extract.odometry`` would hold
    it (``odom_t_ns (N,)``, ``odom_pose (N, 7)``); ``travel_m (F,)``: the base's distance driven
    since the start."""

    t_ns: np.ndarray
    world_T_cam: np.ndarray
    world_T_tag: np.ndarray
    size_m: float
    frame: np.ndarray
    tag: np.ndarray
    corners_px: np.ndarray
    odom_t_ns: np.ndarray
    odom_pose: np.ndarray
    travel_m: np.ndarray
    yaw_err_dps: float


def drive(
    seconds: float = 20.0,
    fps: float = 15.0,
    speed_mps: float = 0.3,
    blind: tuple[float, float] | None = None,
    latency_s: float = 0.005,
    offset_s: float = 0.0,
    scale: float | None = None,
    slip: tuple[float, float, float] | None = None,
    noise_px: float = 0.3,
    seed: int = 0,
    lively: bool = False,
) -> Drive:
    """A robot weaving about a circle of 1.2 m inside a ring of 12 tags for ``seconds`` at
    ``speed_mps``, its camera at ``fps``. ``blind``: the camera sees no tag from ``blind[0]``
    to ``blind[1]`` s; the odometry's stamps ``latency_s`` (plus ``offset_s``) after the state
    they describe; ``scale``: both wheels read that scale (else the LIMO model's random 1-3 %
    per wheel); ``slip``: ``(t0, t1, extra)``: between t0 and t1 s the wheels over-read by
    ``extra`` (0.2: 20 % slip); ``lively``: the speed and turn rate swing (stop-and-go, quick
    turns: what makes a time offset show)."""
    rng = np.random.default_rng(seed)
    dt = 0.002
    n = int(seconds / dt) + 1
    t = np.arange(n) * dt
    v = np.full(n, speed_mps)
    omega = v / 1.2 + 0.3 * np.sin(0.5 * t)  # about a circle of 1.2 m inside the ring
    if lively:
        v = speed_mps * (1.0 + 0.7 * np.sin(1.3 * t))
        omega = v / 1.2 + 0.6 * np.sin(0.9 * t)
    v[t < 0.5] = v[t < 0.5] * t[t < 0.5] / 0.5  # starts from rest
    x = np.zeros(n)
    y = np.zeros(n)
    yaw = np.zeros(n)
    x[0], y[0], yaw[0] = 0.0, -1.2, 0.0
    odo = WheelOdometry(rng=rng)
    if scale is not None:
        odo.scale_l = odo.scale_r = scale
    ox, oy, oyaw = np.zeros(n), np.zeros(n), np.zeros(n)
    for k in range(1, n):
        mid = yaw[k - 1] + 0.5 * omega[k - 1] * dt
        x[k] = x[k - 1] + v[k - 1] * np.cos(mid) * dt
        y[k] = y[k - 1] + v[k - 1] * np.sin(mid) * dt
        yaw[k] = yaw[k - 1] + omega[k - 1] * dt
        extra = 1.0
        if slip is not None and slip[0] <= t[k] < slip[1]:
            extra = 1.0 + slip[2]
        odo.step(v[k - 1] * extra, omega[k - 1], dt)
        ox[k], oy[k], oyaw[k] = odo.x, odo.y, odo.yaw
    travel = np.r_[0.0, np.cumsum(v[:-1] * dt)]
    # the camera's frames
    t_f = np.arange(0.0, seconds - 0.6, 1.0 / fps) + 0.3
    kf = np.round(t_f / dt).astype(int)
    world_T_cam = scene_T_cam_planar(np.stack([x[kf], y[kf]], axis=1), yaw[kf], MOUNT)
    # the odometry at 50 Hz: the state at s, stamped s + latency + offset
    t_o = np.arange(0.0, seconds - 0.02, 0.02)
    ko = np.round(t_o / dt).astype(int)
    stamp = t_o + latency_s + offset_s
    half = 0.5 * oyaw[ko]
    odom_pose = np.stack(
        [ox[ko], oy[ko], np.zeros(len(ko)), 0 * half, 0 * half, np.sin(half), np.cos(half)], axis=1
    )
    # the tags: a ring of 12 upright tags at 2.5 m facing its centre, 0.4 m up
    ang = np.arange(12) * 2 * np.pi / 12
    world_T_tag = []
    for a in ang:
        c = np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 0.4])
        z = -np.array([np.cos(a), np.sin(a), 0.0])  # tag z out of its face, towards the centre
        yy = np.array([0.0, 0.0, 1.0])
        xx = np.cross(yy, z)
        world_T_tag.append(make_T(np.stack([xx, yy, z], axis=1), c))
    W = np.stack(world_T_tag)
    size = 0.16
    pts = tag_corners(np.full(1, size))[0]
    frame, tag, corners = [], [], []
    for f in range(len(t_f)):
        if blind is not None and blind[0] <= t_f[f] < blind[1]:
            continue
        cTw = inv(world_T_cam[f])
        for i in range(len(W)):
            cTt = cTw @ W[i]
            p = pts @ cTt[:3, :3].T + cTt[:3, 3]
            if (p[:, 2] < 0.3).any() or p[:, 2].max() > 4.0:
                continue
            facing = cTt[:3, 2] @ (-cTt[:3, 3] / np.linalg.norm(cTt[:3, 3]))
            if facing < 0.3:
                continue
            uv = FOCAL_PX * p[:, :2] / p[:, 2:] + np.array([320.0, 240.0])
            if (uv < 5).any() or (uv[:, 0] > 635).any() or (uv[:, 1] > 475).any():
                continue
            frame.append(f)
            tag.append(i)
            corners.append(uv + rng.normal(scale=noise_px, size=uv.shape))
    return Drive(
        t_ns=np.round(t_f * 1e9).astype(np.int64) + 10**18,
        world_T_cam=world_T_cam,
        world_T_tag=W,
        size_m=size,
        frame=np.asarray(frame, np.int64),
        tag=np.asarray(tag, np.int64),
        corners_px=np.asarray(corners).reshape(-1, 4, 2),
        odom_t_ns=np.round(stamp * 1e9).astype(np.int64) + 10**18,
        odom_pose=odom_pose,
        travel_m=travel[kf],
        yaw_err_dps=float(np.degrees(odo.drift_rps)),
    )


def problem(d: Drive, settings: JointSettings) -> CornerProblem:
    """The joint problem of the drive's observations (both IPPE solutions: the true pose and
    none), frames in time order."""
    cam_T_tag = np.full((len(d.frame), 2, 4, 4), np.nan)
    cam_T_tag[:, 0] = inv(d.world_T_cam[d.frame]) @ d.world_T_tag[d.tag]
    rows = CornerRows(
        d.frame,
        d.t_ns[d.frame],
        d.tag,
        d.corners_px,
        np.full(len(d.frame), d.size_m),
        cam_T_tag,
    )
    return corner_problem(rows, d.tag, CAMERA, settings, True)


def odometry_data(
    d: Drive, base_T_camera: np.ndarray | None = None, topic: str = "/odom"
) -> OdometryData:
    """The drive's odometry as the stages hand it over; the frames with no tag listed."""
    seen = np.unique(d.frame)
    blind = np.setdiff1d(np.arange(len(d.t_ns)), seen)
    return OdometryData(
        d.odom_t_ns,
        d.odom_pose,
        np.full((len(d.odom_t_ns), 3), 1e-3),
        base_T_camera,
        "tf_static" if base_T_camera is not None else "",
        topic,
        d.t_ns[blind],
    )


def true_base_T_camera(yaw_deg: float = 0.0, forward_m: float = MOUNT.forward_m) -> np.ndarray:
    """``base_T_camera`` ``[x, y, z, qx, qy, qz, qw]`` of the mount (camera yawed by
    ``yaw_deg`` to a wrong one, or moved to ``forward_m``)."""
    T = scene_T_cam_planar(np.zeros((1, 2)), np.array([np.radians(yaw_deg)]), MOUNT)[0]
    T[0, 3] = forward_m
    return np.r_[T[:3, 3], quat_xyzw_from_R(T[:3, :3])]
