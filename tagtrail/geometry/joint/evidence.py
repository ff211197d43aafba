"""The evidence of a joint solution: how far each frame sits from its own corners, and how far
the priors moved it from the frame solved on its corners alone."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.joint.problem import (
    CornerObservations,
    Corners,
    JointResult,
    centres,
    frame_rms_px,
)
from tagtrail.geometry.joint.solver import solve_joint
from tagtrail.geometry.rotations import log_so3
from tagtrail.geometry.se3 import R_from_rotvec


@dataclass(frozen=True)
class FrameEvidence:
    """How far each frame of a joint solution sits from its own corners: ``reproj_px (F,)`` its
    RMS corner error, ``alone_reproj_px`` that of the frame solved on its corners alone (the map
    fixed, no motion prior: the per-frame solution), ``shift_m`` / ``shift_deg`` the change of
    the camera centre and orientation the motion prior made, ``shift_sigma`` that change in the
    per-frame solution's standard deviations (Mahalanobis distance over the 6 pose parameters:
    below 4.74 in 99.9 % of frames when the prior only removes noise of the assumed size);
    ``R_alone (F, 3, 3)``, ``t_alone (F, 3)``: the per-frame solution's ``cam_T_world``."""

    reproj_px: F64
    alone_reproj_px: F64
    shift_m: F64
    shift_deg: F64
    shift_sigma: F64
    R_alone: F64
    t_alone: F64


SHIFT_SIGMA_BOUND = 4.74  # sqrt of chi^2 with 6 dof at 99.9 %


def frame_evidence(
    res: JointResult, ob: CornerObservations, corners: Corners, max_iter: int = 50
) -> FrameEvidence:
    """:class:`FrameEvidence` of the cameras of ``res`` (tags fixed): every frame solved again on
    its own corners from where the joint solution left it (the same corner model, no prior),
    then compared with it."""
    n_f = len(res.R_cam)
    alone = solve_joint(
        res.R_tag,
        res.t_tag,
        res.R_cam,
        res.t_cam,
        ob,
        np.zeros(len(res.R_tag), bool),
        corners,
        max_iter=max_iter,
        covariance=True,
    )
    w = log_so3(res.R_cam @ np.swapaxes(alone.R_cam, 1, 2))
    d = np.concatenate(
        [w, res.t_cam - np.einsum("nij,nj->ni", R_from_rotvec(w), alone.t_cam)], axis=1
    )
    assert alone.cam_cov is not None
    vf = alone.variance_factor if np.isfinite(alone.variance_factor) else 1.0
    cov = alone.cam_cov * (vf / max(vf, 1.0))  # at the noise the residuals show, not above it
    maha = np.einsum("ni,ni->n", d, np.linalg.solve(cov, d[..., None])[..., 0])
    centre, centre_alone = centres(res.R_cam, res.t_cam), centres(alone.R_cam, alone.t_cam)
    return FrameEvidence(
        reproj_px=frame_rms_px(res.res_px, ob.frame, n_f),
        alone_reproj_px=frame_rms_px(alone.res_px, ob.frame, n_f),
        shift_m=np.linalg.norm(centre - centre_alone, axis=1),
        shift_deg=np.degrees(np.linalg.norm(w, axis=1)),
        shift_sigma=np.sqrt(np.maximum(maha, 0.0)),
        R_alone=alone.R_cam,
        t_alone=alone.t_cam,
    )


def evidence_rows(
    reproj_px: F64, alone_reproj_px: F64, shift_m: F64, shift_deg: F64, shift_sigma: F64
) -> list[tuple[str, float | int | str]]:
    """A trajectory against its evidence (the columns of :class:`FrameEvidence`, NaN: unknown),
    as ``diagnostics.csv`` rows: corner RMS of the output and of the frames on their own corners
    (medians, and their ratio), the temporal step's change, and the frames it moved beyond their
    own uncertainty (``""``: unknown)."""

    def med(v: F64) -> float | str:
        return float(np.nanmedian(v)) if np.isfinite(v).any() else ""

    def top(v: F64) -> float | str:
        return float(np.nanmax(v)) if np.isfinite(v).any() else ""

    rp, ar = med(reproj_px), med(alone_reproj_px)
    sig = shift_sigma
    beyond = int(np.sum(sig > SHIFT_SIGMA_BOUND)) if np.isfinite(sig).any() else ""
    ratio = rp / ar if isinstance(rp, float) and isinstance(ar, float) and ar > 0 else ""
    return [
        ("frame_reproj_px_median", rp),
        ("frame_alone_reproj_px_median", ar),
        ("frame_reproj_ratio", ratio),
        ("frame_shift_m_median", med(shift_m)),
        ("frame_shift_m_max", top(shift_m)),
        ("frame_shift_deg_max", top(shift_deg)),
        ("frame_shift_sigma_max", top(shift_sigma)),
        ("frames_moved_beyond_evidence", beyond),
    ]
