"""Closed-form point-set alignment (Umeyama 1991) with RANSAC, in 2-D (planar) and 3-D.

Solves Eq. 3.10 of the paper, ``min Σ ‖p_ref − (s R p_q + t)‖²`` over matched tag positions, for
the models ``similarity`` / ``rigid`` (2-D, in the plane; Eq. 3.9) and ``sim3`` / ``se3`` (3-D).
Outlier tags are rejected first by RANSAC over minimal samples (2 points in 2-D, 3 in 3-D), then
the model is refitted by least squares on the inliers. Everything is batched: one SVD call fits
every RANSAC hypothesis.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from math import comb

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tagtrail.errors import DataError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.reference_path import Plane

MODELS: dict[str, tuple[int, bool]] = {  # model → (dimension, with scale)
    "similarity": (2, True),
    "rigid": (2, False),
    "sim3": (3, True),
    "se3": (3, False),
}


def umeyama(src: ArrayLike, dst: ArrayLike, with_scale: bool) -> tuple[F64, F64, F64]:
    """Least-squares ``dst ≈ s R src + t`` (Umeyama 1991, Eqs. 40–42), batched.

    ``src, dst (..., N, d)`` (m). Returns ``s (...)``, ``R (..., d, d)`` (det +1) and
    ``t (..., d)`` (m); ``s = 1`` unless ``with_scale``. Where ``src`` has no spread, ``s = nan``.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(axis=-2), dst.mean(axis=-2)
    xs, xd = src - mu_s[..., None, :], dst - mu_d[..., None, :]
    n = src.shape[-2]
    cov = np.einsum("...ni,...nj->...ij", xd, xs) / n
    U, S, Vt = np.linalg.svd(cov)
    D = np.ones(S.shape)
    D[..., -1] = np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)
    R = U @ (D[..., :, None] * Vt)
    var_s = np.einsum("...ni,...ni->...", xs, xs) / n
    if with_scale:
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(var_s > 1e-18, (S * D).sum(axis=-1) / var_s, np.nan)
    else:
        s = np.where(var_s > 1e-18, 1.0, np.nan)
    t = mu_d - s[..., None] * np.einsum("...ij,...j->...i", R, mu_s)
    return np.asarray(s, dtype=np.float64), R, t


@dataclass(frozen=True)
class Alignment:
    """``dst = scale · R @ src + t`` estimated from tag correspondences.

    ``R (d, d)``, ``t (d,)`` (m); ``inliers (n,)`` bool over the correspondences; ``rms_m`` = RMS
    residual (m) over the inliers; ``n_common`` = number of correspondences.
    """

    model: str
    scale: float
    R: F64
    t: F64
    inliers: NDArray[np.bool_]
    rms_m: float

    @property
    def dim(self) -> int:
        return int(self.R.shape[0])

    @property
    def n_common(self) -> int:
        return int(self.inliers.size)

    @property
    def rotation_deg(self) -> float:
        """Signed planar angle (2-D) or rotation angle (3-D), degrees."""
        if self.dim == 2:
            return float(np.degrees(np.arctan2(self.R[1, 0], self.R[0, 0])))
        c = np.clip((np.trace(self.R) - 1.0) / 2.0, -1.0, 1.0)
        return float(np.degrees(np.arccos(c)))

    def apply(self, pts: ArrayLike) -> F64:
        """Map points ``(..., d)`` from the source frame to the destination frame."""
        return self.scale * np.asarray(pts, dtype=np.float64) @ self.R.T + self.t

    def check_scale(self, lo: float = 0.9, hi: float = 1.1, allow: bool = False) -> Alignment:
        """Return self, or raise :class:`DataError` when the scale is outside ``[lo, hi]``."""
        if not allow and not lo <= self.scale <= hi:
            raise DataError(
                f"alignment scale {self.scale:.4f} is outside [{lo:.3f}, {hi:.3f}]: the two maps "
                "were probably built with different tag sizes; rebuild them with the same tag "
                "size, or accept it (align.allow_scale=true; tagtrail relocalize --allow-scale)"
            )
        return self


def _samples(n: int, k: int, iterations: int, seed: int) -> NDArray[np.intp]:
    """Minimal samples ``(H, k)``: all of them when few, else ``iterations`` seeded draws."""
    if comb(n, k) <= iterations:
        return np.array(list(itertools.combinations(range(n), k)), dtype=np.intp)
    rng = np.random.default_rng(seed)
    return np.argsort(rng.random((iterations, n)), axis=1)[:, :k]


def _residuals(s: F64, R: F64, t: F64, src: F64, dst: F64) -> F64:
    pred = s[..., None, None] * np.einsum("...ij,nj->...ni", R, src) + t[..., None, :]
    dist: F64 = np.linalg.norm(pred - dst, axis=-1)
    return dist


def ransac_align(
    src: ArrayLike,
    dst: ArrayLike,
    model: str = "similarity",
    threshold_m: float = 0.10,
    iterations: int = 300,
    seed: int = 0,
) -> Alignment:
    """Robust ``dst ≈ s R src + t`` from correspondences ``src, dst (n, d)`` (m), Eqs. 3.9–3.10.

    RANSAC over minimal samples (d points; every sample when there are at most ``iterations``,
    else ``iterations`` draws seeded by ``seed``): most inliers (residual ≤ ``threshold_m``) win,
    ties go to the smallest inlier residual sum. The model is then refitted on the inliers, and
    once more if that changes the inlier set. Raises :class:`DataError` on too few or degenerate
    correspondences.
    """
    if model not in MODELS:
        raise DataError(f"unknown alignment model {model!r}: use one of {', '.join(MODELS)}")
    d, with_scale = MODELS[model]
    src = np.asarray(src, dtype=np.float64).reshape(-1, d)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, d)
    n = len(src)
    if n < d or len(dst) != n:
        raise DataError(f"{model} alignment needs at least {d} common tags, found {n}")
    idx = _samples(n, d, max(1, int(iterations)), seed)
    s, R, t = umeyama(src[idx], dst[idx], with_scale)
    err = _residuals(s, R, t, src, dst)  # (H, n)
    valid = np.isfinite(s)
    inl = (err <= threshold_m) & valid[:, None]
    count = inl.sum(axis=1)
    cost = np.where(inl, err, 0.0).sum(axis=1)
    order = np.lexsort((cost, -count))
    mask = inl[order[0]]
    if not valid.any() or mask.sum() < d:
        raise DataError(
            f"{model} alignment: no {d} common tags agree within {threshold_m} m "
            "(the maps disagree, or the common tags coincide)"
        )
    s1, R1, t1 = umeyama(src[mask], dst[mask], with_scale)
    new = _residuals(s1, R1, t1, src, dst) <= threshold_m
    if not np.array_equal(new, mask) and new.sum() >= d:
        mask = new
        s1, R1, t1 = umeyama(src[mask], dst[mask], with_scale)
    if not np.isfinite(s1):
        raise DataError(f"{model} alignment: the inlier tags have no spread")
    r1 = _residuals(s1, R1, t1, src, dst)
    rms = float(np.sqrt(np.mean(r1[mask] ** 2)))
    return Alignment(model, float(s1), R1, t1, mask, rms)


def world_transform(al: Alignment, plane: Plane | None) -> tuple[F64, F64]:
    """``ref_A_query (4, 4)`` acting on positions and ``ref_R_query (3, 3)`` on orientations.

    3-D models: ``A = [sR | t]``, ``R``. Planar models, with ``B`` the rows (e1, e2, n):
    ``A[:3,:3] = Bᵀ diag(sR₂, 1) B``, ``A[:3,3] = t_u e1 + t_v e2``, ``R = Bᵀ diag(R₂, 1) B``.
    """
    A = np.eye(4)
    if al.dim == 3:
        A[:3, :3], A[:3, 3] = al.scale * al.R, al.t
        return A, al.R.copy()
    if plane is None:
        raise DataError("a planar alignment needs its plane")
    B = plane.basis
    M = np.eye(3)
    M[:2, :2] = al.scale * al.R
    A[:3, :3] = B.T @ M @ B
    A[:3, 3] = B[:2].T @ al.t
    return A, plane.rotation_about_normal(np.radians(al.rotation_deg))
