"""The cameras against a fixed map (stage ``trajectory``): the joint solve with no tag free
(:func:`solve_track`), and the corner error of poses found frame by frame
(:func:`posed_rms_px`)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.joint.evidence import FrameEvidence, frame_evidence
from tagtrail.geometry.joint.odometry import OdometryData
from tagtrail.geometry.joint.problem import CornerRows, frame_rms_px, observation_rms_px
from tagtrail.geometry.joint.settings import JointSettings
from tagtrail.geometry.joint.setup import Solved, corner_problem, solve_on_corners
from tagtrail.geometry.se3 import T_from_xyz_quat, inv, make_T, xyz_quat_from_T

# the per-frame figures of :class:`FrameEvidence` (the trajectory's evidence columns)
EVIDENCE = tuple(f.name for f in fields(FrameEvidence) if f.name not in ("R_alone", "t_alone"))


@dataclass(frozen=True)
class Track:
    """The cameras of the frames ``t_ns (F,)`` (time order): ``pose (F, 7)`` ``world_T_cam``
    (x, y, z, qx, qy, qz, qw), tags seen ``n_tags``, standard deviations ``std (F, 2)`` (m,
    rad; None: not computed), whether the motion prior held them (``motion_prior``), their
    evidence (the figures :data:`EVIDENCE`, each ``(F,)``) and the frame on its own corners
    ``alone (F, 7)`` (None: the pose itself); the solve (its ground report, convergence,
    corner residuals)."""

    t_ns: I64
    pose: F64
    n_tags: I64
    std: F64 | None
    motion_prior: bool
    evidence: dict[str, F64]
    alone: F64 | None
    solved: Solved


def _pose_of(R_cam: F64, t_cam: F64) -> F64:
    """``world_T_cam`` as ``(F, 7)`` of cameras ``cam_T_world`` ``(R, t)``."""
    xyz, q = xyz_quat_from_T(inv(make_T(R_cam, t_cam)))
    return np.concatenate([xyz, q], axis=1)


def solve_track(
    rows: CornerRows,
    ids: I64,
    W_map: F64,
    camera: CameraModel,
    settings: JointSettings,
    timed: bool,
    fallback: tuple[bool, bool] | None,
    priors: bool = True,
    odometry: OdometryData | None = None,
) -> Track:
    """The cameras of the corner ``rows`` of the mapped tags ``ids`` (sorted; map ``W_map``,
    fixed) under the map's ``settings``; ``fallback``: the map's ground-plane and drive
    decisions, for data too short or too still to decide on; ``priors`` False: each frame on
    its own corners (then its own evidence); ``odometry``: the wheel-odometry prior's data
    (frames with no tag it covers are posed, ``n_tags`` 0, no evidence)."""
    pb = corner_problem(rows, np.searchsorted(ids, rows.tag_id), camera, settings, timed, priors)
    solved = solve_on_corners(
        pb,
        W_map,
        np.zeros(len(ids), bool),
        settings,
        fallback=fallback,
        odometry=odometry if priors else None,
    )
    pb = solved.pb  # with the frames the odometry posed
    res, n_f = solved.res, len(pb.t_ns)
    alone = None
    if pb.motion is not None:
        ev = frame_evidence(res, pb.ob, pb.corners)
        evidence = {c: getattr(ev, c) for c in EVIDENCE}
        alone = _pose_of(ev.R_alone, ev.t_alone)
    else:  # each frame on its own corners: it is its own evidence
        rms = frame_rms_px(res.res_px, pb.ob.frame, n_f)
        zero = np.zeros(n_f)
        evidence = dict(
            reproj_px=rms, alone_reproj_px=rms, shift_m=zero, shift_deg=zero, shift_sigma=zero
        )
    n_tags = np.bincount(pb.ob.frame, minlength=n_f)
    for c in EVIDENCE:  # a frame posed by the odometry alone has no corners to show
        evidence[c] = np.where(n_tags == 0, np.nan, evidence[c])
    pose = _pose_of(res.R_cam, res.t_cam)
    return Track(pb.t_ns, pose, n_tags, res.cam_std, pb.motion is not None, evidence, alone, solved)


def posed_rms_px(
    rows: CornerRows, ids: I64, W_map: F64, camera: CameraModel, frame_idx: I64, pose: F64
) -> F64:
    """Each frame's RMS corner error ``(F,)`` (px; NaN: no corners) at the poses ``pose (F, 7)``
    (``world_T_cam``) of the frames ``frame_idx`` (sorted), from the corner ``rows`` of the
    mapped tags ``ids`` (map ``W_map``) in those frames."""
    rms = np.full(len(frame_idx), np.nan)
    if not len(rows.t_ns):
        return rms
    ob, _ = rows.observations(np.searchsorted(ids, rows.tag_id), camera)
    frames, first = np.unique(rows.frame_idx, return_index=True)
    order = np.argsort(rows.t_ns[first], kind="stable")
    where = np.searchsorted(frame_idx, frames[order])  # ob's frames are in time order
    cam_T_world = inv(T_from_xyz_quat(pose[where, :3], pose[where, 3:]))
    R_cam, t_cam = cam_T_world[:, :3, :3], cam_T_world[:, :3, 3]
    res = observation_rms_px(R_cam, t_cam, W_map[:, :3, :3], W_map[:, :3, 3], ob, camera.focal_px)
    rms[where] = frame_rms_px(res, ob.frame, len(where))
    return rms
