"""The solver: Levenberg-Marquardt with IRLS weights over the corners and a list of priors.

Cost: the corner term of :mod:`.problem` plus every prior's whitened terms (:class:`Terms`), each
under its own robust loss. The camera block of the normal equations is banded (a prior's term
ties at most frames ``k-1..k+1``: 17 sub-diagonals), so the cameras are eliminated by a banded
Cholesky (LAPACK ``pbtrf``) and the dense unknowns -- the free tags, then the priors' own (a
ground plane, a mount), coupled to every frame -- solved on their Schur complement. Left
perturbations ``R <- Exp(w) R``, ``t <- Exp(w) t + v`` of ``cam_T_world`` and ``world_T_tag``.
Covariances (the inverse of the normal matrix at the solution, times the a-posteriori variance
factor) give each tag's and each frame's standard deviation. Nothing here knows which priors
there are: a prior is on when it is in the list.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve, cho_solve_banded, cholesky_banded
from scipy.sparse import coo_matrix

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.joint.problem import (
    CornerObservations,
    Corners,
    JointResult,
    Prior,
    Terms,
    corner_jacobians,
    left_update,
    observation_rms_px,
    project,
    sum_blocks,
)
from tagtrail.geometry.robust import rho
from tagtrail.geometry.rotations import hat

BAND = 17  # sub-diagonals of the camera block: frames k-1, k, k+1 of 6 parameters each
_CHUNK = 20_000_000  # floats of A^-1 B held at once (Schur complement built in column chunks)


@dataclass(frozen=True)
class _State:
    """An estimate and what the cost says of it: the corner residuals ``r (O, 4, 2)``, points
    ``pw``/``pc`` (world, camera), IRLS weights ``w (O,)`` and each prior's terms."""

    R_cam: F64
    t_cam: F64
    R_tag: F64
    t_tag: F64
    values: Mapping[str, Any]
    cost: float
    r: F64
    pw: F64
    pc: F64
    w: F64
    terms: tuple[Terms, ...]


@dataclass(frozen=True)
class _Normal:
    """The normal equations: camera blocks ``Ablk (F, 3, 6, 6)`` (``Ablk[f, d]``: block row
    ``f + d``, column ``f``) and gradient ``gc (F, 6)``; free tags' blocks ``Htt``, ``gt``; the
    priors' unknowns' block ``Hgg``, ``gg`` (None without); ``B`` the coupling of the cameras
    with the dense unknowns."""

    Ablk: F64
    gc: F64
    Htt: F64
    gt: F64
    Hgg: F64 | None
    gg: F64 | None
    B: Any


class _Problem:
    """The fixed parts of one solve: index maps, the priors' column offsets, the corner
    weights (rescaled once with ``estimate_noise``)."""

    def __init__(
        self,
        ob: CornerObservations,
        free: np.ndarray,
        n_f: int,
        n_t: int,
        corners: Corners,
        priors: Sequence[Prior],
    ) -> None:
        self.ob, self.n_f, self.n_t, self.n_o = ob, n_f, n_t, len(ob.frame)
        self.corners, self.priors = corners, tuple(priors) if n_f else ()
        self.free_idx = np.flatnonzero(np.asarray(free, bool))
        self.n_free = len(self.free_idx)
        col = np.full(n_t, -1)
        col[self.free_idx] = np.arange(self.n_free)
        self.of = np.flatnonzero(np.asarray(free, bool)[ob.tag])  # observations of free tags
        self.brow = np.broadcast_to(
            (6 * ob.frame[self.of])[:, None, None] + np.arange(6)[:, None], (len(self.of), 6, 6)
        ).reshape(-1)
        self.bcol = np.broadcast_to(
            (6 * col[ob.tag[self.of]])[:, None, None] + np.arange(6)[None, :], (len(self.of), 6, 6)
        ).reshape(-1)
        names = [p.name for p in self.priors]
        for p in self.priors:
            if not set(p.uses) <= set(names):
                raise ValueError(
                    f"solve_joint: the {p.name} prior needs the "
                    f"{', '.join(sorted(set(p.uses) - set(names)))} prior"
                )
        self.offset: dict[str, int] = {}
        for p in self.priors:  # each prior's own unknowns, in the list's order
            self.offset[p.name] = sum(q.n_params for q in self.priors if q.name in self.offset)
        self.n_g = sum(p.n_params for p in self.priors)  # the priors' unknowns
        self.cols = [
            np.concatenate(
                [np.arange(self.offset[u], self.offset[u] + self._n(u)) for u in p.uses]
            ).astype(np.int64)
            if p.uses
            else np.zeros(0, np.int64)
            for p in self.priors
        ]
        self.n_dense = 6 * self.n_free + self.n_g  # columns of B: the free tags', the priors'
        if self.n_g:  # the priors' block column in B: every frame's 6 rows x the n_g parameters
            self.prow = np.broadcast_to(
                (6 * np.arange(n_f))[:, None, None] + np.arange(6)[:, None], (n_f, 6, self.n_g)
            ).reshape(-1)
            self.pcol = np.broadcast_to(
                6 * self.n_free + np.arange(self.n_g)[None, :], (n_f, 6, self.n_g)
            ).reshape(-1)
        self.bidx = _band_index(n_f)
        self.last_step = 0.0  # the largest parameter change of the last step taken
        self.eye3 = np.broadcast_to(np.eye(3), (self.n_o, 4, 3, 3))
        # normalised coordinates -> units of each observation's corner noise
        self.set_noise(
            np.broadcast_to(np.asarray(corners.sigma_px, np.float64), (self.n_o,)).copy()
        )

    def _n(self, name: str) -> int:
        return next(p.n_params for p in self.priors if p.name == name)

    def set_noise(self, sig: F64) -> None:
        self.sig = sig
        self.scale = self.corners.px_per_unit / sig
        f = self.corners.f_scale_px / float(np.median(sig)) if self.n_o else 1.0
        self.f2 = f * f

    def evaluate(self, Rc: F64, tc: F64, Rt: F64, tt: F64, values: Mapping[str, Any]) -> _State:
        r, pw, pc = project(Rc, tc, Rt, tt, self.ob)
        sq = np.sum(r * r, axis=(1, 2)) * self.scale**2
        bad = (pc[..., 2] <= 1e-6).any(axis=1)  # behind the camera: an outlier, no gradient
        val, w = rho(self.corners.loss, np.where(bad, 1e12, sq) / self.f2)
        terms = tuple(p.terms(Rc, tc, values) for p in self.priors)
        cost = float(self.f2 * val.sum())
        for t in terms:
            cost += t.cost
        return _State(Rc, tc, Rt, tt, values, cost, r, pw, pc, np.where(bad, 0.0, w), terms)

    def normal_equations(self, s: _State) -> _Normal:
        ob, n_o, n_f, n_t, scale = self.ob, self.n_o, self.n_f, self.n_t, self.scale
        Jp, Jc = corner_jacobians(s.pc, scale)
        Jt = Jp @ s.R_cam[ob.frame][:, None] @ np.concatenate([-hat(s.pw), self.eye3], axis=-1)
        Jt = Jt.reshape(n_o, 8, 6)
        rv = s.r.reshape(n_o, 8) * scale[:, None]
        w = s.w
        W = w[:, None, None]
        Ablk = np.zeros((n_f, 3, 6, 6))
        Ablk[:, 0] = sum_blocks(np.einsum("oki,okj->oij", Jc, Jc) * W, ob.frame, n_f)
        gc = sum_blocks(np.einsum("oki,ok->oi", Jc, rv) * w[:, None], ob.frame, n_f)
        Hgg = gg = Bg = None
        if self.n_g:
            Hgg, gg, Bg = (
                np.zeros((self.n_g, self.n_g)),
                np.zeros(self.n_g),
                np.zeros((n_f, 6, self.n_g)),
            )
        for t, cols in zip(s.terms, self.cols, strict=True):
            n = t.Jc.shape[1]  # consecutive frames first .. first + n - 1 (unique per term)
            for i in range(n):
                gc[t.first + i] += np.einsum("mki,mk->mi", t.Jc[:, i], t.r)
                for j in range(i, n):  # block row first+j, column first+i
                    Ablk[t.first + i, j - i] += np.einsum("mki,mkj->mij", t.Jc[:, j], t.Jc[:, i])
            if t.Jg is not None and len(cols):
                assert Hgg is not None and gg is not None and Bg is not None
                Hgg[np.ix_(cols, cols)] += np.einsum("mki,mkj->ij", t.Jg, t.Jg)
                gg[cols] += np.einsum("mki,mk->i", t.Jg, t.r)
                for i in range(n):
                    Bg[
                        (t.first + i)[:, None, None],
                        np.arange(6)[None, :, None],
                        cols[None, None, :],
                    ] += np.einsum("mki,mkj->mij", t.Jc[:, i], t.Jg)
        Htt = sum_blocks(np.einsum("oki,okj->oij", Jt, Jt) * W, ob.tag, n_t)[self.free_idx]
        gt = sum_blocks(np.einsum("oki,ok->oi", Jt, rv) * w[:, None], ob.tag, n_t)[self.free_idx]
        Hct = (np.einsum("oki,okj->oij", Jc, Jt) * W)[self.of]
        vals, rows, cols_ = Hct.reshape(-1), self.brow, self.bcol
        if Hgg is not None and Bg is not None:
            # unknowns the frames leave undetermined (a parked robot: the plane's normal; a
            # straight drive: its roll about the path, the lever arm) take no step that way,
            # instead of crawling
            Hgg += 1e-6 * np.trace(Hgg) / self.n_g * np.eye(self.n_g)
            vals = np.concatenate([vals, Bg.reshape(-1)])
            rows, cols_ = np.concatenate([rows, self.prow]), np.concatenate([cols_, self.pcol])
        B = coo_matrix((vals, (rows, cols_)), shape=(6 * n_f, self.n_dense)).tocsc()
        return _Normal(Ablk, gc, Htt, gt, Hgg, gg, B)

    def schur(self, cb: F64, ne: _Normal, lam: float) -> F64:
        C = np.zeros((self.n_dense, self.n_dense))
        blocks = [*ne.Htt, *([] if ne.Hgg is None else [ne.Hgg])]
        eps = 1e-9 * max(float(np.mean([np.trace(H) / len(H) * 6 for H in blocks])), 1e-300)
        for i, H in enumerate(blocks):  # eps: a tag nothing constrains gets no step, not a NaN
            sl = slice(6 * i, 6 * i + len(H))
            C[sl, sl] = H * (1.0 + lam * np.eye(len(H))) + eps * np.eye(len(H))
        step = max(6, (_CHUNK // max(6 * self.n_f, 1)) // 6 * 6)
        for c0 in range(0, self.n_dense, step):
            Bc = ne.B[:, c0 : c0 + step]
            X = cho_solve_banded((cb, True), Bc.toarray())
            C[:, c0 : c0 + step] -= ne.B.T @ X
        return C

    def step(self, s: _State, ne: _Normal, lam: float) -> _State | None:
        """The state after the damped step at ``lam``; None when the system fails."""
        n_t, n_f = self.n_t, self.n_f
        try:
            cb = cholesky_banded(_band(ne.Ablk, self.bidx, lam), lower=True)
            dt = np.zeros((n_t, 6))
            dg = np.zeros(self.n_g)
            if self.n_dense:
                y = cho_solve_banded((cb, True), ne.gc.reshape(-1))
                S = self.schur(cb, ne, lam)
                rhs = (
                    -np.concatenate([ne.gt.reshape(-1), [] if ne.gg is None else ne.gg])
                    + ne.B.T @ y
                )
                dd = cho_solve(cho_factor(S), rhs)
                dt[self.free_idx] = dd[: 6 * self.n_free].reshape(self.n_free, 6)
                dg = dd[6 * self.n_free :]
                dcv = -y - cho_solve_banded((cb, True), ne.B @ dd)
            else:
                dcv = -cho_solve_banded((cb, True), ne.gc.reshape(-1))
            dc = dcv.reshape(n_f, 6)
            if not (np.isfinite(dc).all() and np.isfinite(dt).all() and np.isfinite(dg).all()):
                return None
        except (LinAlgError, ValueError):
            return None
        Rc, tc = left_update(s.R_cam, s.t_cam, dc)
        Rt, tt = left_update(s.R_tag, s.t_tag, dt)
        values = {
            p.name: p.update(
                s.values[p.name],
                dg[self.offset[p.name] : self.offset[p.name] + p.n_params],
                s.values,
            )
            for p in self.priors
        }
        new = self.evaluate(Rc, tc, Rt, tt, values)
        self.last_step = float(
            max(
                np.abs(dt).max(initial=0.0),
                np.abs(dc).max(initial=0.0),
                np.abs(dg).max(initial=0.0),
            )
        )
        return new


def solve_joint(
    R_tag: F64,
    t_tag: F64,
    R_cam: F64,
    t_cam: F64,
    ob: CornerObservations,
    free: np.ndarray,
    corners: Corners,
    priors: Sequence[Prior] = (),
    *,
    max_iter: int = 50,
    covariance: bool | Literal["last"] = False,
) -> JointResult:
    """Minimise the corners' cost and the ``priors``' over the free tags (``free (T,)`` bool),
    every camera and the priors' own unknowns (from their ``start``), from the given start;
    cameras in time order (the priors' terms tie consecutive frames). ``covariance``: the
    standard deviations and each frame's covariance too (``"last"``: the last frame's only, the
    others NaN -- a live smoother's newest pose, at a fraction of the cost).
    ``JointResult.sigma_px`` reports the median corner noise used (``corners.estimate_noise``:
    the residuals')."""
    n_f, n_t = len(R_cam), len(R_tag)
    pb = _Problem(ob, free, n_f, n_t, corners, priors)
    n_o = pb.n_o
    s = pb.evaluate(R_cam, t_cam, R_tag, t_tag, {p.name: p.start for p in pb.priors})
    it = 0
    for round_ in range(2 if corners.estimate_noise and n_o else 1):
        if round_:  # the corner noise the residuals show, then the solve again from there
            sq0 = np.sum(s.r * s.r, axis=(1, 2)) * pb.scale**2
            dof0 = 8 * n_o - 6 * (n_f + pb.n_free)
            if dof0 <= 0:
                break
            factor = float(np.sum(s.w * sq0) / dof0)
            pb.set_noise(np.clip(pb.sig * np.sqrt(factor), 0.05, 5.0))
            s = pb.evaluate(s.R_cam, s.t_cam, s.R_tag, s.t_tag, s.values)
        lam, converged = 1e-4, n_o == 0
        while it < max_iter * (round_ + 1) and n_o:
            ne = pb.normal_equations(s)
            while True:
                new = pb.step(s, ne, lam)
                if new is not None and new.cost <= s.cost:
                    break
                if lam > 1e8:
                    break
                lam *= 10.0
            if new is None or new.cost > s.cost:
                converged = True  # no descent left at any damping: a (local) minimum
                break
            # a decrease of the whitened cost (a chi^2) under 1e-6 changes nothing: a flat
            # direction (a parked robot's undetermined ground plane) is not crawled along
            done = s.cost - new.cost <= max(1e-10 * s.cost, 1e-6) or pb.last_step < 1e-12
            s = new
            it, lam = it + 1, max(lam / 10.0, 1e-9)
            if done:
                converged = True
                break
    sq = np.sum(s.r * s.r, axis=(1, 2)) * pb.scale**2
    dof = 8 * n_o - 6 * (n_f + pb.n_free)
    chi2 = float(np.sum(s.w * sq))
    for t in s.terms:
        dof += t.dof
        chi2 += float(np.sum(t.r**2))
    vf = chi2 / dof if dof > 0 else float("nan")
    res_px = observation_rms_px(s.R_cam, s.t_cam, s.R_tag, s.t_tag, ob, corners.px_per_unit)
    tag_std = cam_std = cam_cov = tail_cov = None
    if covariance and n_o:
        tag_std, cam_std, cam_cov, tail_cov = _std(
            pb,
            pb.normal_equations(s),
            s.t_tag,
            max(vf, 1.0) if np.isfinite(vf) else 1.0,
            last_only=covariance == "last",
        )
    return JointResult(
        s.R_tag,
        s.t_tag,
        s.R_cam,
        s.t_cam,
        res_px,
        s.cost,
        it,
        converged,
        vf,
        float(np.median(pb.sig)) if n_o else float("nan"),
        {p.name: len(t.r) for p, t in zip(pb.priors, s.terms, strict=True)},
        dict(s.values),
        tag_std,
        cam_std,
        cam_cov,
        tail_cov,
    )


def _band_index(n_f: int) -> tuple[I64, I64, I64, I64, I64]:
    """Scatter indices from camera blocks ``Ablk (F, 3, 6, 6)`` (``Ablk[f, d]`` = block row
    ``f + d``, column ``f``) into LAPACK's lower band storage ``ab (BAND + 1, 6F)``."""
    d, a, b = np.meshgrid(np.arange(3), np.arange(6), np.arange(6), indexing="ij")
    keep = (6 * d + a - b) >= 0
    d, a, b = d[keep], a[keep], b[keep]
    f = np.arange(n_f)
    rows = np.broadcast_to((6 * d + a - b)[:, None], (len(d), n_f))
    cols = 6 * f[None, :] + b[:, None]
    return rows, cols, d, a, b


def _band(Ablk: F64, idx: tuple[I64, I64, I64, I64, I64], lam: float) -> F64:
    rows, cols, d, a, b = idx
    n_f = len(Ablk)
    ab = np.zeros((BAND + 1, 6 * n_f))
    ab[rows, cols] = np.moveaxis(Ablk[:, d, a, b], 0, 1)
    ab[0] *= 1.0 + lam
    ab[0] += 1e-12
    return ab


def _banded_diag_inverse(cb: F64) -> F64:
    """The 6x6 diagonal blocks ``(F, 6, 6)`` of ``A^-1`` from the lower banded Cholesky factor
    ``cb`` of ``A`` (Takahashi's recursion on the band, O(n band^2))."""
    n, b = cb.shape[1], cb.shape[0] - 1
    Z = np.zeros((b + 1, n + b))  # Z[d, j] = (A^-1)[j + d, j]; padded columns are zero
    pad = np.zeros((b + 1, n + b))
    pad[:, :n] = cb
    # window W[p, q] = Z[j+1+p, j+1+q] over the next b indices, read from band storage
    dd = np.abs(np.arange(b)[:, None] - np.arange(b)[None, :])
    lo = np.minimum(np.arange(b)[:, None], np.arange(b)[None, :]) + 1
    for j in range(n - 1, -1, -1):
        ljj, lv = pad[0, j], pad[1:, j]
        W = Z[dd, j + lo]
        zc = -(W @ lv) / ljj
        Z[1:, j] = zc
        Z[0, j] = 1.0 / (ljj * ljj) - (lv @ zc) / ljj
    out = np.zeros((n // 6, 6, 6))
    for p in range(6):
        for q in range(6):
            lo_, d_ = min(p, q), abs(p - q)
            out[:, p, q] = Z[d_, np.arange(n // 6) * 6 + lo_]
    return out


def _std(
    pb: _Problem, ne: _Normal, t_tag: F64, vf: float, last_only: bool = False
) -> tuple[F64, F64, F64, F64 | None]:
    """Per-tag and per-frame ``(position m, rotation rad)`` standard deviations (RMS over the
    axes) and each frame's 6x6 covariance, from the inverse normal matrix, scaled by the
    variance factor ``vf`` (>= 1); ``last_only``: also the last two frames' joint covariance
    ``(12, 12)``, unscaled (None with dense unknowns, or one frame)."""
    Ablk, Htt, Hgg, B = ne.Ablk, ne.Htt, ne.Hgg, ne.B
    free_idx, n_t, bidx = pb.free_idx, pb.n_t, pb.bidx
    n_f = len(Ablk)
    cb = cholesky_banded(_band(Ablk, bidx, 0.0), lower=True)
    tail_cov = None
    if last_only:  # the last 12 columns of A^-1 by two banded solves
        m = min(12, 6 * n_f)
        E = np.zeros((6 * n_f, m))
        E[-m:] = np.eye(m)
        tail = cho_solve_banded((cb, True), E)[-m:]
        cam_cov = np.full((n_f, 6, 6), np.nan)
        cam_cov[-1] = tail[-6:, -6:]
        if m == 12 and not pb.n_dense:
            tail_cov = 0.5 * (tail + tail.T)
    elif np.any(Ablk[:, 1:]):  # frames coupled by the prior: the band's selected inverse
        cam_cov = _banded_diag_inverse(cb)
    else:  # independent frames: each block's own inverse
        cam_cov = np.asarray(np.linalg.inv(Ablk[:, 0] + 1e-12 * np.eye(6)), np.float64)
    tag_std = np.zeros((n_t, 2))
    if len(Htt) or Hgg is not None:  # the free tags, then the ground plane (and mount) if any
        S = pb.schur(cb, ne, 0.0)
        Sinv = cho_solve(cho_factor(S), np.eye(len(S)))
        if len(free_idx):
            blocks = np.stack(
                [Sinv[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(len(free_idx))]
            )
            J = np.zeros((len(free_idx), 3, 6))
            J[:, :, :3] = -hat(t_tag[free_idx])  # d t = -hat(t) w + v
            J[:, :, 3:] = np.eye(3)
            pos = np.einsum("nij,njk,nlk->nil", J, blocks, J)
            tag_std[free_idx, 0] = np.sqrt(np.trace(pos, axis1=1, axis2=2) * vf / 3)
            tag_std[free_idx, 1] = np.sqrt(np.trace(blocks[:, :3, :3], axis1=1, axis2=2) * vf / 3)
        if 6 * n_f * len(S) <= _CHUNK:  # the map's share: X S^-1 X^T, X = A^-1 B
            X = cho_solve_banded((cb, True), B.toarray()).reshape(n_f, 6, -1)
            cam_cov = cam_cov + np.einsum("fik,fjk->fij", X @ Sinv, X)
    cam_cov = cam_cov * vf
    cam_std = np.stack(
        [
            np.sqrt(np.trace(cam_cov[:, 3:, 3:], axis1=1, axis2=2) / 3),
            np.sqrt(np.trace(cam_cov[:, :3, :3], axis1=1, axis2=2) / 3),
        ],
        axis=1,
    )
    return tag_std, cam_std, cam_cov, tail_cov
