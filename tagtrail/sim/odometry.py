"""The LIMO's wheel odometry: its error model, its ``/odom`` messages, its ``/tf_static`` mount.

One model for both drivers: :mod:`tagtrail.sim.follow` steps it live (the closed loop over
zenoh), :func:`odometry_stream` replays it along a scene's path for ``tagtrail simulate``.

Error model (:class:`WheelOdometry`): each wheel's speed is read with a fixed scale error
(drawn once per run, 1–3 %, either sign; or one given scale for both wheels), so distance is off
by their mean and yaw rate by their difference over the track (0.175 m); the yaw rate gets a
constant drift (drawn in ±0.3 °/s) and an over-read in turns proportional to the lateral
acceleration (3 % per m/s², skidding); a :class:`Slip` stretch over-reads both wheels by a
fraction (the wheels spin faster than the ground passes). ``/odom`` is ``nav_msgs/msg/Odometry``
(``odom`` → ``base_link``) at 50 Hz whose header stamp is the host time at publication: the
state it describes is older by a latency drawn in [2, 8] ms per message (NOTES "The LIMO").
Covariance: the LIMO's fixed placeholder (pose diag(0.1, 0.1, 0.1, 1, 1, 1), twist zero).

Frames: ``base_link`` is the rear-axle centre on the floor, x ahead, y left, z up; the camera's
optical frame (z ahead, x right, y down) sits ``Mount.forward_m`` ahead and ``Mount.height_m``
above it (:func:`base_T_cam`), so ``scene_T_cam = scene_T_base @ base_T_cam`` (the planar path
of :func:`tagtrail.sim.scene.scene_T_cam_planar`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tagtrail.errors import SpecError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.se3 import compose, inv, make_T, xyz_quat_from_T
from tagtrail.io import msgs
from tagtrail.sim.scene import Mount

TRACK_M = 0.175
ODOM_TOPIC = "/odom"
TF_STATIC_TOPIC = "/tf_static"
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
RATE_HZ = 50.0
LATENCY_NS = (2_000_000, 8_000_000)  # publication after measurement, drawn per message
SLIP_PER_MPS2 = 0.03
# The LIMO's placeholder (limo_base, Humble; NOTES): fixed, whatever the robot does.
POSE_COVARIANCE = np.diag([0.1, 0.1, 0.1, 1.0, 1.0, 1.0]).reshape(-1)
TWIST_COVARIANCE = np.zeros(36)


@dataclass(frozen=True)
class Slip:
    """A stretch of wheel slip: from ``start_s`` (s after the recording's first frame) for
    ``duration_s``, both wheels over-read their speed by ``fraction`` (0.2: 20 % too far)."""

    start_s: float
    duration_s: float
    fraction: float

    def __post_init__(self) -> None:
        vals = (self.start_s, self.duration_s, self.fraction)
        if not all(math.isfinite(v) for v in vals) or self.start_s < 0 or self.duration_s <= 0:
            raise SpecError("--odom-slip: start_s >= 0 and duration_s > 0 (e.g. 5,1,0.2)")
        if not -0.9 <= self.fraction <= 10.0:
            raise SpecError(f"--odom-slip: fraction {self.fraction:g} is out of range (-0.9..10)")

    def factor(self, t_s: float) -> float:
        """The wheels' over-read at ``t_s`` (s from the first frame): 1 + fraction inside."""
        inside = self.start_s <= t_s < self.start_s + self.duration_s
        return 1.0 + self.fraction if inside else 1.0


@dataclass(kw_only=True)
class Planar:
    """A planar pose ``(x, y, yaw)`` moving at speed ``v`` and yaw rate ``omega``."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    v: float = 0.0
    omega: float = 0.0

    def advance(self, dt: float) -> None:
        """Move by ``dt`` (s) at the current ``v``, ``omega`` (the mid-point heading)."""
        mid = self.yaw + 0.5 * self.omega * dt
        self.x += self.v * math.cos(mid) * dt
        self.y += self.v * math.sin(mid) * dt
        self.yaw += self.omega * dt


@dataclass
class WheelOdometry(Planar):
    """Dead reckoning from wheel speeds with the error model of the module docstring.

    ``scale_error``: both wheels read ``1 + scale_error`` times their speed (None: each wheel's
    scale drawn in ±[1, 3] %). The draws are the same either way, so a seed gives one drift."""

    rng: np.random.Generator
    scale_error: float | None = None
    scale_l: float = field(init=False)
    scale_r: float = field(init=False)
    drift_rps: float = field(init=False)
    slip_per_mps2: float = SLIP_PER_MPS2

    def __post_init__(self) -> None:
        sign = self.rng.choice([-1.0, 1.0], 2)
        self.scale_l, self.scale_r = 1.0 + sign * self.rng.uniform(0.01, 0.03, 2)
        self.drift_rps = math.radians(float(self.rng.uniform(-0.3, 0.3)))
        if self.scale_error is not None:
            self.scale_l = self.scale_r = 1.0 + self.scale_error

    def step(self, v: float, omega: float, dt: float, slip: float = 1.0) -> None:
        """Integrate the wheels' reading of the true (v m/s, omega rad/s) over ``dt`` s;
        ``slip``: both wheels over-read by this factor (:class:`Slip`)."""
        vl, vr = v - omega * TRACK_M / 2, v + omega * TRACK_M / 2
        ml, mr = vl * self.scale_l * slip, vr * self.scale_r * slip
        self.v = (ml + mr) / 2
        self.omega = (mr - ml) / TRACK_M * (
            1.0 + self.slip_per_mps2 * abs(v * omega)
        ) + self.drift_rps
        self.advance(dt)

    def message(self, stamp_ns: int) -> bytes:
        """CDR ``nav_msgs/msg/Odometry`` (frame odom → base_link), stamped ``stamp_ns``."""
        ts = msgs.typestore()
        return bytes(ts.serialize_cdr(self.msg(stamp_ns), ODOMETRY))

    def msg(self, stamp_ns: int) -> Any:
        """The ``nav_msgs/msg/Odometry`` message object of the current state."""
        t = msgs.typestore().types
        V3, Q = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](self.x, self.y, 0.0),
            orientation=Q(0.0, 0.0, math.sin(self.yaw / 2), math.cos(self.yaw / 2)),
        )
        return t[ODOMETRY](
            header=header(stamp_ns, ODOM_FRAME),
            child_frame_id=BASE_FRAME,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=pose, covariance=POSE_COVARIANCE.copy()
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=V3(self.v, 0.0, 0.0), angular=V3(0.0, 0.0, self.omega)
                ),
                covariance=TWIST_COVARIANCE.copy(),
            ),
        )


def header(t_ns: int, frame_id: str) -> Any:
    """A ``std_msgs/msg/Header`` stamped ``t_ns`` (int ns) in ``frame_id``."""
    t = msgs.typestore().types
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
    )


def latency_ns(rng: np.random.Generator) -> int:
    """One publication latency (ns), uniform in :data:`LATENCY_NS`."""
    return int(rng.uniform(*LATENCY_NS))


def base_T_cam(mount: Mount) -> F64:
    """``base_T_cam`` (4, 4): the camera's optical frame in ``base_link`` (module docstring)."""
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return np.asarray(make_T(R, np.array([mount.forward_m, 0.0, mount.height_m])))


def tf_static_msg(base_T_camera: F64, stamp_ns: int, camera_frame: str) -> Any:
    """``tf2_msgs/msg/TFMessage`` with the one transform base_link → ``camera_frame``."""
    t = msgs.typestore().types
    xyz, q = xyz_quat_from_T(base_T_camera)
    tf = t["geometry_msgs/msg/TransformStamped"](
        header=header(stamp_ns, BASE_FRAME),
        child_frame_id=camera_frame,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](*map(float, xyz)),
            rotation=t["geometry_msgs/msg/Quaternion"](*map(float, q)),
        ),
    )
    return t[TF_MESSAGE](transforms=[tf])


def tf_static_qos() -> list[Any]:
    """The offered QoS of ``/tf_static`` (transient local, reliable, keep last 1): a late
    subscriber of a replay still gets the mount."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return [
        Qos(
            QosHistory.KEEP_LAST,
            1,
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL,
            zero,
            zero,
            QosLiveliness.AUTOMATIC,
            zero,
            False,
        )
    ]


def planar(scene_T_base: F64) -> tuple[F64, F64]:
    """``(xy (N, 2) m, yaw (N,) rad, unwrapped)`` of planar base poses ``(N, 4, 4)``."""
    yaw = np.unwrap(np.arctan2(scene_T_base[:, 1, 0], scene_T_base[:, 0, 0]))
    return scene_T_base[:, :2, 3].copy(), yaw


def planar_T(x: float, y: float, yaw: float) -> F64:
    """``(4, 4)`` pose at (x, y) m on the floor, heading ``yaw`` rad about z."""
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray(make_T(R, np.array([x, y, 0.0])))


@dataclass(frozen=True)
class OdomSample:
    """One ``/odom`` message: header stamp (publication), measurement time, the true base pose
    ``scene_T_base`` (4, 4) at the measurement time, and the message."""

    stamp_ns: int
    meas_ns: int
    scene_T_base: F64
    msg: Any


def odometry_stream(
    scene_T_cam: F64,
    t_ns: np.ndarray,
    mount: Mount,
    rng: np.random.Generator,
    scale_error: float | None = None,
    slip: Slip | None = None,
) -> tuple[WheelOdometry, list[OdomSample]]:
    """The robot's ``/odom`` along a camera path ``scene_T_cam`` ``(N, 4, 4)`` at ``t_ns``.

    The base path is ``scene_T_cam @ inv(base_T_cam)``, interpolated (linear in x, y and the
    unwrapped yaw) at 50 Hz from the first frame's time to the last; true (v, omega) between
    two ticks are the chord over the tick (an error-free odometry, integrating with the midpoint
    rule, retraces the interpolated path exactly). Each message describes the state at its tick
    and is stamped a latency later (stamps stay in order: 20 ms ticks, 6 ms of jitter).
    Returns the odometry (its drawn errors) and the samples.
    """
    scene_T_base = compose(scene_T_cam, inv(base_T_cam(mount))[None])
    xy, yaw = planar(scene_T_base)
    t0 = int(t_ns[0])
    dt_ns = int(round(1e9 / RATE_HZ))
    ticks = np.arange(t0, int(t_ns[-1]) + 1, dt_ns, dtype=np.int64)
    rel = (np.asarray(t_ns, dtype=np.int64) - t0).astype(np.float64)
    tr = (ticks - t0).astype(np.float64)
    if len(t_ns) > 1:
        x, y, h = (np.interp(tr, rel, v) for v in (xy[:, 0], xy[:, 1], yaw))
    else:
        x, y, h = (np.full(len(ticks), v[0]) for v in (xy[:, 0], xy[:, 1], yaw))
    odo = WheelOdometry(rng, scale_error)
    samples: list[OdomSample] = []
    dt = dt_ns / 1e9
    for k, tick in enumerate(ticks):
        if k > 0:
            dx, dy, dh = x[k] - x[k - 1], y[k] - y[k - 1], h[k] - h[k - 1]
            mid = h[k - 1] + dh / 2
            ahead = dx * math.cos(mid) + dy * math.sin(mid)
            chord = math.copysign(math.hypot(dx, dy), ahead) if ahead else 0.0
            factor = slip.factor((int(ticks[k - 1]) - t0) / 1e9) if slip else 1.0
            odo.step(chord / dt, dh / dt, dt, factor)
        stamp = int(tick) + latency_ns(rng)
        samples.append(OdomSample(stamp, int(tick), planar_T(x[k], y[k], h[k]), odo.msg(stamp)))
    return odo, samples
