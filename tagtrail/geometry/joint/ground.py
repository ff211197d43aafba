"""The ground-plane prior: a camera on a ground vehicle moves in a plane at a fixed tilt.

A camera bolted to a robot driving on a floor keeps its height above the floor and its roll and
pitch to it; only ``x, y`` on the floor and the heading change. Written in the world frame (the
anchor tag's) the floor is unknown, so the prior carries its own unknowns, a :class:`Plane`:
``n (3,)`` the unit normal in the world, ``d`` (m) the camera centres' offset along it
(``n . c = d``; the plane of the camera centres, not the floor itself) and ``u (3,)`` the same
normal in the camera frame (the mount's tilt). Per frame ``k`` with ``cam_T_world = (R_k, t_k)``
and centre ``c_k = -R_k^T t_k`` (whitened, so the terms read as a negative log-likelihood)::

    p_k = [ (n . c_k - d) / height_sigma ;  (R_k n - u) / tilt_sigma ]        (4,)

``height_sigma`` (m) is how far the camera rises and sinks (floor unevenness, suspension),
``tilt_sigma`` (rad) how far it rolls and pitches; a robust loss per frame lets a ramp or a bump
stop counting instead of bending the map. It is what holds the far end of a long chain of tags
level: without it a corridor's tag map and trajectory bend out of the floor by several cm per
10 m (the pitch error of each tag pair adding up).

Between consecutive frames ``j, j+1`` (``h_j`` s apart) the height changes little
(:class:`GroundLevel`, robust too)::

    l_j = n . (c_{j+1} - c_j) / (level_sigma sqrt(h_j))

``level_sigma`` (m/s/sqrt(Hz)) is the density of the camera's vertical velocity off the plane (a
floor's slope and undulation as the robot drives over it): the height wanders ``level_sigma
sqrt(T)`` over ``T`` seconds, held within ``height_sigma`` by the per-frame term. The per-frame
term alone leaves a frame's height to its own corners within 1 cm: a filter's newest frame,
with no later frame beside it, then jitters by tenths of a mm where a smoother's frames do not
(``stream/continuity.py``).

Plane updates: ``n <- Exp(B a) n`` with ``B (3, 2)`` a basis orthogonal to ``n`` (2 parameters),
``d <- d + dd``, ``u <- u + du``: 6 parameters, as a tag's. Camera perturbations are the joint
solve's left ones, ``R <- Exp(w) R``, ``t <- Exp(w) t + v`` (so ``c <- c - R^T v``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.joint.problem import Terms, centres, steps
from tagtrail.geometry.robust import LossName, rho
from tagtrail.geometry.rotations import cross, hat
from tagtrail.geometry.se3 import R_from_rotvec


@dataclass(frozen=True)
class GroundPrior:
    """How planar the camera's motion is: ``height_sigma_m`` (m) and ``tilt_sigma_rad`` (rad)
    per frame, a robust ``loss`` on each frame's whitened 4-vector with scale ``f_scale``
    (standard deviations)."""

    height_sigma_m: float
    tilt_sigma_rad: float
    level_sigma: float = float("inf")
    loss: LossName = "cauchy"
    f_scale: float = 3.0

    @classmethod
    def of(
        cls, height_sigma_m: float, tilt_sigma_deg: float, level_sigma: float = float("inf")
    ) -> GroundPrior:
        """The prior from its height (m), tilt (deg) and level (m/s/sqrt(Hz); inf: no level
        term) noise."""
        return cls(height_sigma_m, float(np.radians(tilt_sigma_deg)), level_sigma)


@dataclass(frozen=True)
class Plane:
    """``n (3,)``: unit normal (world), ``d`` (m): ``n . c`` of the camera centres, ``u (3,)``:
    the normal seen from the camera (``cam_R_world n``)."""

    n: F64
    d: float
    u: F64

    def basis(self) -> F64:
        """Two unit vectors ``(3, 2)`` orthogonal to ``n`` (the normal's 2 update directions)."""
        a = np.eye(3)[int(np.argmin(np.abs(self.n)))]
        b1 = cross(self.n, a)
        b1 /= np.linalg.norm(b1)
        return np.stack([b1, cross(self.n, b1)], axis=1)

    def update(self, step: F64) -> Plane:
        """The plane after the step ``[a (2) ; dd ; du (3)]``."""
        n = R_from_rotvec((self.basis() @ step[:2])[None])[0] @ self.n
        return Plane(n / np.linalg.norm(n), self.d + float(step[2]), self.u + step[3:])


def _scatter(R_cam: F64, t_cam: F64, prior: GroundPrior) -> tuple[F64, F64, F64]:
    """``M (3, 3)``: the scatter of the centres over ``height_sigma^2`` plus that of the
    rotations over ``tilt_sigma^2``, per frame; the mean centre and the mean rotation."""
    c = centres(R_cam, t_cam)
    c_mean, R_mean = c.mean(axis=0), R_cam.mean(axis=0)
    dc, dR = c - c_mean, R_cam - R_mean
    M = (
        np.einsum("fi,fj->ij", dc, dc) / prior.height_sigma_m**2
        + np.einsum("fki,fkj->ij", dR, dR) / prior.tilt_sigma_rad**2
    ) / len(R_cam)
    return M, c_mean, R_mean


def fit_plane(R_cam: F64, t_cam: F64, prior: GroundPrior) -> Plane:
    """The plane that minimises the prior's cost for fixed cameras: with ``d`` and ``u`` at
    their optima the cost is ``n^T M n`` (:func:`_scatter`), so ``n`` is ``M``'s least
    eigenvector."""
    M, c_mean, R_mean = _scatter(R_cam, t_cam, prior)
    n = np.linalg.eigh(M)[1][:, 0]
    n = n if n @ (R_mean.T @ np.array([0.0, -1.0, 0.0])) >= 0 else -n  # camera y points down
    return Plane(n, float(n @ c_mean), R_mean @ n)


def plane_spread(R_cam: F64, t_cam: F64, prior: GroundPrior) -> float:
    """How well cameras that move in a plane tell its normal: ``M``'s middle eigenvalue over
    its least (:func:`_scatter`), the spread across the one direction of travel (sideways, or
    a turn's change of heading) over the scatter off the plane. A straight drive without
    turning leaves the normal free to roll about the line (1-2: the plane fitted to it can be
    tens of degrees off); a weaving drive gives 30-1000 in its first second, a turn more."""
    lam = np.linalg.eigvalsh(_scatter(R_cam, t_cam, prior)[0])
    return float(lam[1] / max(lam[0], 1e-300))


def plane_terms(
    R_cam: F64, t_cam: F64, plane: Plane, prior: GroundPrior, unknowns: bool = True
) -> tuple[F64, F64, F64 | None]:
    """Whitened residuals ``p (F, 4)`` and their Jacobians on each camera's ``[w ; v]``
    ``(F, 4, 6)`` and on the plane's 6 parameters ``(F, 4, 6)`` (None unless ``unknowns``:
    the plane held fixed)."""
    n_f = len(R_cam)
    sh, st = prior.height_sigma_m, prior.tilt_sigma_rad
    c = centres(R_cam, t_cam)
    Rn = R_cam @ plane.n
    p = np.concatenate([((c @ plane.n - plane.d) / sh)[:, None], (Rn - plane.u) / st], axis=1)
    Jc = np.zeros((n_f, 4, 6))
    Jc[:, 0, 3:] = -Rn / sh  # d c / d v = -R^T
    Jc[:, 1:, :3] = -hat(Rn) / st  # R n <- Exp(w) R n
    if not unknowns:
        return p, Jc, None
    B = plane.basis()
    bxn = cross(B.T, plane.n)  # (2, 3): d n / d a_i
    Jg = np.zeros((n_f, 4, 6))
    Jg[:, 0, :2] = cross(plane.n, c) @ B / sh
    Jg[:, 0, 2] = -1.0 / sh
    Jg[:, 1:, :2] = np.einsum("fij,kj->fik", R_cam, bxn) / st
    Jg[:, 1:, 3:] = -np.eye(3) / st
    return p, Jc, Jg


def robust_weights(p: F64, prior: GroundPrior) -> tuple[F64, F64]:
    """Per-frame loss values and IRLS weights ``(F,)`` of whitened residuals ``p (F, 4)``."""
    f2 = prior.f_scale**2
    val, w = rho(prior.loss, np.sum(p * p, axis=1) / f2)
    return f2 * val, w


def ground_terms(
    R_cam: F64, t_cam: F64, plane: Plane, prior: GroundPrior, unknowns: bool = True
) -> Terms:
    """The prior's robust terms at ``plane``: each frame's whitened 4-vector (height, tilt),
    3 degrees of freedom a frame, less the plane's 5 when it is an unknown (``unknowns``; held
    fixed: no Jacobian on it)."""
    p, Jc, Jg = plane_terms(R_cam, t_cam, plane, prior, unknowns)
    val, w = robust_weights(p, prior)
    s = np.sqrt(w)
    return Terms(
        float(val.sum()),
        p * s[:, None],
        np.arange(len(R_cam)),
        (Jc * s[:, None, None])[:, None],
        None if Jg is None else Jg * s[:, None, None],
        3 * len(R_cam) - (5 if unknowns else 0),
    )


@dataclass(frozen=True)
class GroundPlane:
    """The ground-plane prior as a part of the joint solve (:class:`~.problem.Prior`): its
    noise model ``prior`` and its unknown, the :class:`Plane` (6 parameters, from ``start``)."""

    prior: GroundPrior
    start: Plane

    name = "ground"
    n_params = 6
    uses = ("ground",)

    def terms(self, R_cam: F64, t_cam: F64, values: Mapping[str, Any]) -> Terms:
        """Each frame's whitened 4-vector (height, tilt); 3 degrees of freedom a frame less
        the plane's 5."""
        return ground_terms(R_cam, t_cam, values[self.name], self.prior)

    def update(self, value: Plane, step: F64, values: Mapping[str, Any]) -> Plane:
        return value.update(step)


def level_terms(
    R_cam: F64, t_cam: F64, t_s: F64, j: I64, plane: Plane, prior: GroundPrior, unknowns: bool
) -> Terms:
    """The level terms (module docstring) of the steps ``j`` (frames ``j, j+1`` stamped
    ``t_s``): each step's whitened height change, robust, with Jacobians on its two cameras'
    ``[w ; v]`` and (``unknowns``) on the plane's 6 parameters; 1 degree of freedom a step."""
    Rn = R_cam @ plane.n
    h = -np.einsum("fi,fi->f", Rn, t_cam)  # n . c, c = -R^T t
    inv = 1.0 / (prior.level_sigma * np.sqrt(t_s[j + 1] - t_s[j]))
    q = (h[j + 1] - h[j]) * inv
    f2 = prior.f_scale**2
    val, w = rho(prior.loss, q * q / f2)
    s = np.sqrt(w) * inv
    Jc = np.zeros((len(j), 2, 1, 6))
    Jc[:, 0, 0, 3:] = Rn[j] * s[:, None]  # d (n . c) / d v = -R n
    Jc[:, 1, 0, 3:] = -Rn[j + 1] * s[:, None]
    Jg = None
    if unknowns:
        c = centres(R_cam, t_cam)
        Jg = np.zeros((len(j), 1, 6))
        Jg[:, 0, :2] = (c[j + 1] - c[j]) @ cross(plane.basis().T, plane.n).T * s[:, None]
    return Terms(float(f2 * val.sum()), (q * np.sqrt(w))[:, None], j, Jc, Jg, len(j))


@dataclass(frozen=True)
class GroundLevel:
    """The ground prior's level terms (module docstring) as a part of the joint solve, on the
    :class:`GroundPlane`'s plane (no unknowns of its own): the steps between frames stamped
    ``t_s`` (s) within ``max_gap_s`` (the motion prior's)."""

    prior: GroundPrior
    t_s: F64
    max_gap_s: float
    fixed: Plane | None = None
    """A plane held fixed (a live window's, fitted to the history): then no ``ground`` prior
    is needed beside it."""

    name = "level"
    n_params = 0
    start = None

    @property
    def uses(self) -> tuple[str, ...]:
        return () if self.fixed is not None else ("ground",)

    def terms(self, R_cam: F64, t_cam: F64, values: Mapping[str, Any]) -> Terms:
        """Each step's whitened height change; 1 degree of freedom a step."""
        j = steps(self.t_s, self.max_gap_s)
        plane = values["ground"] if self.fixed is None else self.fixed
        return level_terms(R_cam, t_cam, self.t_s, j, plane, self.prior, self.fixed is None)

    def update(self, value: Any, step: F64, values: Mapping[str, Any]) -> Any:
        return None


PLANAR_BOUND = 2.0  # median normalised chi^2 per degree of freedom below which motion is planar


def planarity(R_cam: F64, t_cam: F64, cam_cov: F64, prior: GroundPrior) -> tuple[Plane, float]:
    """The plane fitted to a solution solved without the prior and how well the motion fits it:
    the median over frames of each frame's squared distance from the plane (height, tilt) over
    its variance (the prior's plus the frame's own from ``cam_cov (F, 6, 6)``, the covariance of
    ``cam_T_world``'s left perturbation ``[w ; v]``), per degree of freedom (3). About 0.8 when
    the camera rides a plane as the prior says; a hand-held camera's metres and degrees of
    motion off any plane give hundreds. The median: a ramp, a bump or a flipped frame does not
    decide it."""
    plane = fit_plane(R_cam, t_cam, prior)
    p = plane_terms(R_cam, t_cam, plane, prior, unknowns=False)[0]
    Rn = R_cam @ plane.n
    var_h = np.einsum("fi,fij,fj->f", Rn, cam_cov[:, 3:, 3:], Rn)
    K = hat(Rn)
    var_g = np.einsum("fij,fjk,flk->fil", K, cam_cov[:, :3, :3], K)  # of R n - u, (F, 3, 3)
    sh2, st2 = prior.height_sigma_m**2, prior.tilt_sigma_rad**2
    chi2 = p[:, 0] ** 2 * sh2 / (sh2 + var_h) + np.einsum(
        "fi,fij,fj->f",
        p[:, 1:],
        np.linalg.inv(np.eye(3) + var_g / st2 + 1e-9 * np.eye(3)),
        p[:, 1:],
    )
    return plane, float(np.median(chi2) / 3.0) if len(chi2) else float("inf")


@dataclass(frozen=True)
class GroundReport:
    """What the ground-plane prior decided and found: the mode, whether it was applied, the
    planarity figure that decided ``auto`` (:func:`planarity`), the plane's normal in the
    world, the camera's tilt to it (deg from its y axis), the camera centres' RMS height off it
    (m), the RMS tilt off the mean (deg), the frames the robust loss let go (beyond its scale),
    the wheeled-drive prior's report (:class:`~.drive.DriveReport`; None without it), when
    ``auto`` was not decided on this data, why (``note``, plain words), and the rest of the
    :class:`Plane`: its offset ``n . c`` (m) and the normal seen from the camera (unit), for the
    live smoother to hold from a run's first frame (``ground.json``)."""

    mode: str
    applied: bool
    planarity: float
    normal: tuple[float, ...]
    camera_tilt_deg: float
    height_rms_m: float
    tilt_rms_deg: float
    frames_off: int
    drive: Any = None
    note: str = ""
    offset_m: float = math.nan
    normal_camera: tuple[float, ...] = ()

    def lines(self) -> list[str]:
        """What was decided, in a line or two of plain words (for the log)."""
        wheels = self.drive
        if self.note:
            held = [
                name
                for name, on in (
                    ("one plane at a fixed tilt", self.applied),
                    ("a wheeled robot's motion", wheels is not None and wheels.applied),
                )
                if on
            ]
            return [
                f"whether the camera moves in one plane like a robot's is not decided on "
                f"this data: {self.note}; "
                + (f"held to {' and '.join(held)}" if held else "held to neither")
            ]
        out = [
            (
                "the camera moves in one plane at a fixed tilt, as on a robot: held there"
                if self.applied
                else "the camera leaves a single plane: its height and tilt left free"
            )
            + f" (off-plane score {self.planarity:.2f}, limit {PLANAR_BOUND:.1f}); the "
            f"camera's up axis is {self.camera_tilt_deg:.1f} deg from that plane's normal, "
            f"and it stays within {1e3 * self.height_rms_m:.1f} mm / "
            f"{self.tilt_rms_deg:.2f} deg RMS of the plane"
        ]
        if wheels is not None:
            out.append(wheels.line())
        return out


def ground_report(
    R_cam: F64,
    t_cam: F64,
    plane: Plane,
    prior: GroundPrior,
    mode: str,
    applied: bool,
    stat: float,
    drive: Any = None,
    note: str = "",
) -> GroundReport:
    """The :class:`GroundReport` of cameras ``cam_T_world`` against ``plane``."""
    p = plane_terms(R_cam, t_cam, plane, prior, unknowns=False)[0]
    u = plane.u / max(float(np.linalg.norm(plane.u)), 1e-300)
    return GroundReport(
        mode=mode,
        applied=bool(applied),
        planarity=stat,
        normal=tuple(float(v) for v in plane.n),
        camera_tilt_deg=float(np.degrees(np.arccos(np.clip(-u[1], -1.0, 1.0)))),
        height_rms_m=float(np.sqrt(np.mean(p[:, 0] ** 2))) * prior.height_sigma_m,
        tilt_rms_deg=float(
            np.degrees(np.sqrt(np.mean(np.sum(p[:, 1:] ** 2, axis=1))) * prior.tilt_sigma_rad)
        ),
        frames_off=int((np.sum(p * p, axis=1) > prior.f_scale**2).sum()),
        drive=drive,
        note=note,
        offset_m=float(plane.d),
        normal_camera=tuple(float(v) for v in u),
    )
