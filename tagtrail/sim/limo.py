"""The simulated LIMO: kinematics with limits, wheel odometry with errors, its camera's detections.

Plain numbers in and out (no zenoh): :mod:`tagtrail.sim.follow` drives it in a closed loop.

- :class:`Kinematics`: the base (rear-axle centre) at ``(x, y, yaw)`` in the scene frame (z up),
  obeying ``cmd_vel`` (v, omega) through a first-order lag (``tau_s``) after clipping to the
  LIMO's limits (NOTES "The LIMO"): |v| ≤ 1 m/s, Ackermann |omega| ≤ |v| / 0.4 m; no command
  for ``cmd_timeout_s``: the command is zero (the base's own watchdog).
- :class:`WheelOdometry`, the error model: each wheel's speed is read with a fixed scale error
  (drawn once per run, 1–3 %, either sign), so distance is off by their mean and yaw rate by
  their difference over the track (0.175 m); the yaw rate gets a constant drift (``drift_dps``,
  drawn in ±0.3 °/s) and an over-read in turns proportional to the lateral acceleration
  (``slip_per_mps2``: 3 % per m/s², skidding). ``/odom`` is ``nav_msgs/msg/Odometry`` at 50 Hz
  whose header stamp is the host time at publication — the state it describes is older by a
  latency drawn in [2, 8] ms — with the LIMO's placeholder covariance.
- :func:`image`: a rendered frame (:class:`~tagtrail.sim.render.Renderer`), as the LIMO's
  camera driver publishes it (raw rgb8);
- :func:`detections`: the tags in view of the camera (mount of :class:`~tagtrail.sim.scene.Mount`)
  projected through the camera model with pixel noise, as ``tagtrail simulate --detections``
  (:func:`tagtrail.sim.bagwrite.synth_detections`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tagtrail.geometry.arrays import F64
from tagtrail.io import msgs
from tagtrail.sim import bagwrite
from tagtrail.sim.camera import FRAME_ID
from tagtrail.sim.render import Renderer
from tagtrail.sim.scenarios import SimOptions
from tagtrail.sim.scene import Scene, scene_T_cam_planar

MAX_SPEED_MPS = 1.0
MIN_TURN_RADIUS_M = 0.4
WHEELBASE_M = 0.2
TRACK_M = 0.175


@dataclass
class Kinematics:
    """The base's true state and its response to commands (module docstring)."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    v: float = 0.0
    omega: float = 0.0
    tau_s: float = 0.1
    cmd_timeout_s: float = 0.5
    cmd: tuple[float, float] = (0.0, 0.0)
    t_cmd: float = -math.inf

    def command(self, v: float, omega: float, t: float) -> None:
        """A ``cmd_vel`` at time ``t``; non-finite values are ignored (kept as zero)."""
        if not (math.isfinite(v) and math.isfinite(omega)):
            v = omega = 0.0
        v = max(-MAX_SPEED_MPS, min(MAX_SPEED_MPS, v))
        bound = abs(v) / MIN_TURN_RADIUS_M
        self.cmd, self.t_cmd = (v, max(-bound, min(bound, omega))), t

    def step(self, t: float, dt: float) -> None:
        """Advance by ``dt`` (s) to time ``t + dt``."""
        v_c, w_c = self.cmd if t - self.t_cmd <= self.cmd_timeout_s else (0.0, 0.0)
        a = min(1.0, dt / self.tau_s)
        self.v += a * (v_c - self.v)
        self.omega += a * (w_c - self.omega)
        self.omega = max(
            -abs(self.v) / MIN_TURN_RADIUS_M, min(abs(self.v) / MIN_TURN_RADIUS_M, self.omega)
        )
        mid = self.yaw + 0.5 * self.omega * dt
        self.x += self.v * math.cos(mid) * dt
        self.y += self.v * math.sin(mid) * dt
        self.yaw = math.atan2(
            math.sin(self.yaw + self.omega * dt), math.cos(self.yaw + self.omega * dt)
        )


@dataclass
class WheelOdometry:
    """Dead reckoning from wheel speeds with the error model of the module docstring."""

    rng: np.random.Generator
    scale_l: float = field(init=False)
    scale_r: float = field(init=False)
    drift_rps: float = field(init=False)
    slip_per_mps2: float = 0.03
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    v: float = 0.0
    omega: float = 0.0

    def __post_init__(self) -> None:
        sign = self.rng.choice([-1.0, 1.0], 2)
        self.scale_l, self.scale_r = 1.0 + sign * self.rng.uniform(0.01, 0.03, 2)
        self.drift_rps = math.radians(float(self.rng.uniform(-0.3, 0.3)))

    def step(self, v: float, omega: float, dt: float) -> None:
        """Integrate the wheels' reading of the true (v, omega) over ``dt``."""
        vl, vr = v - omega * TRACK_M / 2, v + omega * TRACK_M / 2
        ml, mr = vl * self.scale_l, vr * self.scale_r
        self.v = (ml + mr) / 2
        self.omega = (mr - ml) / TRACK_M * (
            1.0 + self.slip_per_mps2 * abs(v * omega)
        ) + self.drift_rps
        mid = self.yaw + 0.5 * self.omega * dt
        self.x += self.v * math.cos(mid) * dt
        self.y += self.v * math.sin(mid) * dt
        self.yaw += self.omega * dt

    def message(self, stamp_ns: int) -> bytes:
        """CDR ``nav_msgs/msg/Odometry`` (frame odom → base_link), stamped ``stamp_ns``."""
        t = msgs.typestore().types
        V3, Q = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](self.x, self.y, 0.0),
            orientation=Q(0.0, 0.0, math.sin(self.yaw / 2), math.cos(self.yaw / 2)),
        )
        cov = np.diag([1e-3, 1e-3, 1e6, 1e6, 1e6, 1e-2]).reshape(-1)  # the LIMO's placeholder
        msg = t["nav_msgs/msg/Odometry"](
            header=bagwrite._header(stamp_ns, "odom"),
            child_frame_id="base_link",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=V3(self.v, 0.0, 0.0), angular=V3(0.0, 0.0, self.omega)
                ),
                covariance=cov,
            ),
        )
        return bytes(msgs.typestore().serialize_cdr(msg, "nav_msgs/msg/Odometry"))


def camera_pose(scene: Scene, x: float, y: float, yaw: float) -> F64:
    """``scene_T_cam`` (4, 4) of the base at (x, y, yaw), with the scene's mount."""
    return np.asarray(scene_T_cam_planar(np.array([[x, y]]), np.array([yaw]))[0])


def detections(
    scene: Scene,
    scene_T_cam: F64,
    stamp_ns: int,
    opts: SimOptions,
    rng: np.random.Generator,
    blind: bool = False,
) -> tuple[bytes, bytes, int]:
    """CDR ``(AprilTagDetectionArray, CameraInfo, number of tags)`` of one frame; ``blind``:
    no tag in view (an empty array, as apriltag_ros publishes)."""
    one = Scene(
        scene.name,
        scene.camera,
        scene.tags,
        scene.walls,
        scene.anchor_id,
        scene_T_cam[None],
        np.array([stamp_ns]),
    )
    vis, corners, margins = bagwrite.synth_detections(one, opts, rng)
    sel = vis.visible[0] & (not blind)
    ts = msgs.typestore()
    det = bagwrite.detections_msg(
        stamp_ns, FRAME_ID, one.tag_ids[sel], corners[0, sel], margins[0, sel]
    )
    info = bagwrite.camera_info_msg(one, stamp_ns)
    return (
        bytes(ts.serialize_cdr(det, msgs.DETECTIONS)),
        bytes(ts.serialize_cdr(info, msgs.CAMERA_INFO)),
        int(sel.sum()),
    )


def image(
    renderer: Renderer,
    scene: Scene,
    scene_T_cam: F64,
    stamp_ns: int,
    rng: np.random.Generator,
    blind: bool = False,
) -> tuple[bytes, bytes]:
    """CDR ``(sensor_msgs/msg/Image rgb8, CameraInfo)`` of one rendered frame (the renderer of
    ``tagtrail simulate``); ``blind``: a black frame (the lens covered: no tag in view)."""
    c = scene.camera
    rgb = np.zeros((c.height, c.width, 3), np.uint8) if blind else renderer.render(scene_T_cam, rng)
    h, w = rgb.shape[:2]
    msg = bagwrite._t(msgs.IMAGE)(
        header=bagwrite._header(stamp_ns, FRAME_ID),
        height=h,
        width=w,
        encoding="rgb8",
        is_bigendian=0,
        step=3 * w,
        data=rgb.reshape(-1),
    )
    ts = msgs.typestore()
    return (
        bytes(ts.serialize_cdr(msg, msgs.IMAGE)),
        bytes(ts.serialize_cdr(bagwrite.camera_info_msg(scene, stamp_ns), msgs.CAMERA_INFO)),
    )
