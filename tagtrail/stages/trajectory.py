"""trajectory: ``world_T_cam`` per frame from the tag map and that frame's observations (Eq. 3.8).

``joint`` (what ``auto`` picks when the dataset has detections and a camera): every frame's
camera pose on its tags' corners against the fixed map, held together in time by the priors of
:mod:`tagtrail.geometry.joint` -- the same problem as ``optimize``'s joint solve with the map
fixed, under the map's settings (``optimize.report.joint``, the ``map_report`` input: wire it to
the dataset whose ``tag_map`` you use, e.g. ``reference:optimize.report`` for a query), so on the
reference recording it is the joint solution's trajectory. On data too short or too still to
decide the ground-plane and wheeled-drive priors on (a parked query), the map's decisions are
taken. Each frame starts from the IPPE solution its neighbours agree with; a single-tag
frame is held by its neighbours; frames further apart than ``max_gap_s`` are not linked, and
frames without a tag get no pose -- unless the dataset's wheel odometry covers them (the map's
``joint.odometry``, geometry.joint.odometry): then they are posed by it (``n_tags`` 0, their
standard deviation growing away from the tags, no evidence), up to 10 s from a tag. Rows
carry ``std_pos_m`` / ``std_rot_deg`` (the frame's
standard deviation given the map), ``motion_prior`` (True: the smoother adds nothing) and the
frame's evidence (:class:`tagtrail.geometry.joint.FrameEvidence`): ``reproj_px`` (its RMS
corner error), ``alone_reproj_px`` (that of the frame on its own corners, the per-frame
solution), ``shift_m`` / ``shift_deg`` / ``shift_sigma`` (how far the motion prior moved it from
there, in metres, degrees and the per-frame solution's standard deviations) and that per-frame
pose itself (``alone_*`` pose columns: ``trajectory_raw.csv``, the trajectory before any temporal
step).

The frame-by-frame methods: every mapped tag ``i`` seen in a frame gives ``world_T_cam^(i) =
world_T_tag_i (cam_T_tag_i)^-1`` (of its two IPPE solutions, the one the map agrees with in
its frame, ``geometry.ippe.map_branches``; in a frame of one tag, the one with the lower
reprojection error), fused by

- ``avg``: translation mean + chordal rotation mean of the per-tag estimates (paper, "averaging");
- ``lsq``: per-frame robust least squares over the per-tag estimates (IRLS, ``loss``/``f_scale``
  on the 6-vector ``[dt ; rot_weight_m * dR]``) -- the original tool's default;
- ``pnp``: frames with >= 2 mapped tags: one RANSAC PnP over all their corners (undistorted),
  immune to single-tag IPPE flips; other frames and PnP failures fall back to ``lsq``;
- ``auto``: ``joint`` when the dataset has detections and a camera, else ``lsq``.

Frames without a mapped tag get no pose. Output rows are sorted by ``t_ns``.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator

from tagtrail.errors import DataError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import frame_poses
from tagtrail.geometry.ippe import map_branches
from tagtrail.geometry.joint import JointSettings, OdometryData, odometry_input
from tagtrail.geometry.joint.settings import JOINT_OLD_KEYS
from tagtrail.geometry.joint.track import posed_rms_px, solve_track
from tagtrail.geometry.robust import LossName
from tagtrail.geometry.se3 import T_from_xyz_quat, xyz_quat_from_T
from tagtrail.schemas.artifacts import (
    ALONE_POSE_COLS,
    ALT_POSE_COLS,
    CORNER_COLS,
    EVIDENCE_COLS,
    POSE_COLS,
    both_solutions,
    columns,
    corner_arrays,
    corner_rows,
    per_frame,
    timed,
)
from tagtrail.schemas.documents import MountDoc, OptimizeReport
from tagtrail.stages.base import Export, ExportFiles, StageParams, refuse_old_keys

log = logging.getLogger(__name__)

TRAJ_COLS = columns("trajectory.trajectory")


OLD_KEYS = {
    k: v.format(joint="optimize.joint") + "; trajectory takes the map's settings "
    "(its map_report input)"
    for k, v in JOINT_OLD_KEYS.items()
}


class Params(StageParams):
    method: Literal["auto", "joint", "avg", "lsq", "pnp"] = "auto"
    """How each frame's camera pose is found: ``joint`` (all frames on their tags' corners, held
    together by the map's priors), ``avg``, ``lsq`` or ``pnp`` (frame by frame); ``auto``:
    ``joint`` with detections and a camera, else ``lsq``."""
    loss: LossName = "soft_l1"
    """Robust loss of the ``lsq`` fusion (per tag, on the 6-vector residual)."""
    f_scale: float = Field(0.1, ge=1e-6, le=100.0)
    """Residual norm (m) where the ``lsq`` loss turns sub-quadratic."""
    rot_weight_m: float = Field(1.0, ge=1e-6, le=1000.0)
    """``lsq``: metres of residual per radian of rotation residual."""
    ransac_px: float = Field(3.0, gt=0.0, le=1000.0)
    """``pnp``: RANSAC inlier threshold (pixels)."""
    priors: Literal["map", "none"] = "map"
    """``joint``: ``map`` (default): the priors the map was made with (its joint settings and,
    on data too short or still to decide on, its decisions); ``none``: each frame on its own
    corners against the map."""

    @model_validator(mode="before")
    @classmethod
    def _old_names(cls, data: Any) -> Any:
        """A joint-solve key: one line saying the settings are the map's now."""
        return refuse_old_keys("trajectory", data, OLD_KEYS)


INPUTS = {
    "observations": "pnp.observations",
    "detections": "extract.detections",
    "camera": "extract.camera",
    "tag_map": "optimize.tag_map",
    "map_report": "optimize.report",
    "frames": "extract.frames",
    "odometry": "extract.odometry",
    "mount": "extract.mount",
}
OUTPUTS = ("trajectory",)
SCOPE = "all"


def _empty() -> pd.DataFrame:
    out = pd.DataFrame({"t_ns": np.zeros(0, np.int64)})
    for c in POSE_COLS:
        out[c] = np.zeros(0)
    out["n_tags"] = np.zeros(0, np.int32)
    return _extra(out)


def _extra(
    out: pd.DataFrame,
    std: np.ndarray | None = None,
    prior: bool = False,
    evidence: dict[str, np.ndarray] | None = None,
    alone: np.ndarray | None = None,
) -> pd.DataFrame:
    """The columns after the pose: std, ``motion_prior``, the evidence (NaN: unknown, without
    corners) and the frame's own pose ``alone (N, 7)`` (default: the pose itself)."""
    std = np.full((len(out), 2), np.nan) if std is None else std
    out["std_pos_m"] = std[:, 0]
    out["std_rot_deg"] = np.rad2deg(std[:, 1])
    out["motion_prior"] = np.full(len(out), prior)
    for c in EVIDENCE_COLS:
        out[c] = np.full(len(out), np.nan) if evidence is None else evidence[c]
    out[ALONE_POSE_COLS] = out[POSE_COLS].to_numpy(np.float64) if alone is None else alone
    return out


def joint_trajectory(
    rows: pd.DataFrame,
    ids: np.ndarray,
    W_map: np.ndarray,
    camera: CameraModel,
    settings: JointSettings,
    is_timed: bool,
    fallback: tuple[bool, bool] | None,
    priors: bool = True,
    odometry: OdometryData | None = None,
) -> pd.DataFrame:
    """The ``joint`` method (geometry.joint.track.solve_track) on ``corner_rows`` of the mapped
    tags ``ids`` (map ``W_map``) under the map's ``settings``; ``fallback``: the map's
    ground-plane and drive decisions, for data too short or too still to decide on; ``priors``
    False: each frame on its own corners; ``odometry``: the wheel-odometry prior's data (the
    frames with no tag it covers posed too, ``n_tags`` 0)."""
    tr = solve_track(
        corner_arrays(rows), ids, W_map, camera, settings, is_timed, fallback, priors, odometry
    )
    res, ground = tr.solved.res, tr.solved.ground
    for line in [] if ground is None else ground.lines():
        log.info("trajectory: %s", line)
    if tr.solved.odometry is not None:
        for note in tr.solved.odometry.notes:  # optimize warned of it: one warning a dataset
            log.info("trajectory: %s", note)
        log.info("trajectory: %s", tr.solved.odometry.line())
    if not res.converged:
        log.warning(
            "trajectory: the joint solve stopped after %d iterations before converging", res.iters
        )
    out = pd.DataFrame({"t_ns": tr.t_ns})
    out[POSE_COLS] = tr.pose
    out["n_tags"] = tr.n_tags.astype(np.int32)
    log.info(
        "trajectory: %d frames solved together (%d tied to their neighbours by smooth "
        "motion); tag corners fit to %.2f px RMS",
        len(tr.t_ns),
        res.prior_terms,
        float(np.sqrt(np.mean(res.res_px**2))),
    )
    return _extra(out, tr.std, tr.motion_prior, tr.evidence, tr.alone)


def _own_evidence(
    out: pd.DataFrame,
    frame_idx: np.ndarray,
    rows: pd.DataFrame,
    ids: np.ndarray,
    W_map: np.ndarray,
    camera: CameraModel | None,
) -> pd.DataFrame:
    """Frame-by-frame poses ``out`` (of frames ``frame_idx``, sorted) are their own evidence:
    their corner RMS (``reproj_px`` = ``alone_reproj_px``; NaN without corners), no shift."""
    rms = np.full(len(out), np.nan)
    rows = rows[rows["frame_idx"].isin(frame_idx)]
    if len(rows) and camera is not None:
        pose = out[POSE_COLS].to_numpy(np.float64)
        rms = posed_rms_px(corner_arrays(rows), ids, W_map, camera, frame_idx, pose)
    zero = np.zeros(len(out))
    return _extra(
        out,
        evidence=dict(
            reproj_px=rms, alone_reproj_px=rms, shift_m=zero, shift_deg=zero, shift_sigma=zero
        ),
    )


def _at_map_scale(obs: pd.DataFrame, size: np.ndarray, ids: np.ndarray) -> pd.DataFrame:
    """Observations at the map's tag sizes ``size`` (of the sorted ``ids``; NaN: unknown), where
    they differ from the sizes pnp solved with: a surveyed similarity rescales the map, and a
    query's tags are the reference map's. IPPE is scale-covariant, so a pose's translation scales
    with the size."""
    if "size_m" not in obs.columns or not len(obs):
        return obs
    own = obs["size_m"].to_numpy(np.float64)
    new = size[np.searchsorted(ids, obs["tag_id"].to_numpy(np.int64))]
    ratio = np.where(np.isfinite(new) & (new > 0) & np.isfinite(own) & (own > 0), new / own, 1.0)
    if np.allclose(ratio, 1.0, rtol=1e-9, atol=0.0):
        return obs
    obs = obs.copy()
    obs["size_m"] = own * ratio
    for cols in (POSE_COLS[:3], ALT_POSE_COLS[:3]):
        if all(c in obs.columns for c in cols):
            obs[cols] = obs[cols].to_numpy(np.float64) * ratio[:, None]
    return obs


def run(
    observations: pd.DataFrame,
    detections: pd.DataFrame,
    camera: CameraModel | None,
    tag_map: pd.DataFrame,
    params: Params,
    frames: pd.DataFrame | None = None,
    map_report: OptimizeReport | None = None,
    odometry: pd.DataFrame | None = None,
    mount: MountDoc | None = None,
) -> dict[str, Any]:
    """One ``world_T_cam`` per frame with a mapped tag (``TRAJ_COLS``), and with ``odometry``
    (``extract.odometry``, ``extract.mount``) the frames without one it covers (``n_tags`` 0).
    ``map_report``: the map's ``optimize.report`` (its joint settings and decisions; None: the
    defaults)."""
    settings = (
        JointSettings() if map_report is None or map_report.joint is None else map_report.joint
    )
    bundle = None if map_report is None else map_report.bundle
    decided = None if bundle is None else bundle.ground
    fallback = (
        None
        if decided is None
        else (decided.applied, decided.drive is not None and decided.drive.applied)
    )
    if decided is not None and decided.note:  # a map that could not decide either
        log.warning(
            "trajectory: the map report decided no ground plane on its own data (%s); "
            "is it the map's? A query localized against the reference map wires "
            "trajectory.map_report: reference:optimize.report beside trajectory.tag_map",
            decided.note,
        )
        fallback = None
    is_timed = timed(frames)
    if not is_timed and settings.motion != "none":
        log.info("trajectory: the stamps are the files' order, not capture times: no motion prior")
    if tag_map is None or len(tag_map) == 0:
        raise DataError("trajectory: the tag map is empty (did optimize map any tag?)")
    ids = tag_map["tag_id"].to_numpy(np.int64)
    order = np.argsort(ids)
    ids = ids[order]
    mv = tag_map[POSE_COLS].to_numpy(np.float64)[order]
    W_map = T_from_xyz_quat(mv[:, :3], mv[:, 3:])
    obs = observations[observations["tag_id"].isin(ids)]
    obs = obs[~obs.duplicated(["frame_idx", "tag_id"], keep=False)]
    if "size_m" in tag_map.columns:
        obs = _at_map_scale(obs, tag_map["size_m"].to_numpy(np.float64)[order], ids)
    if obs.empty:
        log.warning("trajectory: no frame sees a mapped tag; the trajectory is empty")
        return {"trajectory": _empty()}
    obs = obs.sort_values(["frame_idx", "tag_id"], kind="stable")
    blind = None
    if frames is not None and len(frames):
        blind = frames.loc[~frames["frame_idx"].isin(obs["frame_idx"]), "t_ns"].to_numpy(np.int64)
    odo = odometry_input(odometry, mount, blind)
    has_pix = detections is not None and len(detections) > 0 and camera is not None
    parts = []
    rows = corner_rows(obs, detections, ids) if has_pix else pd.DataFrame(columns=["frame_idx"])
    if has_pix and params.method in ("auto", "joint"):
        assert camera is not None
        if len(rows):
            parts.append(
                joint_trajectory(
                    rows,
                    ids,
                    W_map,
                    camera,
                    settings,
                    is_timed,
                    fallback,
                    params.priors == "map",
                    odo,
                )
            )
            # frames without usable corners fall back to the frame-by-frame fusion
            obs = obs[~obs["frame_idx"].isin(rows["frame_idx"].unique())]
            if obs.empty:
                return {"trajectory": parts[0]}
            log.info(
                "trajectory: %d frames without usable corners fused frame by frame",
                obs["frame_idx"].nunique(),
            )
    elif params.method == "joint":
        log.warning("trajectory: method joint needs detections and a camera; using lsq")
    frame = obs["frame_idx"].to_numpy(np.int64)
    uframe, group = np.unique(frame, return_inverse=True)
    t_ns = obs.groupby("frame_idx")["t_ns"].first().reindex(uframe).to_numpy(np.int64)
    k = np.searchsorted(ids, obs["tag_id"].to_numpy(np.int64))
    px = None
    if has_pix and params.method == "pnp":
        det = detections.drop_duplicates(["frame_idx", "tag_id"], keep=False)
        det = det.set_index(["frame_idx", "tag_id"])[CORNER_COLS]
        key = pd.MultiIndex.from_arrays([obs["frame_idx"].to_numpy(), obs["tag_id"].to_numpy()])
        px = det.reindex(key).to_numpy(np.float64).reshape(-1, 4, 2)
    elif params.method == "pnp":
        log.warning("trajectory: method pnp needs detections and a camera; using lsq")
    size = np.full(len(obs), np.nan)
    if "size_m" in tag_map.columns:
        size = tag_map["size_m"].to_numpy(np.float64)[order][k]
    if "size_m" in obs.columns:
        size = np.where(np.isfinite(size), size, obs["size_m"].to_numpy(np.float64))
    # each observation's IPPE solution the map agrees with in its frame (one-tag frames: the
    # lower-reprojection one)
    both = both_solutions(obs)
    pick = map_branches(frame, W_map[k][:, :3, :3], both[:, :, :3, :3])
    res = frame_poses(
        W_map[k],
        both[np.arange(len(obs)), pick],
        group,
        len(uframe),
        corners_px=px,
        size_m=size,
        camera=camera,
        method="lsq" if params.method == "joint" else params.method,
        loss=params.loss,
        f_scale=params.f_scale,
        rot_weight_m=params.rot_weight_m,
        ransac_px=params.ransac_px,
    )
    if res.method == "pnp":
        log.info("trajectory: multi-tag PnP for %d of %d frames", res.by_pnp.sum(), len(uframe))
    T = res.world_T_cam
    xyz, q = xyz_quat_from_T(T)
    out = pd.DataFrame({"t_ns": t_ns})
    out[POSE_COLS] = np.concatenate([xyz, q], axis=1)
    out["n_tags"] = res.n_tags.astype(np.int32)
    out = pd.concat(
        [*parts, _own_evidence(out, uframe, rows, ids, W_map, camera)], ignore_index=True
    )
    return {"trajectory": out.sort_values("t_ns", kind="stable").reset_index(drop=True)}


def _raw_trajectory_file(trajectory: pd.DataFrame | None) -> ExportFiles | None:
    """``trajectory_raw.csv``: each frame on its own corners, before any temporal step (the
    motion prior or the smoother)."""
    return (
        None
        if trajectory is None
        else {"trajectory_raw.csv": ("trajectory_csv", per_frame(trajectory))}
    )


EXPORTS = (
    Export(
        "trajectory_raw",
        ("trajectory_raw.csv",),
        {"trajectory": "trajectory.trajectory"},
        _raw_trajectory_file,
    ),
)
