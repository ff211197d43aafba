"""eval: errors of the trajectory and the tag map against a dataset's ground truth.

Ground truth is a SPEC folder (``trajectory.csv`` of ``world_T_cam`` with world = the GT anchor
tag's frame, ``tag_map.yaml``/``.csv`` with every tag). The estimate's world is its anchor's frame
(the tag at the identity pose); when it differs from the GT anchor, GT is re-expressed in it first:
``a_T_x = (gt_T_a)^-1 gt_T_x``; a map with no tag at the identity (``optimize.survey``: a surveyed
world) is taken to be in ground truth's world. Trajectory poses are matched by exact stamp; tags by
id (the anchor itself, exact by construction, is left out of the tag statistics). Errors: position
``|p - p_gt|`` (m) and rotation angle of ``R_gt^T R`` (deg); statistics mean, median, rmse, p95,
max, min.

``gauge_free``: the same errors after one rigid motion (no scale) that best fits the estimated tag
positions, anchor included, to ground truth (Umeyama 1991), applied to the map and the trajectory
alike. The anchored errors include the anchor tag's own pose error -- world IS that tag's frame --
levered over the map: the yaw of a 16 cm tag seen near frontally is the least observable quantity
of the whole problem (its corners pin it to ~7 deg per frame at 1.5 m with 0.3 px noise), so a few
tenths of a degree there move tags 4 m away by cm while the map is right to ~1 mm within itself.
This block separates the two (the way SLAM benchmarks report an aligned trajectory error); it is
None with fewer than 3 common tags.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pandas as pd

from tagtrail.errors import DataError
from tagtrail.geometry.registration import umeyama
from tagtrail.geometry.se3 import T_from_xyz_quat, inv, make_T, pose_error
from tagtrail.schemas.artifacts import POSE_COLS, per_frame
from tagtrail.schemas.documents import Evaluation
from tagtrail.schemas.inputs import GroundTruth
from tagtrail.stages.base import Export, ExportFiles, Metric, StageParams

log = logging.getLogger(__name__)


class Params(StageParams):
    pass


INPUTS = {
    "trajectory": "smooth.trajectory",
    "raw_trajectory": "trajectory.trajectory",
    "tag_map": "optimize.tag_map",
    "ground_truth": "ground_truth",
}
OUTPUTS = ("evaluation",)
SCOPE = "all"

ERROR_BLOCKS = ("trajectory", "trajectory_raw", "tags", "gauge_free.trajectory", "gauge_free.tags")
ERROR_STATS = ("mean", "median", "rmse", "p95", "max", "min")
_DEFAULTS = {"trajectory.rmse_m": 1, "tags.rmse_m": 2}  # the sweep's first columns
METRICS = tuple(
    Metric(name, "evaluation", (*block.split("."), key, stat), unit, default=_DEFAULTS.get(name, 0))
    for block in ERROR_BLOCKS
    for stat in ERROR_STATS
    for unit, key in (("m", "position_m"), ("deg", "angle_deg"))
    for name in [f"{block}.{stat}_{unit}"]
)
METRICS_HELP = (
    f"BLOCK.STAT_m and BLOCK.STAT_deg (errors vs ground truth; BLOCK: "
    f"{', '.join(ERROR_BLOCKS)}; STAT: {', '.join(ERROR_STATS)})"
)


def _evaluation_file(evaluation: Evaluation | None) -> ExportFiles | None:
    """``evaluation.json``: errors vs ground truth (datasets that have it)."""
    return (
        None
        if evaluation is None
        else {"evaluation.json": ("json", evaluation.model_dump(mode="json"))}
    )


EXPORTS = (
    Export("evaluation", ("evaluation.json",), {"evaluation": "eval.evaluation"}, _evaluation_file),
)


def error_stats(x: np.ndarray) -> dict[str, float | None]:
    """mean, median, rmse, p95, max, min of errors ``x`` (None when there are none)."""
    x = np.asarray(x, dtype=np.float64)
    keys = ("mean", "median", "rmse", "p95", "max", "min")
    if x.size == 0:
        return dict.fromkeys(keys)
    vals = (x.mean(), np.median(x), np.sqrt(np.mean(x * x)), np.percentile(x, 95), x.max(), x.min())
    return {k: float(v) for k, v in zip(keys, vals, strict=True)}


def _poses(df: pd.DataFrame, cols: list[str] = POSE_COLS) -> np.ndarray:
    v = df[cols].to_numpy(np.float64)
    return T_from_xyz_quat(v[:, :3], v[:, 3:])


def _block(T: np.ndarray, T_gt: np.ndarray, n_ref: int) -> dict[str, Any]:
    dt, dr = pose_error(T, T_gt)
    return {
        "n": int(len(dt)),
        "coverage": float(len(dt) / n_ref) if n_ref else 0.0,
        "position_m": error_stats(dt),
        "angle_deg": error_stats(np.rad2deg(dr)),
    }


def trajectory_errors(
    est: pd.DataFrame, gt: pd.DataFrame, gt_T_world: np.ndarray, fix: np.ndarray | None = None
) -> dict[str, Any]:
    """Errors of ``est`` against ``gt`` (``gt_world_T_cam``) at equal ``t_ns``; ``gt_T_world``
    ``(4, 4)``: the estimate's world frame expressed in GT's world; ``fix`` ``(4, 4)``: a motion
    applied to the estimate first (``gauge_free``)."""
    m = est[["t_ns", *POSE_COLS]].merge(gt[["t_ns", *POSE_COLS]], on="t_ns", suffixes=("", "_gt"))
    T_gt = inv(gt_T_world) @ _poses(m, [f"{c}_gt" for c in POSE_COLS])
    T = _poses(m) if fix is None else fix @ _poses(m)
    return _block(T, T_gt, len(gt))


def gauge_fit(T_tag: np.ndarray, T_tag_gt: np.ndarray) -> np.ndarray | None:
    """Rigid ``(4, 4)`` best mapping the estimated tag positions onto ground truth (None: < 3
    tags or all on a line)."""
    src, dst = T_tag[:, :3, 3], T_tag_gt[:, :3, 3]
    if len(src) < 3 or np.linalg.svd(src - src.mean(0), compute_uv=False)[1] < 1e-6:
        return None
    _, R, t = umeyama(src, dst, with_scale=False)
    return make_T(R, t)


def estimated_anchor(tag_map: pd.DataFrame) -> int | None:
    """The tag at the identity pose (the optimiser's fixed gauge), if any."""
    v = tag_map[POSE_COLS].to_numpy(np.float64)
    ident = np.abs(v - [0, 0, 0, 0, 0, 0, 1]).max(axis=1, initial=0.0) < 1e-9
    return int(tag_map["tag_id"].to_numpy()[ident][0]) if ident.any() else None


def run(
    trajectory: pd.DataFrame,
    raw_trajectory: pd.DataFrame,
    tag_map: pd.DataFrame,
    ground_truth: GroundTruth,
    params: Params,
) -> dict[str, Any]:
    """Evaluation JSON: anchors, ``trajectory``, ``trajectory_raw``, ``tags`` error blocks."""
    gt_dir = ground_truth.path
    gt_traj = ground_truth.trajectory
    gt_tags, gt_anchor = ground_truth.tag_map, ground_truth.anchor_id
    gt_tags = gt_tags.drop_duplicates("tag_id").set_index("tag_id")
    anchor = estimated_anchor(tag_map)
    if anchor is None:
        anchor = gt_anchor
        log.warning(
            "eval: no tag of the map is at the identity (a surveyed world?): the "
            "anchored errors take it to be ground truth's world"
        )
    if anchor is not None and anchor != gt_anchor:
        if anchor not in gt_tags.index:
            raise DataError(
                f"eval: the map's anchor tag {anchor} is not in the ground-truth tag map"
                f" {gt_dir} (its tags: {sorted(gt_tags.index)[:20]})"
            )
        gt_T_world = _poses(gt_tags.loc[[anchor]])[0]
    else:
        gt_T_world = np.eye(4)

    both = np.intersect1d(tag_map["tag_id"].to_numpy(np.int64), gt_tags.index.to_numpy())
    common = both[both != anchor]
    est_tags = tag_map.set_index("tag_id").loc[common]
    T_tag = _poses(est_tags)
    T_tag_gt = inv(gt_T_world) @ _poses(gt_tags.loc[common])
    n_tags = len(gt_tags) - (anchor in gt_tags.index)
    fix = gauge_fit(
        _poses(tag_map.set_index("tag_id").loc[both]), inv(gt_T_world) @ _poses(gt_tags.loc[both])
    )
    gauge_free = None
    if fix is not None:
        gauge_free = {
            "rotation_deg": float(
                np.degrees(np.arccos(np.clip((np.trace(fix[:3, :3]) - 1) / 2, -1.0, 1.0)))
            ),
            "translation_m": float(np.linalg.norm(fix[:3, 3])),
            "trajectory": trajectory_errors(trajectory, gt_traj, gt_T_world, fix),
            "tags": _block(fix @ T_tag, T_tag_gt, n_tags),
        }
    evaluation: dict[str, Any] = {
        "anchor_id": anchor,
        "gt_anchor_id": gt_anchor,
        "trajectory": trajectory_errors(trajectory, gt_traj, gt_T_world),
        "trajectory_raw": trajectory_errors(per_frame(raw_trajectory), gt_traj, gt_T_world),
        "tags": _block(T_tag, T_tag_gt, n_tags),
        "gauge_free": gauge_free,
    }
    if evaluation["trajectory"]["n"] == 0:
        log.warning("eval: no trajectory stamp matches the ground truth in %s", gt_dir)
    return {"evaluation": Evaluation.model_validate(evaluation)}
