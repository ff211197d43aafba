"""The simulated LIMO: kinematics with limits, wheel odometry with errors, its camera's detections.

Plain numbers in and out (no zenoh): :mod:`tagtrail.sim.follow` drives it in a closed loop.

- :class:`Kinematics`: the base (rear-axle centre) at ``(x, y, yaw)`` in the scene frame (z up),
  obeying ``cmd_vel`` (v, omega) through a first-order lag (``tau_s``) after clipping to the
  LIMO's limits (NOTES "The LIMO"): |v| ≤ 1 m/s, Ackermann |omega| ≤ |v| / 0.4 m; no command
  for ``cmd_timeout_s``: the command is zero (the base's own watchdog).
- :class:`WheelOdometry`, the error model (scale error 1–3 % per wheel, yaw drift, slip in
  turns; ``/odom`` at 50 Hz stamped at publication, 2–8 ms after the state it describes): defined
  in :mod:`tagtrail.sim.odometry`, shared with ``tagtrail simulate``'s recorded ``/odom``.
- :func:`image`: a rendered frame (:class:`~tagtrail.sim.render.Renderer`), as the LIMO's
  camera driver publishes it (raw rgb8);
- :func:`detections`: the tags in view of the camera (mount of :class:`~tagtrail.sim.scene.Mount`)
  projected through the camera model with pixel noise, as ``tagtrail simulate --detections``
  (:func:`tagtrail.sim.bagwrite.synth_detections`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tagtrail.geometry.arrays import F64
from tagtrail.io import msgs
from tagtrail.sim import bagwrite
from tagtrail.sim.camera import FRAME_ID
from tagtrail.sim.odometry import TRACK_M as TRACK_M  # re-exported: the closed loop uses them
from tagtrail.sim.odometry import Planar
from tagtrail.sim.odometry import WheelOdometry as WheelOdometry
from tagtrail.sim.odometry import latency_ns as latency_ns
from tagtrail.sim.render import Renderer
from tagtrail.sim.scenarios import SimOptions
from tagtrail.sim.scene import Scene, scene_T_cam_planar

MAX_SPEED_MPS = 1.0
MIN_TURN_RADIUS_M = 0.4
WHEELBASE_M = 0.2


@dataclass
class Kinematics(Planar):
    """The base's true state and its response to commands (module docstring)."""

    tau_s: float = 0.1
    cmd_timeout_s: float = 0.5
    cmd: tuple[float, float] = (0.0, 0.0)
    t_cmd: float = -math.inf
    before: tuple[float, float, float] = (0.0, 0.0, -math.inf)  # the command before, its time

    def command(self, v: float, omega: float, t: float) -> None:
        """A ``cmd_vel`` at time ``t``; non-finite values are ignored (kept as zero)."""
        if not (math.isfinite(v) and math.isfinite(omega)):
            v = omega = 0.0
        v = max(-MAX_SPEED_MPS, min(MAX_SPEED_MPS, v))
        bound = abs(v) / MIN_TURN_RADIUS_M
        self.before = (*self.cmd, self.t_cmd)
        self.cmd, self.t_cmd = (v, max(-bound, min(bound, omega))), t

    def step(self, t: float, dt: float) -> None:
        """Advance by ``dt`` (s) to time ``t + dt``, under the command in force at ``t`` (a
        step caught up after a command came still takes the one before for its time)."""
        cmd, t_cmd = (
            (self.cmd, self.t_cmd) if t >= self.t_cmd else (self.before[:2], self.before[2])
        )
        v_c, w_c = cmd if t - t_cmd <= self.cmd_timeout_s else (0.0, 0.0)
        a = min(1.0, dt / self.tau_s)
        self.v += a * (v_c - self.v)
        self.omega += a * (w_c - self.omega)
        self.omega = max(
            -abs(self.v) / MIN_TURN_RADIUS_M, min(abs(self.v) / MIN_TURN_RADIUS_M, self.omega)
        )
        self.advance(dt)
        self.yaw = math.atan2(math.sin(self.yaw), math.cos(self.yaw))


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
