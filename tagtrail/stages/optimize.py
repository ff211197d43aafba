"""optimize: the tag map ``world_T_tag`` by robust non-linear least squares (Eq. 3.4-3.7).

The anchor tag is fixed at the identity (gauge); every other mapped tag has a rotation vector and
a translation. Residual per edge observation: ``[t_pred - t_obs ; rot_weight_m * Log(R_pred^T
R_obs)]`` scaled by ``sqrt(weight)``; the robust ``loss`` acts on its norm with scale ``f_scale``
(m). Initialised from a spanning tree of robust per-pair means; solved by scipy's ``trf`` with an
analytic sparse Jacobian. See :mod:`tagtrail.geometry.posegraph` for the maths.

``method="joint"`` (the default; datasets with detections and a camera) then solves tag poses and
the camera pose of every frame showing >= 2 mapped tags jointly on the corner reprojection error
(px; robust ``joint_loss`` per tag with scale ``joint_f_scale_px``), starting from the pose-graph
map and per-frame fused camera poses. The pairwise edges of Eq. 3.2 carry the bias of single-tag
PnP (a small tag's out-of-plane rotation error levered over the distance to the other tag) and
the pose graph inherits it; the joint solve does not (figures: bench/ and the closing notes).
The edge residuals and per-tag RMS are those of the final map. ``"pairwise"``: the paper's pose
graph alone, also what observation-only datasets get.

The joint solve needs redundancy: its gain is averaging many frames, each camera pose shared by
its tags; from a handful of frames the shared pose couples the tags' model errors instead (a
miscalibrated lens: a near tag fitting poorly drags the far ones; seen on the real FRC field
photos, 3 frames per group of tags). So it runs only with ``joint_min_frames`` (30) frames or
more showing two mapped tags; otherwise the pose-graph map is kept and the log says so.
Old parameter names (``refine: corners|none``, ``ba_*``) still work with a deprecation line.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tagtrail.errors import DataError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import camera_estimates, fuse_robust, tag_corners
from tagtrail.geometry.ippe import best_pose
from tagtrail.geometry.posegraph import (
    CornerObservations,
    PoseGraph,
    bundle_adjust,
    relative_residuals,
    solve,
)
from tagtrail.geometry.robust import LossName
from tagtrail.geometry.se3 import R_from_quat_xyzw, inv, make_T, quat_xyzw_from_R
from tagtrail.schemas.artifacts import CORNER_COLS, POSE_COLS, columns, ippe_solutions
from tagtrail.schemas.documents import OptimizeReport, TagGraph
from tagtrail.stages.base import StageParams

log = logging.getLogger(__name__)

TAG_MAP_COLS = columns("optimize.tag_map")
RESIDUAL_COLS = columns("optimize.edge_residuals")


_RENAMED = {"ba_loss": "joint_loss", "ba_f_scale_px": "joint_f_scale_px",
            "ba_max_iter": "joint_max_iter", "ba_min_frames": "joint_min_frames"}
_REFINE = {"corners": "joint", "none": "pairwise"}


class Params(StageParams):
    method: Literal["joint", "pairwise"] = "joint"
    """``joint`` (default): the pairwise pose graph, then all tag and camera poses jointly on the
    corner reprojection error (needs detections and a camera and ``joint_min_frames``; else the
    pose graph is kept). ``pairwise``: the paper's pose graph alone (Eq. 3.4-3.7)."""
    loss: LossName = "soft_l1"
    """Robust loss on each edge's residual norm (Eq. 3.7): linear, soft_l1, huber, cauchy."""
    f_scale: float = Field(0.1, gt=0.0)
    """Residual norm (m) where the robust loss turns from quadratic to sub-quadratic."""
    rot_weight_m: float = Field(1.0, gt=0.0)
    """Metres of residual per radian of rotation residual (1.0: the paper's plain stacking)."""
    max_nfev: int = Field(100, ge=1)
    joint_loss: LossName = "huber"
    """Robust loss of the joint solve, on each tag's 8-vector of corner errors (px)."""
    joint_f_scale_px: float = Field(1.0, gt=0.0)
    """Corner error norm (px) where the joint solve's loss turns sub-quadratic."""
    joint_max_iter: int = Field(50, ge=1)
    joint_min_frames: int = Field(30, ge=1)
    """Frames showing >= 2 mapped tags needed for the joint solve; with fewer, the pose graph
    is kept (module docstring)."""

    @model_validator(mode="before")
    @classmethod
    def _old_names(cls, data: Any) -> Any:
        """``refine: corners|none`` and ``ba_*`` still work, with one deprecation line each."""
        if not isinstance(data, dict):
            return data
        out = dict(data)
        if "refine" in out:
            old = out.pop("refine")
            if "method" in out:
                raise ValueError("give optimize.method only (optimize.refine is its old name)")
            new = _REFINE.get(old, old)
            log.warning("optimize.refine is deprecated: use optimize.method: %s", new)
            out["method"] = new
        for old, new in _RENAMED.items():
            if old in out:
                if new in out:
                    raise ValueError(f"give optimize.{new} only (optimize.{old} is its old name)")
                log.warning("optimize.%s is deprecated: use optimize.%s", old, new)
                out[new] = out.pop(old)
        return out


INPUTS = {
    "edges": "edges.edges",
    "graph": "edges.graph",
    "observations": "pnp.observations",
    "detections": "extract.detections",
    "camera": "extract.camera",
}
OUTPUTS = ("tag_map", "edge_residuals", "report")
SCOPE = "all"


def _per_tag_rms(idx_i: np.ndarray, idx_j: np.ndarray, sq: np.ndarray, n: int) -> np.ndarray:
    """RMS of per-edge values ``sqrt(sq)`` over the edges touching each tag (NaN if none)."""
    s = np.bincount(idx_i, sq, n) + np.bincount(idx_j, sq, n)
    c = np.bincount(idx_i, minlength=n) + np.bincount(idx_j, minlength=n)
    return np.where(c > 0, np.sqrt(s / np.maximum(c, 1)), np.nan)


def refine_on_corners(
    R: np.ndarray, t: np.ndarray, tags: np.ndarray, anchor: int, observations: pd.DataFrame,
    detections: pd.DataFrame, camera: CameraModel, params: Params,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]] | None:
    """Bundle-adjusted ``world_T_tag`` (``R (T, 3, 3)``, ``t (T, 3)``, for the sorted ids
    ``tags``) and a report block, or None when no frame shows two mapped tags with corners."""
    obs = observations[observations["tag_id"].isin(tags)]
    obs = obs[~obs.duplicated(["frame_idx", "tag_id"], keep=False)]
    det = detections.drop_duplicates(["frame_idx", "tag_id"], keep=False)
    m = obs.merge(det[["frame_idx", "tag_id", *CORNER_COLS]], on=["frame_idx", "tag_id"])
    m = m[np.isfinite(m[CORNER_COLS].to_numpy(np.float64)).all(axis=1)]
    m = m[np.isfinite(m["size_m"].to_numpy(np.float64)) & (m["size_m"] > 0)]
    m = m[m.groupby("frame_idx")["tag_id"].transform("size") >= 2]
    if m.empty:
        return None
    m = m.sort_values(["frame_idx", "tag_id"], kind="stable")
    n_frames = m["frame_idx"].nunique()
    if n_frames < params.joint_min_frames:
        log.info("optimize: %d frames show two mapped tags (< joint_min_frames %d): no bundle "
                 "adjustment, the pose-graph map is kept", n_frames, params.joint_min_frames)
        return None
    cam = camera
    px = m[CORNER_COLS].to_numpy(np.float64).reshape(-1, 4, 2)
    k = np.searchsorted(tags, m["tag_id"].to_numpy(np.int64))
    frames, f = np.unique(m["frame_idx"].to_numpy(np.int64), return_inverse=True)
    world_T_tag = make_T(R, t)
    # Start: each frame's camera pose fused from its tags' IPPE poses in the pose-graph map.
    cam_T_tag = best_pose(*ippe_solutions(m))
    world_T_cam = fuse_robust(camera_estimates(world_T_tag[k], cam_T_tag), f, len(frames))
    cam_T_world = inv(world_T_cam)
    ob = CornerObservations(frame=f, tag=k, pts_tag=tag_corners(m["size_m"].to_numpy(np.float64)),
                            uv=cam.undistort(px))
    res = bundle_adjust(
        R, t, cam_T_world[:, :3, :3], cam_T_world[:, :3, 3], ob, anchor,
        px_per_unit=0.5 * float(cam.K[0, 0] + cam.K[1, 1]), loss=params.joint_loss,
        f_scale_px=params.joint_f_scale_px, max_iter=params.joint_max_iter,
    )
    if not res.converged:
        log.warning("optimize: bundle adjustment stopped after %d iterations (joint_max_iter) "
                    "before converging", res.iters)
    block = {
        "frames": int(len(frames)),
        "observations": int(len(m)),
        "iterations": res.iters,
        "converged": res.converged,
        "cost_px2": res.cost,
        "rms_px": float(np.sqrt(np.mean(res.res_px**2))),
        "p95_px": float(np.percentile(res.res_px, 95)),
    }
    return res.R_tag, res.t_tag, block


def run(
    edges: pd.DataFrame,
    graph: TagGraph,
    observations: pd.DataFrame,
    params: Params,
    detections: pd.DataFrame | None = None,
    camera: CameraModel | None = None,
) -> dict[str, Any]:
    """Tag map (``TAG_MAP_COLS``), per-edge residuals (``RESIDUAL_COLS``) and a report dict."""
    tags = np.asarray(sorted(int(t) for t in graph.get("tags", [])), dtype=np.int64)
    anchor = graph.anchor_id
    if anchor not in tags:
        raise DataError(f"optimize: anchor tag {anchor} is not among the mapped tags {tags}")
    ti, tj = edges["tag_i"].to_numpy(np.int64), edges["tag_j"].to_numpy(np.int64)
    if not (np.isin(ti, tags).all() and np.isin(tj, tags).all()):
        raise DataError("optimize: edges name tags missing from the graph's tag list")
    ii, jj = np.searchsorted(tags, ti), np.searchsorted(tags, tj)
    adj = coo_matrix((np.ones(len(ii)), (ii, jj)), shape=(len(tags), len(tags)))
    _, label = connected_components(adj, directed=False)
    lost = tags[label != label[np.searchsorted(tags, anchor)]]
    if len(lost):
        raise DataError(
            f"optimize: tags {lost.tolist()} share no edge path with anchor tag {anchor}"
            " (the edges and graph artifacts disagree; re-run the edges stage)"
        )
    vals = edges[POSE_COLS].to_numpy(np.float64)
    g = PoseGraph(
        n_tags=len(tags),
        anchor=int(np.searchsorted(tags, anchor)),
        idx_i=ii,
        idx_j=jj,
        R_obs=R_from_quat_xyzw(vals[:, 3:]),
        t_obs=vals[:, :3],
        weight=edges["weight"].to_numpy(np.float64),
        rot_weight_m=params.rot_weight_m,
    )
    res = solve(g, loss=params.loss, f_scale=params.f_scale, max_nfev=params.max_nfev)
    R_map, t_map, res_t, res_r = res.R, res.t, res.res_t, res.res_r
    bundle = None
    if (params.method == "joint" and detections is not None and len(detections) > 0
            and camera is not None):
        out = refine_on_corners(R_map, t_map, tags, g.anchor, observations, detections, camera,
                                params)
        if out is not None:
            R_map, t_map, bundle = out
            res_t, res_r = relative_residuals(R_map, t_map, g)

    e_t = np.linalg.norm(res_t, axis=1)
    e_r = np.linalg.norm(res_r, axis=1)
    obs_tag = observations["tag_id"].to_numpy(np.int64)
    n_obs = pd.Series(obs_tag).value_counts().reindex(tags, fill_value=0).to_numpy(np.int64)
    if "size_m" in observations.columns:
        size = observations.groupby("tag_id")["size_m"].median().reindex(tags).to_numpy(float)
    else:
        size = np.full(len(tags), np.nan)
    tag_map = pd.DataFrame({"tag_id": tags.astype(np.int32)})
    tag_map[POSE_COLS] = np.concatenate([t_map, quat_xyzw_from_R(R_map)], axis=1)
    tag_map["n_obs"] = n_obs
    tag_map["size_m"] = size
    tag_map["res_t_rms_m"] = _per_tag_rms(ii, jj, e_t**2, len(tags))
    tag_map["res_r_rms_deg"] = np.rad2deg(_per_tag_rms(ii, jj, e_r**2, len(tags)))

    residuals = pd.DataFrame(
        {
            "tag_i": ti.astype(np.int32),
            "tag_j": tj.astype(np.int32),
            "t_ns": edges["t_ns"].to_numpy(np.int64),
            "res_t_m": e_t,
            "res_r_deg": np.rad2deg(e_r),
        }
    )
    report = {
        "anchor_id": anchor,
        "loss": params.loss,
        "f_scale": params.f_scale,
        "cost": res.cost,
        "nfev": res.nfev,
        "status": res.status,
        "rms_t_m": float(np.sqrt(np.mean(e_t**2))) if len(e_t) else 0.0,
        "rms_r_deg": float(np.rad2deg(np.sqrt(np.mean(e_r**2)))) if len(e_r) else 0.0,
        "method": "joint" if bundle is not None else "pairwise",
        "bundle": bundle,
    }
    return {"tag_map": tag_map, "edge_residuals": residuals,
            "report": OptimizeReport.model_validate(report)}
