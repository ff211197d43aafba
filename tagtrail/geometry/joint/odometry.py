"""The wheel-odometry prior: the robot's own measure of how its base moved between two frames.

A wheeled robot integrates its wheel speeds (and, on the LIMO, its IMU's yaw) into a planar pose
``odom_T_base`` at about 50 Hz (``nav_msgs/Odometry``). Between consecutive frames ``j, j+1``
(stamps ``t_j``, s) the odometry's relative motion of the base, in the base frame at ``j``, is
``o_j = (ox, oy, otheta)``, read at ``t_j + offset`` (linear interpolation; the odometry's stamp
is when it was *published*, a few ms after the wheels were read, hence the ``offset``). The
same motion predicted by the cameras (``cam_T_world = (R, t)``) through the camera's mount::

    R_rel = R_j R_{j+1}^T,  p = R_j (c_{j+1} - c_j)        camera j+1 in camera j
    o     = -lever_m f                                       the base's origin in the camera
    d     = R_rel o + p - o                                  the base's step (camera j)
    dx, dy, dtheta = f . d,  s . d,  u . Log(R_rel)

``u`` is the ground plane's normal seen from the camera (the ground prior's :class:`Plane.u`
when it is on, else the plane fitted to the cameras, held fixed), ``f``/``s`` the robot's forward
and left axes in the camera frame and ``lever_m`` the camera's distance ahead of the base's
origin: the wheeled-drive prior's :class:`~.drive.Mount`, here an unknown of this prior (from
the recorded ``base_T_camera`` when there is one, else fitted as the drive prior fits it). The
odometry's errors are modelled as unknowns: ``scale`` (distance read ``scale`` times the true:
the wheels' mean scale error), ``yaw_scale`` (turns read ``yaw_scale`` times the true),
``yaw_per_m`` (yaw read per metre driven: the wheels' scale difference over the track) and
``yaw_drift_rps`` (a gyro's or the wheels' constant yaw drift). The odometry integrates its
distance along its own heading, so a step it reads turned by ``theta`` where the base turned by
``dtheta`` comes out bent by ``b = (theta - dtheta) / 2`` (the chords of two arcs, rates
constant within the step; first order in ``b``): two wheels 4 % apart read 0.22 rad a metre,
and a 4 cm step straight ahead is read 0.17 mm to the side, a lateral bias the cameras then
strained against. The whitened residual of step ``j`` (``h_j`` s)::

    theta = yaw_scale dtheta + yaw_per_m scale dx,   b = (theta - dtheta) / 2
    q_j = [ (scale (dx - b dy) - ox) / st ; (scale (dy + b dx) - oy) / st ;
            (theta + yaw_drift_rps h_j - otheta) / sr ]

with ``st^2 = sigma_m^2 |o_xy| + FLOOR_M^2`` and ``sr^2 = SIGMA_RAD^2 |otheta| + (SIGMA_RAD_PER_M
sqrt|o_xy|)^2 + FLOOR_RAD^2``: the error grows per metre and per radian travelled (slip, uneven
floor), with a floor for the stamps' jitter. A robust loss (Cauchy, 3 standard deviations) on
each step's 3-vector: a stretch of wheel slip stops counting instead of bending the trajectory.

Unknowns (:class:`OdometryState`, 7 parameters): the mount's yaw about ``u`` and its lever arm
(the drive prior's :meth:`Mount.update`), the time offset (bounded to ``MAX_OFFSET_S``), the
scale, the yaw scale, the yaw per metre and the yaw drift. The camera Jacobians are in closed
form (:meth:`OdometryPrior.camera_terms`), the unknowns' central differences of the prediction.

With the prior, frames with no tag in view but covered by the odometry get a pose
(:func:`extend_frames`): held by the odometry, the motion prior and the ground plane, their
uncertainty (the solver's covariance) growing with the distance from the last tag; not beyond
``MAX_DEAD_RECKONING_S`` from a frame with a tag (gaps beyond stay gaps).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.joint.drive import Mount, fit_mount
from tagtrail.geometry.joint.ground import Plane
from tagtrail.geometry.joint.problem import Terms
from tagtrail.geometry.robust import LossName, rho
from tagtrail.geometry.rotations import cross, log_so3, right_jacobian_inv
from tagtrail.geometry.se3 import R_from_quat_xyzw, R_from_rotvec, T_from_xyz_quat, inv, make_T

N_ODOM = 7  # mount yaw, lever arm, time offset, scale, yaw scale, yaw per metre, yaw drift
MAX_OFFSET_S = 0.5  # the time offset is solved within +-0.5 s (latency, a host clock's skew)
# the error model: 1 cm per sqrt(metre) of slip, 2 mm floor (the stamps' jitter at 0.5 m/s);
# 0.02 rad per sqrt(rad) turned, 0.01 rad per sqrt(m) driven, 0.2 deg floor
FLOOR_M = 0.002
SIGMA_RAD = 0.02
SIGMA_RAD_PER_M = 0.01
FLOOR_RAD = float(np.radians(0.2))
MAX_DEAD_RECKONING_S = 10.0  # frames further than this from a frame with a tag get no pose
ODOM_LOSS: LossName = "cauchy"  # each step's robust loss, at ODOM_F_SCALE standard deviations
ODOM_F_SCALE = 3.0
ODOM_BOUND = 2.0  # the prior's robust chi^2 per degree of freedom, in the variance factor
# What the odometry's errors are before the data says otherwise (weak priors on the unknowns,
# so a straight drive, which cannot tell a turn's scale, leaves it near 1 instead of anywhere):
# wheel scales within a few %, the yaw per metre of two wheels a few % apart over a 0.175 m
# track, a gyro's or wheels' drift under a degree a second, a latency well under a second.
SCALE_SIGMA, YAW_SCALE_SIGMA, YAW_PER_M_SIGMA = 0.05, 0.05, 0.5
DRIFT_SIGMA_RPS, OFFSET_SIGMA_S = 0.01, 0.2
# A recorded mount (/tf_static) holds the solved one within 2 cm and 2 deg unless the motion
# says otherwise: a straight drive, which cannot tell the lever arm, keeps the recorded one.
MOUNT_LEVER_SIGMA_M, MOUNT_YAW_SIGMA_RAD = 0.02, float(np.radians(2.0))
_EPS = 1e-6  # central-difference step (rad, m, s)


@dataclass(frozen=True)
class Odometry:
    """Wheel odometry: stamps ``t_s (N,)`` (s, on the frames' clock: from the first frame's
    stamp, increasing) and the base's planar pose ``x, y`` (m) and ``yaw`` (rad, unwrapped) in
    the odometry frame; ``topic`` names it in log lines."""

    t_s: F64
    x: F64
    y: F64
    yaw: F64
    topic: str = "odometry"

    def at(self, t: F64) -> F64:
        """The pose ``(len(t), 3)`` ``[x, y, yaw]`` at times ``t`` (clamped to the range)."""
        return np.stack([np.interp(t, self.t_s, v) for v in (self.x, self.y, self.yaw)], axis=1)

    def relative(self, ta: F64, tb: F64) -> F64:
        """The base's motion ``(P, 3)`` from ``ta`` to ``tb``: ``[dx, dy, dyaw]`` in the base
        frame at ``ta``."""
        a, b = self.at(ta), self.at(tb)
        c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
        ex, ey = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        return np.stack([c * ex + s * ey, -s * ex + c * ey, b[:, 2] - a[:, 2]], axis=1)

    def covers(self, t: F64, margin: float = 0.0) -> np.ndarray:
        """Whether times ``t`` lie within the odometry's stamps (``margin`` s inside)."""
        return np.asarray((t >= self.t_s[0] + margin) & (t <= self.t_s[-1] - margin))

    def extended(self, t: float, max_s: float) -> Odometry:
        """The odometry carried on to ``t`` (s) at its last step's speed and turn rate (in the
        base's frame, :func:`carried_on`), when ``t`` is past the last stamp by at most
        ``max_s``; else itself. What a frame taken since the last message needs (a live
        frame's arrives after it)."""
        ahead = t - float(self.t_s[-1])
        if not 0.0 < ahead <= max_s or len(self.t_s) < 2:
            return self
        f = ahead / float(self.t_s[-1] - self.t_s[-2])
        a = (float(self.x[-2]), float(self.y[-2]), float(self.yaw[-2]))
        b = (float(self.x[-1]), float(self.y[-1]), float(self.yaw[-1]))
        x, y, yaw = carried_on(a, b, f)
        return replace(
            self,
            t_s=np.append(self.t_s, t),
            x=np.append(self.x, x),
            y=np.append(self.y, y),
            yaw=np.append(self.yaw, yaw),
        )


Pose2 = tuple[float, float, float]
"""A planar pose ``(x, y, yaw)`` of the base in the odometry's frame."""


def planar_step(a: Pose2, b: Pose2) -> Pose2:
    """The base's motion ``(dx, dy, dyaw)`` from pose ``a`` to ``b`` in its frame at ``a``
    (the yaw's change wrapped to +-pi): :meth:`Odometry.relative` for one step, in scalars
    (a live node's per-message work, where numpy's overhead on three numbers dominates)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    ex, ey = b[0] - a[0], b[1] - a[1]
    dyaw = math.atan2(math.sin(b[2] - a[2]), math.cos(b[2] - a[2]))
    return c * ex + s * ey, -s * ex + c * ey, dyaw


def carried_on(a: Pose2, b: Pose2, f: float) -> Pose2:
    """The pose past ``b`` by ``f`` times the step from ``a`` to ``b``, at that step's speed
    and turn rate in the base's frame: f of the step's twist (SE(2)'s log), its exp from
    ``b`` -- exact on an arc."""
    dx, dy, th = planar_step(a, b)
    p, q = _sinc_cosc(th)
    det = p * p + q * q
    vx, vy = (p * dx + q * dy) / det * f, (p * dy - q * dx) / det * f
    p, q = _sinc_cosc(th * f)
    sx, sy = p * vx - q * vy, q * vx + p * vy
    c, s = math.cos(b[2]), math.sin(b[2])
    return b[0] + c * sx - s * sy, b[1] + s * sx + c * sy, b[2] + th * f


def _sinc_cosc(th: float) -> tuple[float, float]:
    """``sin(th)/th`` and ``(1 - cos(th))/th`` (their series near 0): SE(2)'s exp takes a twist
    ``v`` to the step ``[[a, -b], [b, a]] v``."""
    if abs(th) < 1e-4:
        return 1.0 - th * th / 6.0, th / 2.0 - th**3 / 24.0
    return math.sin(th) / th, (1.0 - math.cos(th)) / th


@dataclass
class StampGrid:
    """Stamps of a fixed-rate stream put back on the clock it samples on. A driver that reads
    its wheels on a timer and stamps each message at publication (the LIMO's ``/odom``, NOTES)
    adds a latency that changes per message (2-8 ms): at 1 m/s, millimetres of pose in every
    sample, more than a tag fix's error. The samples lie on a grid: the least-squares line of
    the last ``window`` stamps against their index puts each new one on it (its offset is the
    mean latency, which the caller's fixed latency takes off). A stream on no grid passes as it
    is: a step that is not a whole number of periods (40 % off) starts the grid again, and
    residuals over a quarter period leave the stamps raw. Live, :meth:`add` takes each message
    as it arrives (the newest stamp on the line's end: ~2 standard deviations of the jitter over
    the square root of the window); offline :func:`on_grid` runs it over the recording."""

    window: int = 50
    _k: deque[int] = field(default_factory=deque)
    _t: deque[int] = field(default_factory=deque)
    _period: float = 0.0

    def add(self, t_ns: int) -> int:
        """The stamp ``t_ns`` (ns) on the grid (as it is while the grid is not known)."""
        k, t = self._k, self._t
        if t and t_ns <= t[-1]:
            return t_ns
        if len(t) >= 4 and self._period == 0.0:
            self._period = float(np.median(np.diff(np.asarray(t, np.float64))))
        if self._period > 0.0:
            m = (t_ns - t[-1]) / self._period
            if m < 0.5 or abs(m - round(m)) > 0.4:
                k.clear()
                t.clear()
                self._period = 0.0
        k.append(k[-1] + max(round((t_ns - t[-1]) / self._period), 1) if self._period else len(k))
        t.append(t_ns)
        while len(t) > self.window:
            k.popleft()
            t.popleft()
        if len(t) < 10:
            return t_ns
        kk = np.asarray(k, np.float64) - k[0]
        tt = np.asarray(t, np.float64) - t[0]
        kc, tc = kk - kk.mean(), tt - tt.mean()
        slope = float(kc @ tc / (kc @ kc))
        if slope <= 0.0:
            return t_ns
        self._period = slope
        resid = tc - slope * kc
        if float(np.sqrt(resid @ resid / len(resid))) > 0.25 * slope:
            return t_ns
        return t[0] + int(round(tt.mean() + slope * kc[-1]))


def on_grid(t_ns: I64) -> I64:
    """Stamps ``t_ns (N,)`` of a recorded stream put on its grid (:class:`StampGrid`, as live);
    as they are where the result would not be increasing."""
    g = StampGrid()
    out = np.array([g.add(int(v)) for v in np.asarray(t_ns, np.int64)], np.int64)
    return out if (np.diff(out) > 0).all() else np.asarray(t_ns, np.int64)


def odometry_from_table(
    t_ns: I64, pose: F64, var: F64 | None, t0_ns: int, topic: str = "odometry"
) -> tuple[Odometry | None, str]:
    """The :class:`Odometry` of ``extract.odometry`` rows (stamps ``t_ns (N,)``, ``pose (N, 7)``
    ``x, y, z, qx, qy, qz, qw`` of ``odom_T_base``, variances ``var (N, 3)`` of x, y, yaw or
    None) on the frames' clock (``t0_ns``: the first frame's stamp); or None and why, in plain
    words: no message, a single one, a NaN pose, stamps that go back or repeat, a covariance of
    zeros or none at all (``extract`` writes NaN variances for a zero covariance; a driver that
    does not fill it in claims a certainty nobody has)."""
    t_ns = np.asarray(t_ns, np.int64)
    pose = np.asarray(pose, np.float64).reshape(-1, 7)
    if len(t_ns) == 0:
        return None, "no message"
    if len(t_ns) < 2:
        return None, "a single message, no motion to read"
    if not np.isfinite(pose).all():
        return None, f"{int((~np.isfinite(pose).all(axis=1)).sum())} messages with NaN poses"
    if (np.diff(t_ns) <= 0).any():
        return None, f"its stamps go back {int((np.diff(t_ns) <= 0).sum())} times"
    if var is not None:
        v = np.asarray(var, np.float64).reshape(len(t_ns), -1)
        fin = np.isfinite(v)
        if not fin.any() or np.all(v[fin] == 0.0):  # extract writes NaN for a zero covariance
            return None, "its covariance is all zeros or not given"
    q = pose[:, 3:]
    nq = np.linalg.norm(q, axis=1)
    if (nq < 1e-6).any():
        return None, "messages with a zero quaternion"
    R = R_from_quat_xyzw(q / nq[:, None])
    yaw = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    t_ns = on_grid(t_ns)
    return (
        Odometry(
            np.asarray((t_ns - t0_ns) * 1e-9, np.float64),
            pose[:, 0].copy(),
            pose[:, 1].copy(),
            np.asarray(yaw, np.float64),
            topic,
        ),
        "",
    )


def mount_from_base_T_camera(xyz_quat: F64, u: F64) -> Mount:
    """The :class:`Mount` of a recorded ``base_T_camera`` ``[x, y, z, qx, qy, qz, qw]``: the
    base's forward axis seen from the camera (across the plane's normal ``u``), the camera's
    offset ahead of the base's origin (its sideways offset is not modelled: the drive prior's
    mount has none)."""
    v = np.asarray(xyz_quat, np.float64)
    R = R_from_quat_xyzw(v[3:] / np.linalg.norm(v[3:]))  # base_R_camera
    g = R.T @ np.array([1.0, 0.0, 0.0])
    uh = u / np.linalg.norm(u)
    g = g - (g @ uh) * uh
    return Mount(g / np.linalg.norm(g), float(v[0]))


@dataclass(frozen=True)
class OdometryState:
    """The prior's unknowns (module docstring)."""

    mount: Mount
    offset_s: float = 0.0
    scale: float = 1.0
    yaw_scale: float = 1.0
    yaw_per_m: float = 0.0
    yaw_drift_rps: float = 0.0

    def update(self, step: F64, u: F64) -> OdometryState:
        """The state after a step of its 7 parameters (``u``: the plane's camera-frame normal)."""
        return OdometryState(
            self.mount.update(step[:2], u),
            float(np.clip(self.offset_s + step[2], -MAX_OFFSET_S, MAX_OFFSET_S)),
            self.scale + float(step[3]),
            self.yaw_scale + float(step[4]),
            self.yaw_per_m + float(step[5]),
            self.yaw_drift_rps + float(step[6]),
        )


def predict(Ra: F64, ta: F64, Rb: F64, tb: F64, u: F64, mount: Mount) -> F64:
    """The base's motion ``(P, 3)`` ``[dx, dy, dtheta]`` between cameras ``a`` and ``b``
    (``cam_T_world``, ``(P, 3, 3), (P, 3)``), in the base frame at ``a`` (module docstring)."""
    uh = u / np.linalg.norm(u)
    s = mount.lateral(uh)[0]
    f = cross(s, uh)
    R_rel = Ra @ np.swapaxes(Rb, 1, 2)
    ca = -np.einsum("pji,pj->pi", Ra, ta)
    cb = -np.einsum("pji,pj->pi", Rb, tb)
    p = np.einsum("pij,pj->pi", Ra, cb - ca)
    o = -mount.lever_m * f
    d = R_rel @ o + p - o
    return np.stack([d @ f, d @ s, log_so3(R_rel) @ uh], axis=1)


def step_sigmas(o: F64, sigma_m: float) -> tuple[F64, F64]:
    """Each step's ``st``, ``sr`` ``(P,)`` (module docstring) from the odometry's readings
    ``o (P, 3)``."""
    dist = np.hypot(o[:, 0], o[:, 1])
    st = np.sqrt(sigma_m**2 * dist + FLOOR_M**2)
    sr = np.sqrt(SIGMA_RAD**2 * np.abs(o[:, 2]) + SIGMA_RAD_PER_M**2 * dist + FLOOR_RAD**2)
    return st, sr


def reading_model(pr: F64, st: OdometryState) -> F64:
    """What the odometry reads ``(..., P, 3)`` for the base's true steps ``pr (..., P, 3)``
    under its errors ``st``, but the drift (module docstring): ``[scale (dx - b dy), scale (dy
    + b dx), yaw_scale dtheta + yaw_per_m scale dx]``, ``b`` the bend of its path."""
    dx, dy, dth = pr[..., 0], pr[..., 1], pr[..., 2]
    th = st.yaw_scale * dth + st.yaw_per_m * st.scale * dx
    b = 0.5 * (th - dth)
    return np.stack([st.scale * (dx - b * dy), st.scale * (dy + b * dx), th], axis=-1)


def whiten(m: F64, o: F64, drift: F64, sig_t: F64, sig_r: F64) -> F64:
    """Whitened residuals ``(..., P, 3)`` of modelled readings ``m (..., P, 3)``
    (:func:`reading_model`) plus the drift's yaw ``drift (P,)`` against the read ``o (P,
    3)``."""
    return np.stack(
        [
            (m[..., 0] - o[:, 0]) / sig_t,
            (m[..., 1] - o[:, 1]) / sig_t,
            (m[..., 2] + drift - o[:, 2]) / sig_r,
        ],
        axis=-1,
    )


def step_model(Ra: F64, ta: F64, Rb: F64, tb: F64, u: F64, st: OdometryState) -> tuple[F64, F64]:
    """The readings the odometry should give ``(P, 3)`` (:func:`reading_model`) between
    cameras ``a`` and ``b`` (``cam_T_world``, ``(P, 3, 3), (P, 3)``) and their Jacobians
    ``(P, 3, 2, 6)`` (reading, frame, ``[w ; v]``) on the two cameras, in closed form: under
    the joint solve's left perturbations (``R <- Exp(w) R``, ``c <- c - R^T v``) the base's
    step ``d = R_rel o + p - o`` moves by ``-[R_rel o + p]x w_a + v_a + R_rel [o]x w_b - R_rel
    v_b`` and ``Log R_rel`` by ``J_l^-1 w_a - J_r^-1 w_b`` (``J_l^-1 = J_r^-T``). Nothing of
    the odometry's own readings: a live step takes it before they arrive."""
    uh = u / np.linalg.norm(u)
    s = st.mount.lateral(uh)[0]
    f = cross(s, uh)
    R_rel = Ra @ np.swapaxes(Rb, 1, 2)
    dc = np.einsum("pji,pj->pi", Ra, ta) - np.einsum("pji,pj->pi", Rb, tb)  # c_b - c_a
    o = -st.mount.lever_m * f
    a = R_rel @ o + np.einsum("pij,pj->pi", Ra, dc)  # d + o
    e = log_so3(R_rel)
    pr = np.stack([(a - o) @ f, (a - o) @ s, e @ uh], axis=1)
    m = reading_model(pr, st)
    Jinv = right_jacobian_inv(e)
    D = np.empty((len(Ra), 3, 2, 6))  # of the true step pr: dx, dy, dtheta
    for row, ax in ((0, f), (1, s)):  # f . d and s . d
        Rta = np.einsum("pji,j->pi", R_rel, ax)
        D[:, row, 0, :3] = cross(a, ax)
        D[:, row, 0, 3:] = ax
        D[:, row, 1, :3] = cross(Rta, o)
        D[:, row, 1, 3:] = -Rta
    D[:, 2, 0, :3] = np.einsum("pij,j->pi", Jinv, uh)  # u . Log R_rel
    D[:, 2, 1, :3] = -np.einsum("pji,j->pi", Jinv, uh)
    D[:, 2, :, 3:] = 0.0
    # the reading (reading_model) through its bend b = ((yaw_scale - 1) dtheta + yaw_per_m
    # scale dx) / 2
    k = st.yaw_per_m * st.scale
    dx, dy = pr[:, 0, None, None], pr[:, 1, None, None]
    b = (0.5 * ((st.yaw_scale - 1.0) * pr[:, 2] + k * pr[:, 0]))[:, None, None]
    Db = 0.5 * ((st.yaw_scale - 1.0) * D[:, 2] + k * D[:, 0])
    J = np.empty_like(D)
    J[:, 0] = st.scale * (D[:, 0] - b * D[:, 1] - dy * Db)
    J[:, 1] = st.scale * (D[:, 1] + b * D[:, 0] + dx * Db)
    J[:, 2] = st.yaw_scale * D[:, 2] + k * D[:, 0]
    return m, J


@dataclass(frozen=True)
class OdometryPrior:
    """The odometry prior as a part of the joint solve (:class:`~.problem.Prior`): the
    odometry ``odo``, the frames' stamps ``t_s (F,)`` (s), the steps ``j (P,)`` it ties (frame
    ``j`` to ``j + 1``), the slip per sqrt(metre) ``sigma_m``; the plane: the ground prior's
    unknown when ``grounded`` (then ``uses`` it), else ``plane`` held fixed; its unknowns from
    ``start``."""

    odo: Odometry
    t_s: F64
    j: I64
    sigma_m: float
    start: OdometryState
    plane: Plane
    grounded: bool = False
    recorded: Mount | None = None
    loss: LossName = ODOM_LOSS
    f_scale: float = ODOM_F_SCALE

    name = "odometry"
    n_params = N_ODOM

    @property
    def uses(self) -> tuple[str, ...]:
        return ("ground", "odometry") if self.grounded else ("odometry",)

    @cached_property
    def _sigmas(self) -> tuple[F64, F64]:
        """Each step's ``st``, ``sr`` (module docstring), from the odometry at the start."""
        return step_sigmas(self._measured_at_start, self.sigma_m)

    def measured(self, offset_s: float) -> F64:
        """The odometry's motion of each step ``(P, 3)`` read at the frames' stamps + offset."""
        if offset_s == self.start.offset_s:  # the sigmas' and, offset held, every solve's
            return self._measured_at_start
        return self.odo.relative(self.t_s[self.j] + offset_s, self.t_s[self.j + 1] + offset_s)

    @cached_property
    def _measured_at_start(self) -> F64:
        o = self.odo.relative(
            self.t_s[self.j] + self.start.offset_s, self.t_s[self.j + 1] + self.start.offset_s
        )
        o.setflags(write=False)  # shared: read only
        return o

    def _u(self, values: Mapping[str, Any]) -> F64:
        return np.asarray(values["ground"].u if self.grounded else self.plane.u)

    def raw(
        self, Ra: F64, ta: F64, Rb: F64, tb: F64, u: F64, st: OdometryState, meas: F64 | None = None
    ) -> F64:
        """Whitened residuals ``(P, 3)`` before the robust weights."""
        pr = predict(Ra, ta, Rb, tb, u, st.mount)
        return self._whiten(pr, st, self.measured(st.offset_s) if meas is None else meas)

    def _whiten(self, pr: F64, st: OdometryState, o: F64) -> F64:
        """Whitened residuals ``(..., P, 3)`` of predicted steps ``pr (..., P, 3)`` against the
        measured ``o (P, 3)``."""
        h = self.t_s[self.j + 1] - self.t_s[self.j]
        return whiten(reading_model(pr, st), o, st.yaw_drift_rps * h, *self._sigmas)

    def residuals(self, R_cam: F64, t_cam: F64, values: Mapping[str, Any]) -> F64:
        """Whitened residuals ``(P, 3)`` at cameras ``cam_T_world`` and the unknowns."""
        j = self.j
        return self.raw(
            R_cam[j], t_cam[j], R_cam[j + 1], t_cam[j + 1], self._u(values), values[self.name]
        )

    def weights(self, q: F64) -> tuple[F64, F64]:
        """Per-step robust cost and IRLS weight ``(P,)`` of whitened residuals ``q (P, 3)``."""
        f2 = self.f_scale**2
        val, w = rho(self.loss, np.sum(q * q, axis=1) / f2)
        return f2 * val, w

    def jacobians(self, R_cam: F64, t_cam: F64, values: Mapping[str, Any]) -> tuple[F64, F64]:
        """``Jc (P, 2, 3, 6)`` on the cameras ``[w ; v]`` of frames ``j, j+1`` and ``Jg (P, 3,
        G)`` on the unknowns ``uses`` names (the plane's 6 then this prior's 7, or its 7)."""
        j = self.j
        Ra, ta, Rb, tb = R_cam[j], t_cam[j], R_cam[j + 1], t_cam[j + 1]
        u, st = self._u(values), values[self.name]
        meas = self.measured(st.offset_s)
        Jc = self.camera_terms(Ra, ta, Rb, tb, u, st, meas)[1]
        cols: list[F64] = []
        if self.grounded:
            plane: Plane = values["ground"]
            for k in range(6):
                e = np.zeros(6)
                e[k] = _EPS
                qp = self.raw(Ra, ta, Rb, tb, plane.update(e).u, st, meas)
                qm = self.raw(Ra, ta, Rb, tb, plane.update(-e).u, st, meas)
                cols.append((qp - qm) / (2 * _EPS))
        for k in range(N_ODOM):
            e = np.zeros(N_ODOM)
            e[k] = _EPS
            sp, sm = _nudge(st, e, u), _nudge(st, -e, u)
            qp = self.raw(Ra, ta, Rb, tb, u, sp, None if k == 2 else meas)
            qm = self.raw(Ra, ta, Rb, tb, u, sm, None if k == 2 else meas)
            cols.append((qp - qm) / (2 * _EPS))
        return Jc, np.stack(cols, axis=2)

    def camera_terms(
        self, Ra: F64, ta: F64, Rb: F64, tb: F64, u: F64, st: OdometryState, meas: F64
    ) -> tuple[F64, F64]:
        """The whitened residuals ``(P, 3)`` (as :meth:`raw`) and their Jacobians ``Jc (P, 2,
        3, 6)`` on the cameras ``[w ; v]`` of frames ``j, j+1`` (``Ra, ta``, ``Rb, tb``), in
        closed form (:func:`step_model`; the whitening is linear in the readings)."""
        m, J = step_model(Ra, ta, Rb, tb, u, st)
        h = self.t_s[self.j + 1] - self.t_s[self.j]
        sig_t, sig_r = self._sigmas
        q = whiten(m, meas, st.yaw_drift_rps * h, sig_t, sig_r)
        sig = np.stack([sig_t, sig_t, sig_r], axis=1)
        return q, np.transpose(J / sig[:, :, None, None], (0, 2, 1, 3))

    def terms(self, R_cam: F64, t_cam: F64, values: Mapping[str, Any]) -> Terms:
        """Each step's whitened 3-vector (robust), then two rows of the weak priors on the
        unknowns (``SCALE_SIGMA`` ...; tied to no frame); 3 degrees of freedom a step plus the
        priors' 5 less the unknowns' 7."""
        q = self.residuals(R_cam, t_cam, values)
        val, w = self.weights(q)
        Jc, Jg = self.jacobians(R_cam, t_cam, values)
        s = np.sqrt(w)
        st: OdometryState = values[self.name]
        sig = np.array(
            [SCALE_SIGMA, YAW_SCALE_SIGMA, YAW_PER_M_SIGMA, DRIFT_SIGMA_RPS, OFFSET_SIGMA_S]
        )
        pr = np.array(
            [st.scale - 1.0, st.yaw_scale - 1.0, st.yaw_per_m, st.yaw_drift_rps, st.offset_s]
        )
        r0 = np.zeros((3, 3))
        r0.reshape(-1)[:5] = pr / sig
        G = Jg.shape[2]
        J0 = np.zeros((3, 3, G))
        own = G - N_ODOM  # the plane's columns first, when it rides on the ground prior's
        for row, col in enumerate((3, 4, 5, 6, 2)):  # scale, yaw scale, per metre, drift, offset
            J0[row // 3, row % 3, own + col] = 1.0 / sig[row]
        if self.recorded is not None:  # the mount's yaw (turned about u) and lever arm
            u = self._u(values)
            uh = u / np.linalg.norm(u)
            a, b = self.recorded.g, st.mount.g
            r0[2, 0] = np.arctan2(cross(a, b) @ uh, a @ b) / MOUNT_YAW_SIGMA_RAD
            r0[2, 1] = (st.mount.lever_m - self.recorded.lever_m) / MOUNT_LEVER_SIGMA_M
            J0[2, 0, own] = 1.0 / MOUNT_YAW_SIGMA_RAD
            J0[2, 1, own + 1] = 1.0 / MOUNT_LEVER_SIGMA_M
        return Terms(
            float(val.sum() + np.sum(r0 * r0)),
            np.concatenate([q * s[:, None], r0]),
            np.concatenate([self.j, np.zeros(3, np.int64)]),
            np.concatenate([Jc * s[:, None, None, None], np.zeros((3, *Jc.shape[1:]))]),
            np.concatenate([Jg * s[:, None, None], J0]),
            3 * len(self.j) + 5 + (2 if self.recorded is not None else 0) - N_ODOM,
        )

    def update(self, value: OdometryState, step: F64, values: Mapping[str, Any]) -> OdometryState:
        return value.update(step, self._u(values))


def _nudge(st: OdometryState, e: F64, u: F64) -> OdometryState:
    """``st`` moved by ``e`` without the offset's clip (a difference quotient at the bound)."""
    out = st.update(e, u)
    return replace(out, offset_s=st.offset_s + float(e[2]))


def covered_steps(t_s: F64, odo: Odometry, max_gap_s: float, margin: float) -> I64:
    """Steps ``j (P,)``: consecutive frames within ``max_gap_s`` both inside the odometry's
    stamps by ``margin`` s (room for the time offset)."""
    t = np.asarray(t_s, np.float64)
    dt = np.diff(t)
    ok = (dt > 0) & (dt <= max_gap_s) & odo.covers(t[:-1], margin) & odo.covers(t[1:], margin)
    return np.flatnonzero(ok).astype(np.int64)


def fit_yaw(cam_yaw: F64, ox: F64, h: F64, otheta: F64) -> tuple[float, float, float]:
    """The odometry's yaw errors ``(yaw_scale, yaw_per_m, yaw_drift_rps)`` that fit steps of
    known turns: the cameras' yaw ``cam_yaw (P,)`` (rad), the odometry's forward step ``ox``
    (m), the steps' durations ``h`` (s) and the odometry's yaw ``otheta`` (rad) -- the prior's
    model ``otheta = yaw_scale cam_yaw + yaw_per_m ox + yaw_drift_rps h``, weighed by its yaw
    noise, robust (Cauchy at 3 standard deviations) and held near ``(1, 0, 0)`` by the weak
    priors the offline solve uses (a steady arc cannot tell a turn's scale from a drift)."""
    X = np.stack([cam_yaw, ox, h], axis=1)
    inv_var = 1.0 / (SIGMA_RAD**2 * np.abs(otheta) + SIGMA_RAD_PER_M**2 * np.abs(ox) + FLOOR_RAD**2)
    prior = np.diag(1.0 / np.array([YAW_SCALE_SIGMA, YAW_PER_M_SIGMA, DRIFT_SIGMA_RPS]) ** 2)
    beta0 = np.array([1.0, 0.0, 0.0])
    beta, w = beta0, np.ones(len(otheta))
    for _ in range(5):  # IRLS
        Xw = X * (w * inv_var)[:, None]
        beta = np.linalg.solve(X.T @ Xw + prior, Xw.T @ otheta + prior @ beta0)
        z = (otheta - X @ beta) ** 2 * inv_var / 9.0
        w = rho("cauchy", z)[1]
    return float(beta[0]), float(beta[1]), float(beta[2])


def fit_state(
    R_cam: F64,
    t_cam: F64,
    t_s: F64,
    odo: Odometry,
    plane: Plane,
    mount: Mount | None,
    max_gap_s: float,
    sigma_m: float,
) -> OdometryState:
    """The unknowns that fit fixed cameras: the time offset first, by the turn rates (a grid of
    5 ms over +-``MAX_OFFSET_S``, the yaw scale and drift by least squares at each), then
    Gauss-Newton on all 7 (the mount from ``mount`` when given, else the drive prior's
    :func:`~.drive.fit_mount`)."""
    margin = MAX_OFFSET_S + 0.01
    j = covered_steps(t_s, odo, max_gap_s, margin)
    if mount is None:
        mount = fit_mount(R_cam, t_cam, t_s, j, plane)
    state = OdometryState(mount)
    if len(j) < 4:
        return state
    u = plane.u / np.linalg.norm(plane.u)
    cam_yaw = log_so3(R_cam[j] @ np.swapaxes(R_cam[j + 1], 1, 2)) @ u
    h = t_s[j + 1] - t_s[j]
    grid = np.arange(-MAX_OFFSET_S, MAX_OFFSET_S + 1e-9, 0.005)
    costs = np.zeros(len(grid))
    A = np.stack([cam_yaw, h], axis=1)
    for i, off in enumerate(grid):
        oy = odo.relative(t_s[j] + off, t_s[j + 1] + off)[:, 2]
        sol, *_ = np.linalg.lstsq(A, oy, rcond=None)
        r = oy - A @ sol
        costs[i] = float(np.sum(np.minimum(r * r, np.radians(2.0) ** 2)))
    # of the offsets the turns cannot tell apart (a straight drive: all), the one nearest 0
    tie = costs <= costs.min() * (1.0 + 1e-3) + 1e-12
    state = replace(state, offset_s=float(grid[tie][np.argmin(np.abs(grid[tie]))]))
    prior = OdometryPrior(odo, t_s, j, sigma_m, state, plane)
    for _ in range(10):
        vals = {"odometry": state}
        q = prior.residuals(R_cam, t_cam, vals)
        _, w = prior.weights(q)
        _, Jg = prior.jacobians(R_cam, t_cam, vals)
        sw = np.sqrt(w)[:, None, None]
        A = (Jg * sw).reshape(-1, N_ODOM)
        b = (q * sw[:, :, 0]).reshape(-1)
        H = A.T @ A + 1e-9 * np.trace(A.T @ A) / N_ODOM * np.eye(N_ODOM)
        step = -np.linalg.solve(H, A.T @ b)
        state = state.update(step, plane.u)
        if np.abs(step).max() < 1e-9:
            break
    return state


def dead_reckon(
    R_cam: F64,
    t_cam: F64,
    posed: np.ndarray,
    t_s: F64,
    odo: Odometry,
    u: F64,
    state: OdometryState,
) -> tuple[F64, F64]:
    """Start poses for the frames not ``posed`` (``(F,)`` bool): each from the nearest posed
    frame before it (else after it), moved by the odometry between them (corrected by the
    state's scale and yaw terms) through the mount. Returns ``cam_T_world`` ``(F, 3, 3), (F,
    3)``."""
    R, t = R_cam.copy(), t_cam.copy()
    idx = np.flatnonzero(posed)
    uh = u / np.linalg.norm(u)
    s = state.mount.lateral(uh)[0]
    f = cross(s, uh)
    base_R = np.stack([f, s, uh], axis=1)  # cam_R_base: columns = base axes in the camera
    lever = state.mount.lever_m
    for k in np.flatnonzero(~posed):
        before = idx[idx < k]
        ref = int(before[-1]) if len(before) else int(idx[idx > k][0])
        o = odo.relative(
            np.array([t_s[ref] + state.offset_s]), np.array([t_s[k] + state.offset_s])
        )[0]
        yaw = (o[2] - state.yaw_drift_rps * (t_s[k] - t_s[ref]) - state.yaw_per_m * o[0]) / max(
            state.yaw_scale, 1e-3
        )
        dist = o[:2] / state.scale  # a start: the path's bend (reading_model) left to the solve
        # base_ref_T_base_k, then cam_ref_T_cam_k = cam_T_base base_ref_T_base_k base_T_cam
        Rb = R_from_rotvec(np.array([[0.0, 0.0, yaw]]))[0]
        tb = np.array([dist[0], dist[1], 0.0])
        R_ck = base_R @ Rb @ base_R.T  # cam_ref_R_cam_k
        # base origin in the camera: -lever f; cam_T_base = (base_R, -lever f)
        o_cam = -lever * f
        p = base_R @ tb + o_cam - R_ck @ o_cam  # camera k's centre in camera ref
        c_ref = -R[ref].T @ t[ref]
        c_k = c_ref + R[ref].T @ p
        R[k] = R_ck.T @ R[ref]
        t[k] = -R[k] @ c_k
    return R, t


@dataclass(frozen=True)
class OdometryReport:
    """What the odometry prior decided and found: ``mode`` (auto, on, off), whether it was
    applied and why (``why``, plain words), the topic, the solved time offset (ms, the
    odometry's stamps later than the frames' by it), scale, yaw scale, yaw per metre (deg/m) and
    drift (deg/s), the mount (lever arm m, camera yaw deg from the robot's forward axis, its
    source), the strain that decided ``auto``, the fraction of steps the robust loss
    down-weighted (beyond its scale), the steps tied and the frames posed by odometry alone
    (no tag in view)."""

    mode: str
    applied: bool
    why: str
    topic: str = "odometry"
    offset_ms: float = float("nan")
    scale: float = float("nan")
    yaw_scale: float = float("nan")
    yaw_per_m_deg: float = float("nan")
    yaw_drift_dps: float = float("nan")
    lever_m: float = float("nan")
    camera_yaw_deg: float = float("nan")
    mount_source: str = ""
    strain: float = float("nan")
    down_weighted: float = float("nan")
    steps: int = 0
    frames_odometry_only: int = 0
    notes: tuple[str, ...] = field(default_factory=tuple)

    def line(self) -> str:
        """What was decided and found, in plain words (for the log)."""
        if not self.applied:
            return f"wheel odometry ({self.topic}) not used: {self.why}"
        return (
            f"wheel odometry ({self.topic}) ties {self.steps} steps between frames "
            f"({self.why}): its stamps {self.offset_ms:.0f} ms after the frames', distances "
            f"read x{self.scale:.3f}, turns x{self.yaw_scale:.3f}; the camera sits "
            f"{self.lever_m:.3f} m ahead of the base ({self.mount_source}); "
            f"{100 * self.down_weighted:.1f} % of steps down-weighted as slip; "
            f"{self.frames_odometry_only} frames with no tag in view posed by it"
        )


def camera_yaw_deg(mount: Mount, u: F64) -> float:
    """The camera's yaw from the robot's forward axis (deg, about the normal, positive left)."""
    uh = u / np.linalg.norm(u)
    fwd = cross(mount.lateral(uh)[0], uh)
    z = np.array([0.0, 0.0, 1.0]) - uh[2] * uh
    return float(np.degrees(np.arctan2(cross(fwd, z) @ uh, fwd @ z)))


@dataclass(frozen=True)
class OdometryData:
    """A dataset's odometry as the stages read it (``extract.odometry``, ``extract.mount``):
    stamps ``t_ns (N,)``, poses ``pose (N, 7)`` of ``odom_T_base``, variances ``var (N, 3)`` or
    None, the recorded ``base_T_camera`` ``(7,)`` or None and where it came from, the topic;
    ``frames_t_ns``: the stamps of the camera's frames with no tag observation (they get a pose
    where the odometry covers them)."""

    t_ns: I64
    pose: F64
    var: F64 | None = None
    base_T_camera: F64 | None = None
    mount_source: str = ""
    topic: str = "odometry"
    frames_t_ns: I64 | None = None


# A level camera looking ahead, on the base's origin: the mount assumed when none is recorded.
LEVEL_BASE_R_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_motion(data: OdometryData, t0_ns: int) -> Callable[[float, float], F64] | None:
    """``cam_a_T_cam_b`` (4, 4) between times ``ta, tb`` (s from ``t0_ns``) by the wheels' dead
    reckoning through the recorded mount (else a level camera looking ahead on the base), the
    odometry's errors uncorrected: a start (:func:`~.start.link_tags`), which the joint solve
    refines. None when the odometry is unusable."""
    odo, _ = odometry_from_table(data.t_ns, data.pose, data.var, t0_ns, data.topic)
    if odo is None:
        return None
    if data.base_T_camera is not None:
        v = np.asarray(data.base_T_camera, np.float64)
        b_T_c = T_from_xyz_quat(v[None, :3], v[None, 3:] / np.linalg.norm(v[3:]))[0]
    else:
        b_T_c = make_T(LEVEL_BASE_R_CAM, np.zeros(3))
    c_T_b = inv(b_T_c)

    def motion(ta: float, tb: float) -> F64:
        o = odo.relative(np.array([ta]), np.array([tb]))[0]
        rel = make_T(R_from_rotvec(np.array([[0.0, 0.0, o[2]]]))[0], np.array([o[0], o[1], 0.0]))
        return np.asarray(c_T_b @ rel @ b_T_c)

    return motion
