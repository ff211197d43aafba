"""The wheeled-drive (non-holonomic) prior: a wheeled robot moves along its heading.

A differential-drive or Ackermann robot does not slide sideways: the point between its wheels
moves along the robot's forward axis, and a camera mounted ``lever_m`` ahead of that point
moves sideways only as the robot turns, by ``lever_m`` per radian of yaw. Between consecutive
frames ``j, j+1`` (``cam_T_world = (R, t)``, centres ``c``, step ``h_j`` s)::

    x_j     = (R_j + R_{j+1}) (c_{j+1} - c_j) / 2        the step in the camera frame (m)
    theta_j = (R_j n) . Log(R_j R_{j+1}^T)               its yaw about the plane's normal (rad)
    q_j     = (s . x_j - lever_m theta_j) / (lateral_sigma sqrt(h_j))

``n`` is the ground plane's normal (:mod:`tagtrail.geometry.joint.ground`; the drive prior rides on
it), ``s`` the robot's lateral axis seen from the camera (unit, ``up x forward``, across the
plane's normal: the mount's yaw) and ``lever_m`` the camera's distance ahead of the centre of
rotation: both unknowns of the solve, the camera's :class:`Mount`. ``lateral_sigma``
(m/s/sqrt(Hz)) is the density of the white noise on the lateral velocity beyond that (wheel
slip, skid in turns): over ``T`` seconds the camera drifts sideways ``lateral_sigma sqrt(T)``.
A robust loss per step lets a skid or a bump stop counting. It ties the camera's heading, which
the tags give well, to its direction of travel, so its lateral position is held by the heading
instead of jumping where the tags in view change (a single oblique tag fixes the camera's
bearing to it far better than its range).

Not for a holonomic (mecanum, omni) robot moving sideways or a hand-held camera:
:func:`strain` measures how hard the corners pull against the prior in a solution solved with
it, and ``auto`` keeps it only where they leave it unstrained.

Mount updates: the forward axis turned by ``b`` about the plane's normal, ``lever_m <- lever_m +
dl``: 2 parameters, after the plane's 6.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.joint.ground import Plane
from tagtrail.geometry.joint.problem import Terms, centres, steps
from tagtrail.geometry.robust import LossName, rho
from tagtrail.geometry.rotations import cross, hat, log_so3, right_jacobian_inv
from tagtrail.geometry.se3 import R_from_rotvec

N_MOUNT = 2  # parameters of a Mount: its yaw about the plane's normal, its lever arm


@dataclass(frozen=True)
class DrivePrior:
    """The lateral velocity noise density ``lateral_sigma`` (m/s/sqrt(Hz)), a robust ``loss``
    on each step's whitened residual with scale ``f_scale`` (standard deviations)."""

    lateral_sigma: float
    loss: LossName = "cauchy"
    f_scale: float = 3.0


@dataclass(frozen=True)
class Mount:
    """``g (3,)``: the robot's forward axis in the camera frame (unit, across the plane's normal
    seen from the camera, ``Plane.u``); ``lever_m``: the camera's distance ahead of the robot's
    centre of rotation (m). The lateral axis is ``s = u x g / |u x g|`` (left), across the
    plane's normal by construction: a lateral axis free to tilt would turn up the normal, along
    which the ground prior already holds the camera, and the drive prior would hold nothing."""

    g: F64
    lever_m: float

    def lateral(self, u: F64) -> tuple[F64, F64, float]:
        """``s (3,)``, ``w = u x g`` and ``|w|`` for the plane's camera-frame normal ``u``."""
        uh = u / np.linalg.norm(u)
        w = cross(uh, self.g)
        nw = float(np.linalg.norm(w))
        return w / nw, w, nw

    def update(self, step: F64, u: F64) -> Mount:
        """The mount after the step ``[b ; dl]``: ``g`` turned by ``b`` rad about ``u``."""
        g = R_from_rotvec((step[0] * u / np.linalg.norm(u))[None])[0] @ self.g
        return Mount(g / np.linalg.norm(g), self.lever_m + float(step[1]))


def _geometry(R: F64, t: F64, j: I64, n: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
    """Per step: ``x (P, 3)``, ``theta (P,)``, ``E = R_j R_{j+1}^T``, ``e = Log E``, the
    camera-frame normal ``u = R_j n`` and the world step ``dc``."""
    c = centres(R, t)
    dc = c[j + 1] - c[j]
    Ra, Rb = R[j], R[j + 1]
    x = 0.5 * (np.einsum("pij,pj->pi", Ra, dc) + np.einsum("pij,pj->pi", Rb, dc))
    E = Ra @ np.swapaxes(Rb, 1, 2)
    e = log_so3(E)
    u = Ra @ n
    return x, np.einsum("pi,pi->p", u, e), E, e, u, dc


def drive_terms(
    R_cam: F64,
    t_cam: F64,
    t_s: F64,
    j: I64,
    plane: Plane,
    mount: Mount,
    prior: DrivePrior,
    unknowns: bool = True,
) -> tuple[F64, F64, F64 | None]:
    """Whitened residuals ``q (P,)`` of the steps ``j`` and their Jacobians on the cameras
    ``[w ; v]`` of frames ``j, j+1`` ``(P, 2, 6)`` and on the plane's 6 then the mount's 2
    parameters ``(P, 8)`` (None unless ``unknowns``: plane and mount held fixed)."""
    x, theta, E, e, u, dc = _geometry(R_cam, t_cam, j, plane.n)
    s, w, nw = mount.lateral(plane.u)
    lev = mount.lever_m
    inv_sig = 1.0 / (prior.lateral_sigma * np.sqrt(t_s[j + 1] - t_s[j]))
    q = (x @ s - lev * theta) * inv_sig
    Ra, Rb = R_cam[j], R_cam[j + 1]
    xa, xb = np.einsum("pij,pj->pi", Ra, dc), np.einsum("pij,pj->pi", Rb, dc)
    Jinv_T = np.swapaxes(right_jacobian_inv(e), 1, 2)
    Es = E @ s
    EtS = np.einsum("pji,j->pi", E, s)
    Jc = np.zeros((len(j), 2, 6))
    # s . x: rotations turn the step in the camera frame, translations move the centres
    Jc[:, 0, :3] = 0.5 * cross(xa, s)
    Jc[:, 1, :3] = 0.5 * cross(xb, s)
    Jc[:, 0, 3:] = 0.5 * (s + Es)
    Jc[:, 1, 3:] = -0.5 * (s + EtS)
    # theta = (R_j n) . Log(R_j R_{j+1}^T)
    Jc[:, 0, :3] -= lev * (
        cross(u, e) + np.einsum("pij,pj->pi", E, np.einsum("pij,pj->pi", Jinv_T, u))
    )
    Jc[:, 1, :3] += lev * np.einsum("pij,pj->pi", Jinv_T, u)
    Jc *= inv_sig[:, None, None]
    if not unknowns:
        return q, Jc, None
    Jg = np.zeros((len(j), 6 + N_MOUNT))
    bxn = cross(plane.basis().T, plane.n)  # (2, 3): d n / d a_i
    Jg[:, :2] = -lev * np.einsum("pk,pki,ci->pc", e, Ra, bxn)
    # s = w / |w|, w = u^ x g: d s = (I - s s^T) d w / |w|; through u, d w = -[g]x d u^
    unorm = float(np.linalg.norm(plane.u))
    uh = plane.u / unorm
    P = (np.eye(3) - np.outer(s, s)) / nw
    Jg[:, 3:6] = x @ (P @ -hat(mount.g) @ (np.eye(3) - np.outer(uh, uh)) / unorm)
    Jg[:, 6] = x @ (P @ cross(uh, w))  # g turned about u^: d w = u^ x (u^ x g) d b
    Jg[:, 7] = -theta
    Jg *= inv_sig[:, None]
    return q, Jc, Jg


def robust_weights(q: F64, prior: DrivePrior) -> tuple[F64, F64]:
    """Per-step loss values and IRLS weights ``(P,)`` of whitened residuals ``q (P,)``."""
    f2 = prior.f_scale**2
    val, w = rho(prior.loss, q * q / f2)
    return f2 * val, w


def fit_mount(
    R_cam: F64,
    t_cam: F64,
    t_s: F64,
    j: I64,
    plane: Plane,
    min_turn_rad: float = 0.0,
    lever_m: float | None = None,
) -> Mount:
    """The mount that fits fixed cameras: the forward axis first the steps' principal direction
    in the camera frame (across the plane's normal; the way most steps go), then the yaw about
    the normal and the lever arm that minimise the lateral steps (weighted by ``1 / h``, as the
    prior weighs them) by Gauss-Newton; the lever arm stays 0 without turns (under
    ``min_turn_rad`` of yaw in all: noise in the yaw steps alone would set it), or is held at
    ``lever_m`` when the mount is known (then the yaw alone is fitted)."""
    lever0 = 0.0 if lever_m is None else float(lever_m)
    u = plane.u / max(float(np.linalg.norm(plane.u)), 1e-300)
    fwd = cross(u, np.array([1.0, 0.0, 0.0]))  # camera z, when nothing moves
    if not len(j):
        return Mount(fwd / np.linalg.norm(fwd), lever0)
    x, theta, *_ = _geometry(R_cam, t_cam, j, plane.n)
    xp = x - np.outer(x @ u, u)
    if np.linalg.norm(xp) > 0:
        fwd = np.linalg.eigh(xp.T @ xp)[1][:, -1]
        fwd = -fwd if np.sum(np.sign(xp @ fwd)) < 0 else fwd
    mount = Mount(fwd / np.linalg.norm(fwd), lever0)
    w = 1.0 / (t_s[j + 1] - t_s[j])
    turns = (
        lever_m is None
        and float(np.sum(w * theta * theta)) > 1e-12
        and float(np.abs(theta).sum()) >= min_turn_rad
    )
    for _ in range(5):  # lateral = s . x - lever theta; d s / d yaw = -g
        s = mount.lateral(plane.u)[0]
        r = x @ s - mount.lever_m * theta
        J = np.stack([-(x @ mount.g), -theta], axis=1)[:, : 2 if turns else 1]
        step = np.linalg.lstsq(J * np.sqrt(w)[:, None], -r * np.sqrt(w), rcond=None)[0]
        mount = mount.update(np.r_[step, 0.0][:2], plane.u)
        if np.abs(step).max() < 1e-9:
            break
    return mount


@dataclass(frozen=True)
class WheeledDrive:
    """The wheeled-drive prior as a part of the joint solve (:class:`~.problem.Prior`): its
    noise model ``prior`` on the steps between frames stamped ``t_s`` (s) within ``max_gap_s``
    (the motion prior's), riding on the ground prior's plane; its unknown, the camera's
    :class:`Mount` (2 parameters, from ``start``)."""

    prior: DrivePrior
    t_s: F64
    max_gap_s: float
    start: Mount

    name = "drive"
    n_params = N_MOUNT
    uses = ("ground", "drive")

    @cached_property
    def j(self) -> I64:
        """The steps ``j (P,)``: frames whose successor follows within ``max_gap_s``."""
        return steps(self.t_s, self.max_gap_s)

    def terms(self, R_cam: F64, t_cam: F64, values: Mapping[str, Any]) -> Terms:
        """Each step's whitened lateral velocity; 1 degree of freedom a step less the mount's 2."""
        q, Jc, Jg = drive_terms(
            R_cam, t_cam, self.t_s, self.j, values["ground"], values[self.name], self.prior
        )
        assert Jg is not None
        val, w = robust_weights(q, self.prior)
        s = np.sqrt(w)
        return Terms(
            float(val.sum()),
            (q * s)[:, None],
            self.j,
            (Jc * s[:, None, None])[:, :, None],
            (Jg * s[:, None])[:, None],
            len(self.j) - N_MOUNT,
        )

    def update(self, value: Mount, step: F64, values: Mapping[str, Any]) -> Mount:
        return value.update(step, values["ground"].u)


WHEELED_BOUND = 2.0  # the drive prior's robust chi^2 per step, in the variance factor


def strain(q: F64, prior: DrivePrior, variance_factor: float) -> float:
    """How hard the corners pull against the drive prior in a solution solved with it: its
    robust chi^2 per step (whitened steps ``q (P,)``), in that solution's variance factor.
    Well under 1 where the robot moves as the prior says (simulated wheeled robots
    0.01-0.02); a camera that slides or turns on its own (a mecanum base, a panning camera)
    leaves every step strained by several times that. NaN without steps."""
    if not len(q):
        return float("nan")
    _, w = robust_weights(q, prior)
    return float(np.mean(q * q * w)) / max(variance_factor, 1e-12)


class DriveReport(BaseModel):
    """What the wheeled-drive prior decided and found, of the solution solved with it: the
    mode, whether it was applied, the strain that decided ``auto`` (:func:`strain`: the prior's
    robust chi^2 per step in the solution solved with it, in its variance factor; wheeled below
    :data:`WHEELED_BOUND`; NaN without steps), the camera's lever arm ahead of the centre of
    rotation (m) and its yaw from the robot's forward axis (deg, about the plane's normal,
    positive to the left), the RMS lateral velocity beyond the lever arm (m/s) and the steps the
    robust loss let go (beyond its scale). A pydantic model: it is also the report's document
    (``optimize.report.bundle.ground.drive``), unknown keys refused, immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: Literal["auto", "wheeled"]
    applied: bool
    strain: float
    lever_m: float
    camera_yaw_deg: float
    lateral_rms_mps: float
    steps_off: int
    forward_camera: tuple[float, float, float] | None = None
    """The robot's forward axis in the camera frame (unit; :class:`Mount`'s ``g``)."""

    def line(self) -> str:
        """What was decided and found, in plain words (for the log)."""
        return (
            (
                "the camera moves like a wheeled robot's, never sliding sideways: held so"
                if self.applied
                else "the camera moves sideways too: not held to a wheeled robot's motion"
            )
            + f" (sideways-motion score {self.strain:.2f}, limit {WHEELED_BOUND:.1f}); the "
            f"camera sits {self.lever_m:.3f} m from the turning point, looks "
            f"{self.camera_yaw_deg:.1f} deg off the direction of travel and slides "
            f"{1e3 * self.lateral_rms_mps:.1f} mm/s RMS sideways"
        )


def drive_report(
    q: F64, part: WheeledDrive, plane: Plane, mount: Mount, mode: str, applied: bool, fit: float
) -> DriveReport:
    """The :class:`DriveReport` of a solution with the ``plane`` and ``mount`` it solved and
    its whitened steps ``q (P,)``."""
    j = part.j
    h = part.t_s[j + 1] - part.t_s[j]
    u = plane.u / max(float(np.linalg.norm(plane.u)), 1e-300)
    fwd = cross(mount.lateral(u)[0], u)  # the robot's forward axis, camera frame
    z = np.array([0.0, 0.0, 1.0]) - u[2] * u
    yaw = np.degrees(np.arctan2(cross(fwd, z) @ u, fwd @ z))
    lat = q * part.prior.lateral_sigma / np.sqrt(h)  # m/s
    return DriveReport(
        mode=mode,
        applied=bool(applied),
        strain=fit,
        lever_m=mount.lever_m,
        camera_yaw_deg=float(yaw),
        lateral_rms_mps=float(np.sqrt(np.mean(lat**2))) if len(lat) else 0.0,
        steps_off=int((q * q > part.prior.f_scale**2).sum()),
        forward_camera=(float(fwd[0]), float(fwd[1]), float(fwd[2])),
    )
