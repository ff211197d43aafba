"""The joint problem: what is observed (tag corners in frames), what is solved for (tag and
camera poses, and each prior's own unknowns), how the corners are weighed, and the result.

Unknowns: ``world_T_tag`` of the free tags (all but the anchor for a map; none for a trajectory
against a fixed map) and ``cam_T_world`` of every frame seeing a tag, frames in time order. The
corner term of the cost (whitened, so it reads as a negative log-likelihood)::

    sum_o  f^2 rho(|r_o|^2 / f^2)

``r_o`` (8,): observation ``o``'s corner reprojection errors in pixels divided by its corner
noise (:func:`corner_sigma`), ``rho`` a robust loss on the whole tag with scale ``f`` (in units
of the noise) -- the maximum-likelihood map under Gaussian corner noise, which does not inherit
the bias of single-tag PnP. A tag's weight follows from its geometry: a small, far or oblique
tag's corners move less per metre or radian of pose, and are noisier, so its observation counts
less; a bridge between two parts of the map seen in one or two frames weighs what those frames'
corners say, no more. The priors (:mod:`.motion`, :mod:`.ground`, :mod:`.drive`) add their own
terms (:class:`Terms`); :mod:`.solver` minimises the sum.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, Protocol

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.robust import LossName
from tagtrail.geometry.rotations import hat
from tagtrail.geometry.se3 import R_from_rotvec


@dataclass(frozen=True)
class CornerObservations:
    """Tag corners seen in frames: observation ``o`` is tag ``tag[o]`` (index ``0..T-1``) in frame
    ``frame[o]`` (index ``0..F-1``), its corners ``pts_tag (O, 4, 3)`` (tag frame, m) seen at
    ``uv (O, 4, 2)`` (undistorted normalised image coordinates, ``x/z, y/z``)."""

    frame: I64
    tag: I64
    pts_tag: F64
    uv: F64


@dataclass(frozen=True)
class Corners:
    """How the corners are weighed: ``px_per_unit`` (the focal length, px per normalised unit),
    ``sigma_px`` the corner noise (one value or one per observation, :func:`corner_sigma`),
    a robust ``loss`` per tag with scale ``f_scale_px`` (taken at the noise's median);
    ``estimate_noise``: after the first solve, rescale the noise to what the residuals show
    (clamped to 0.05-5 px) and solve again, so that precise corners are not outweighed by the
    priors (nor noisy ones by them overruled)."""

    px_per_unit: float
    sigma_px: float | F64 = 1.0
    loss: LossName = "huber"
    f_scale_px: float = 1.0
    estimate_noise: bool = False


@dataclass(frozen=True)
class Terms:
    """One prior's whitened residuals at an estimate, each term's robust IRLS weight applied
    (``r * sqrt(w)``, ``J * sqrt(w)``): ``r (M, d)``; term ``m`` ties the consecutive frames
    ``first[m] .. first[m] + n - 1`` with Jacobians ``Jc (M, n, d, 6)`` on their ``[w ; v]``
    and ``Jg (M, d, G)`` on the unknowns the prior declares (``Prior.uses``; None without);
    ``cost`` its robust cost, ``dof`` the degrees of freedom its terms add (terms less its own
    unknowns' freedoms)."""

    cost: float
    r: F64
    first: I64
    Jc: F64
    Jg: F64 | None = None
    dof: int = 0


def steps(t_s: F64, max_gap_s: float) -> I64:
    """Frames ``j (P,)`` whose successor ``j + 1`` follows within ``max_gap_s``."""
    dt = np.diff(np.asarray(t_s, np.float64))
    return np.flatnonzero((dt > 0) & (dt <= max_gap_s)).astype(np.int64)


class Prior(Protocol):
    """A prior of the joint solve: ``name`` keys its unknowns (``n_params`` parameters, starting
    at ``start``; ``uses``: the names whose unknowns its terms depend on, its own last when it
    has any), ``terms`` its :class:`Terms` at cameras ``cam_T_world`` ``(F, 3, 3), (F, 3)`` and
    unknowns ``values`` (name -> value), ``update`` its unknowns after a step of its
    ``n_params`` (``values``: all unknowns before the step)."""

    @property
    def name(self) -> str: ...
    @property
    def n_params(self) -> int: ...
    @property
    def start(self) -> Any: ...
    @property
    def uses(self) -> tuple[str, ...]: ...
    def terms(self, R_cam: F64, t_cam: F64, values: Mapping[str, Any]) -> Terms: ...
    def update(self, value: Any, step: F64, values: Mapping[str, Any]) -> Any: ...


@dataclass(frozen=True)
class JointResult:
    """Solved ``world_T_tag`` (``R_tag (T, 3, 3)``, ``t_tag (T, 3)``) and ``cam_T_world``
    (``R_cam (F, 3, 3)``, ``t_cam (F, 3)``); ``res_px (O,)``: RMS corner error of each
    observation (px); ``tag_std``/``cam_std`` ``(T|F, 2)``: position (m) and rotation (rad)
    standard deviations (RMS over the axes; 0 for fixed tags; None unless asked for) and
    ``cam_cov (F, 6, 6)`` each frame's covariance of the left perturbation ``[w ; v]`` of
    ``cam_T_world`` (the map's share included when it is free; scaled as the std),
    ``tail_cov`` the last two frames' (below);
    ``variance_factor``: the whitened cost per degree of freedom (1 when the noise is as
    assumed); ``terms``: each prior's number of terms (``terms["motion"]``: frames held by the
    motion prior); ``sigma_px``: the median corner noise used; ``unknowns``: each prior's
    solved unknowns (``"ground"``: its :class:`~.ground.Plane`, ``"drive"``: its
    :class:`~.drive.Mount`)."""

    R_tag: F64
    t_tag: F64
    R_cam: F64
    t_cam: F64
    res_px: F64
    cost: float
    iters: int
    converged: bool
    variance_factor: float
    sigma_px: float
    terms: Mapping[str, int] = field(default_factory=dict)
    unknowns: Mapping[str, Any] = field(default_factory=dict)
    tag_std: F64 | None = None
    cam_std: F64 | None = None
    cam_cov: F64 | None = None
    tail_cov: F64 | None = None
    """With ``covariance="last"`` and no free tag nor prior unknown: the last two frames'
    joint covariance ``(12, 12)`` of their ``[w ; v]``, unscaled (the inverse normal matrix's
    block): what the solve knows of them, a filter's prior for the next frame
    (:mod:`.newest`)."""

    @property
    def prior_terms(self) -> int:
        """Frames held by the motion prior."""
        return int(self.terms.get("motion", 0))


def project(
    R_cam: F64, t_cam: F64, R_tag: F64, t_tag: F64, ob: CornerObservations
) -> tuple[F64, F64, F64]:
    """Residuals ``(O, 4, 2)`` (normalised), points in world and camera frames ``(O, 4, 3)``."""
    pts_w = np.einsum("oij,okj->oki", R_tag[ob.tag], ob.pts_tag) + t_tag[ob.tag][:, None]
    pts_c = np.einsum("oij,okj->oki", R_cam[ob.frame], pts_w) + t_cam[ob.frame][:, None]
    z = np.where(pts_c[..., 2:3] > 1e-9, pts_c[..., 2:3], 1e-9)
    return pts_c[..., :2] / z - ob.uv, pts_w, pts_c


def corner_jacobians(pc: F64, scale: F64) -> tuple[F64, F64]:
    """The whitened projection's Jacobians at camera-frame corners ``pc (O, 4, 3)`` with
    ``scale (O,)`` (normalised units -> units of each observation's noise): ``Jp (O, 4, 2, 3)``
    on the camera-frame point and ``Jc (O, 8, 6)`` on the camera's left perturbation
    ``[w ; v]``."""
    n_o = len(pc)
    z = pc[..., 2]
    Jp = np.zeros((n_o, 4, 2, 3))
    Jp[..., 0, 0] = Jp[..., 1, 1] = scale[:, None] / z
    Jp[..., 2] = -scale[:, None, None] * pc[..., :2] / (z * z)[..., None]
    eye = np.broadcast_to(np.eye(3), (n_o, 4, 3, 3))
    Jc = (Jp @ np.concatenate([-hat(pc), eye], axis=-1)).reshape(n_o, 8, 6)
    return Jp, Jc


def sum_blocks(x: F64, idx: I64, n: int) -> F64:
    """``out[k] = sum of x[o] with idx[o] == k`` for blocks ``x (O, ...)``."""
    flat = x.reshape(len(x), -1)
    out = np.stack([np.bincount(idx, flat[:, c], n) for c in range(flat.shape[1])], axis=1)
    return out.reshape((n, *x.shape[1:]))


def left_update(R: F64, t: F64, d: F64) -> tuple[F64, F64]:
    """``(Exp(w) R, Exp(w) t + v)`` for steps ``d = [w ; v]`` ``(N, 6)``."""
    dR = R_from_rotvec(d[:, :3])
    return dR @ R, np.einsum("nij,nj->ni", dR, t) + d[:, 3:]


def centres(R_cam: F64, t_cam: F64) -> F64:
    """Camera centres in the world ``(F, 3)`` of ``cam_T_world`` ``(F, 3, 3), (F, 3)``."""
    return np.asarray(-np.einsum("fji,fj->fi", R_cam, t_cam))


def observation_rms_px(
    R_cam: F64, t_cam: F64, R_tag: F64, t_tag: F64, ob: CornerObservations, px_per_unit: float
) -> F64:
    """Each observation's RMS corner error ``(O,)`` (px) at cameras ``cam_T_world`` and tags
    ``world_T_tag``."""
    r, _, _ = project(R_cam, t_cam, R_tag, t_tag, ob)
    return np.asarray(np.sqrt(np.mean(np.sum(r * r, axis=2), axis=1)) * px_per_unit)


def frame_rms_px(res_px: F64, frame: I64, n_f: int) -> F64:
    """Each frame's RMS corner error ``(F,)`` from its observations' RMS errors ``res_px``."""
    n = np.bincount(frame, minlength=n_f)
    return np.sqrt(np.bincount(frame, res_px**2, n_f) / np.maximum(n, 1))


def same_frame_pairs(frame: I64) -> tuple[I64, I64]:
    """All ordered pairs ``(a, b)`` of observations in the same frame, ``a == b`` included."""
    order = np.argsort(frame, kind="stable")
    f = frame[order]
    starts = np.flatnonzero(np.r_[True, f[1:] != f[:-1]])
    size = np.diff(np.r_[starts, len(f)])
    grp = np.repeat(np.arange(len(starts)), size)  # frame group of each sorted observation
    reps = size[grp]  # each observation pairs with every member of its group
    a = np.repeat(np.arange(len(f)), reps)
    b = starts[grp][a] + np.arange(len(a)) - np.repeat(np.cumsum(reps) - reps, reps)
    return order[a], order[b]


def corner_sigma(corners_px: F64, sigma_px: float, side_ref_px: float = 20.0) -> F64:
    """Each observation's corner noise ``(O,)`` px: ``sigma_px`` for a tag whose mean side is
    ``side_ref_px``, scaling as ``sqrt(side_ref_px / side)`` within 0.5-2x -- a corner is fitted
    to edges whose pixel count grows with the side, so a small, far or foreshortened (oblique)
    tag's corners are noisier (the weighting by geometry; its low decision margin goes with
    it)."""
    c = np.asarray(corners_px, np.float64).reshape(-1, 4, 2)
    side = np.linalg.norm(c - np.roll(c, 1, axis=1), axis=2).mean(axis=1)
    ratio = np.sqrt(side_ref_px / np.maximum(side, 1e-6))
    return np.asarray(sigma_px * np.clip(np.nan_to_num(ratio, nan=1.0), 0.5, 2.0))


@dataclass(frozen=True)
class CornerRows:
    """Observations with their corners, in (time, frame, tag) order: frame ids, stamps (ns),
    tag ids, corners ``(O, 4, 2)`` (px), sizes (m), both IPPE solutions ``(O, 2, 4, 4)``."""

    frame_idx: I64
    t_ns: I64
    tag_id: I64
    corners_px: F64
    size_m: F64
    cam_T_tag: F64

    def take(self, keep: np.ndarray) -> CornerRows:
        """The rows ``keep`` (bool or indices)."""
        return CornerRows(*(getattr(self, f.name)[keep] for f in fields(self)))

    def observations(self, tag: I64, camera: CameraModel) -> tuple[CornerObservations, I64]:
        """:func:`corner_observations` of these rows, ``tag`` their tags' indices."""
        return corner_observations(
            self.frame_idx, self.t_ns, tag, self.corners_px, self.size_m, camera
        )


def corner_observations(
    frame_idx: I64, t_ns: I64, tag: I64, corners_px: F64, size_m: F64, camera: CameraModel
) -> tuple[CornerObservations, I64]:
    """Observations (frames numbered in time order) and each frame's stamp ``(F,)`` (ns), from
    per-observation frame ids, stamps, tag indices, corners ``(O, 4, 2)`` (px) and sizes (m)."""
    frames, f = np.unique(frame_idx, return_inverse=True)
    stamp = np.zeros(len(frames), np.int64)
    stamp[f] = t_ns
    order = np.argsort(stamp, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    ob = CornerObservations(
        frame=rank[f],
        tag=np.asarray(tag, np.int64),
        pts_tag=tag_corners(size_m),
        uv=camera.undistort(corners_px),
    )
    return ob, stamp[order]
