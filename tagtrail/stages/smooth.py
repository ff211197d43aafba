"""smooth: temporal regularisation of the raw trajectory (paper Sec. 3.1, before export).

``method="lsq"``: robust sparse least squares on SO(3) x R^3 -- a data term keeping each pose
near its raw estimate plus a penalty on linear and angular accelerations (second differences,
non-uniform stamps; see :mod:`tagtrail.geometry.smoothing`). Weights are 1/standard deviation:
``pos_sigma_m`` / ``rot_sigma_deg`` (per-frame noise of the raw poses) against ``pos_acc_mps2`` /
``rot_acc_dps2`` (plausible accelerations); the robust ``loss`` (scale ``f_scale`` standard
deviations) keeps manoeuvres and rejects outlier frames. Segments break at gaps > ``max_gap_s``.
``method="none"`` passes the trajectory through unchanged; ``"auto"`` (default) is ``none`` for a
trajectory already held together by the motion prior of the joint solve (rows with
``motion_prior``: smoothing it again would only move it away from its evidence) and ``lsq``
otherwise (frame-by-frame trajectories: pairwise maps, observation-only datasets). The defaults
favour the heading of short segments (what ``report``'s point mode compares a parked query with)
without cutting the corners of a room loop. The change it makes is added to each row's
``shift_m`` / ``shift_deg`` (the distance from the frame's own evidence, when the trajectory
carries it); its ``reproj_px`` and ``shift_sigma`` become unknown (NaN): the smoother sees no
corners.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field

from tagtrail.geometry.robust import LossName
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import R_from_quat_xyzw, quat_xyzw_from_R
from tagtrail.geometry.smoothing import smooth_poses
from tagtrail.schemas.artifacts import EVIDENCE_COLS, POSE_COLS, STD_COLS, timed
from tagtrail.stages.base import Export, ExportFiles, StageParams


class Params(StageParams):
    method: Literal["auto", "none", "lsq"] = "auto"
    """``lsq``: robust least-squares smoothing of the trajectory; ``none``: passed through;
    ``auto``: ``none`` when the trajectory stage's motion prior already held the frames, else
    ``lsq``."""
    pos_sigma_m: float = Field(0.01, ge=1e-6, le=10.0)
    """Per-frame position noise of the raw trajectory (m): weight of the position data term."""
    rot_sigma_deg: float = Field(1.0, ge=1e-4, le=180.0)
    """Per-frame orientation noise (deg): weight of the rotation data term."""
    pos_acc_mps2: float = Field(0.2, ge=1e-6, le=1000.0)
    """Standard deviation of the linear acceleration (m/s^2): smaller = smoother positions."""
    rot_acc_dps2: float = Field(60.0, ge=1e-4, le=1e5)
    """Standard deviation of the angular acceleration (deg/s^2): smaller = smoother rotations."""
    loss: LossName = "soft_l1"
    """Robust loss on each data and smoothness term: linear, soft_l1, huber, cauchy."""
    f_scale: float = Field(3.0, ge=1e-3, le=1000.0)
    """Robust scale, in standard deviations of each term."""
    max_gap_s: float = Field(1.0, gt=0.0, le=1e6)
    """Stamps further apart than this start a new segment (no smoothing across the gap)."""


INPUTS = {"trajectory": "trajectory.trajectory", "frames": "extract.frames"}
OUTPUTS = ("trajectory",)
SCOPE = "all"


def run(
    trajectory: pd.DataFrame, params: Params, frames: pd.DataFrame | None = None
) -> dict[str, Any]:
    """The smoothed trajectory: same rows (sorted by ``t_ns``) and columns as the input. Frames
    whose stamps are only an image folder's file order (``extract.frames.timed``) are not
    smoothed: nothing links them in time."""
    traj = trajectory.sort_values("t_ns", kind="stable").reset_index(drop=True)
    prior = "motion_prior" in traj.columns and bool(traj["motion_prior"].any())
    if (
        params.method == "none"
        or (params.method == "auto" and prior)
        or len(traj) < 3
        or not timed(frames)
    ):
        return {"trajectory": traj}
    t_ns = traj["t_ns"].to_numpy(np.int64)
    t_s = (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    vals = traj[POSE_COLS].to_numpy(np.float64)
    R0 = R_from_quat_xyzw(vals[:, 3:])
    R, p = smooth_poses(
        t_s,
        R0,
        vals[:, :3],
        pos_sigma_m=params.pos_sigma_m,
        rot_sigma_rad=np.deg2rad(params.rot_sigma_deg),
        pos_acc=params.pos_acc_mps2,
        rot_acc=np.deg2rad(params.rot_acc_dps2),
        loss=params.loss,
        f_scale=params.f_scale,
        max_gap_s=params.max_gap_s,
    )
    out = traj.copy()
    out[POSE_COLS] = np.concatenate([p, quat_xyzw_from_R(R)], axis=1)
    if "shift_m" in out.columns:  # camera centre and orientation moved by the smoothing
        out["shift_m"] += np.linalg.norm(p - vals[:, :3], axis=1)
        out["shift_deg"] += np.degrees(geodesic_angle(R, R0))
        out["reproj_px"] = out["shift_sigma"] = np.nan
    return {"trajectory": out}


def _trajectory_files(trajectory: pd.DataFrame | None) -> ExportFiles | None:
    """``trajectory.csv``, ``trajectory.tum``; with them ``trajectory_std.csv`` (each frame's
    standard deviation) and ``trajectory_evidence.csv`` (each frame's fit to its own corners)
    when the trajectory has them (else a stale one from another run is removed)."""
    if trajectory is None:
        return None
    files: dict[str, tuple[str, Any] | None] = {
        "trajectory.csv": ("trajectory_csv", trajectory),
        "trajectory.tum": ("trajectory_tum", trajectory),
    }
    for name, cols, fmt in (
        ("trajectory_std.csv", STD_COLS, "trajectory_std_csv"),
        ("trajectory_evidence.csv", EVIDENCE_COLS, "trajectory_evidence_csv"),
    ):
        has = all(c in trajectory.columns for c in cols) and trajectory[cols[0]].notna().any()
        files[name] = (fmt, trajectory) if has else None
    return files


EXPORTS = (
    Export(
        "trajectories",
        ("trajectory.csv", "trajectory.tum", "trajectory_std.csv", "trajectory_evidence.csv"),
        {"trajectory": "smooth.trajectory"},
        _trajectory_files,
    ),
)
