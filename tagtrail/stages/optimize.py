"""optimize: the tag map ``world_T_tag`` by robust non-linear least squares (Eq. 3.4-3.7).

The anchor tag is fixed at the identity (gauge); every other mapped tag has a rotation vector and
a translation. Residual per edge observation: ``[t_pred - t_obs ; rot_weight_m * Log(R_pred^T
R_obs)]`` scaled by ``sqrt(weight)``; the robust ``loss`` acts on its norm with scale ``f_scale``
(m). Initialised from a spanning tree of robust per-pair means; solved by scipy's ``trf`` with an
analytic sparse Jacobian. See :mod:`tagtrail.geometry.posegraph` for the maths.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from pydantic import Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tagtrail.errors import DataError
from tagtrail.geometry.posegraph import LossName, PoseGraph, solve
from tagtrail.geometry.se3 import R_from_quat_xyzw, quat_xyzw_from_R
from tagtrail.io.layouts import POSE_COLS
from tagtrail.stages.base import StageParams

TAG_MAP_COLS = ["tag_id", *POSE_COLS, "n_obs", "size_m", "res_t_rms_m", "res_r_rms_deg"]
RESIDUAL_COLS = ["tag_i", "tag_j", "t_ns", "res_t_m", "res_r_deg"]


class Params(StageParams):
    loss: LossName = "soft_l1"
    """Robust loss on each edge's residual norm (Eq. 3.7): linear, soft_l1, huber, cauchy."""
    f_scale: float = Field(0.1, gt=0.0)
    """Residual norm (m) where the robust loss turns from quadratic to sub-quadratic."""
    rot_weight_m: float = Field(1.0, gt=0.0)
    """Metres of residual per radian of rotation residual (1.0: the paper's plain stacking)."""
    max_nfev: int = Field(100, ge=1)


INPUTS = {"edges": "edges.edges", "graph": "edges.graph", "observations": "pnp.observations"}
OUTPUTS = ("tag_map", "edge_residuals", "report")
SCOPE = "all"
DEPENDS = ("tagtrail.geometry.posegraph", "tagtrail.geometry.rotations", "tagtrail.geometry.se3")


def _per_tag_rms(idx_i: np.ndarray, idx_j: np.ndarray, sq: np.ndarray, n: int) -> np.ndarray:
    """RMS of per-edge values ``sqrt(sq)`` over the edges touching each tag (NaN if none)."""
    s = np.bincount(idx_i, sq, n) + np.bincount(idx_j, sq, n)
    c = np.bincount(idx_i, minlength=n) + np.bincount(idx_j, minlength=n)
    return np.where(c > 0, np.sqrt(s / np.maximum(c, 1)), np.nan)


def run(
    edges: pd.DataFrame, graph: dict[str, Any], observations: pd.DataFrame, params: Params
) -> dict[str, Any]:
    """Tag map (``TAG_MAP_COLS``), per-edge residuals (``RESIDUAL_COLS``) and a report dict."""
    tags = np.asarray(sorted(int(t) for t in graph.get("tags", [])), dtype=np.int64)
    anchor = int(graph["anchor_id"])
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

    e_t = np.linalg.norm(res.res_t, axis=1)
    e_r = np.linalg.norm(res.res_r, axis=1)
    obs_tag = observations["tag_id"].to_numpy(np.int64)
    n_obs = pd.Series(obs_tag).value_counts().reindex(tags, fill_value=0).to_numpy(np.int64)
    if "size_m" in observations.columns:
        size = observations.groupby("tag_id")["size_m"].median().reindex(tags).to_numpy(float)
    else:
        size = np.full(len(tags), np.nan)
    tag_map = pd.DataFrame({"tag_id": tags.astype(np.int32)})
    tag_map[POSE_COLS] = np.concatenate([res.t, quat_xyzw_from_R(res.R)], axis=1)
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
    }
    return {"tag_map": tag_map, "edge_residuals": residuals, "report": report}
