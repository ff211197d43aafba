"""optimize: the tag map ``world_T_tag`` by robust non-linear least squares (Eq. 3.4-3.7).

The anchor tag is fixed at the identity (gauge); every other mapped tag has a rotation vector and
a translation. Residual per edge observation: ``[t_pred - t_obs ; rot_weight_m * Log(R_pred^T
R_obs)]`` scaled by ``sqrt(weight)``; the robust ``loss`` acts on its norm with scale ``f_scale``
(m). Initialised from a spanning tree of robust per-pair means; solved by Levenberg-Marquardt on
the pair-accumulated normal equations (sparse LU). See :mod:`tagtrail.geometry.posegraph` for the
maths. That map then checks each observation's IPPE solution in its frame
(``branch_check``, :func:`tagtrail.geometry.ippe.map_branches`): edges built from a solution the
map disagrees with are rebuilt from the other, and the graph solved again.

``method="joint"`` (the default; datasets with detections and a camera) then solves the tag
poses and the camera pose of every frame that sees a mapped tag jointly on the corner
reprojection error, the frames held together in time by a constant-velocity motion prior, and on
a ground robot by the ground-plane and wheeled-drive priors (:mod:`tagtrail.geometry.joint`:
units, weights, priors and the solver; its settings ``joint``, which ``trajectory`` takes too).
It starts from the pose-graph map, each frame at the IPPE solution its neighbours agree with;
tags the pose graph left out (seen with the map only ambiguously, or never together with it) are
placed through the trajectory first (``link_tags``). The pairwise edges of Eq. 3.2 carry the
bias of single-tag PnP (a small tag's out-of-plane rotation error levered over the distance to
the other tag) and the pose graph inherits it; the joint solve does not. Each tag gets its
standard deviation (``std_pos_m``, ``std_rot_deg``; the anchor 0). The edge residuals and
per-tag RMS are those of the final map. ``"pairwise"``: the paper's pose graph alone, also what
observation-only datasets get.

The joint solve needs redundancy: its gain is averaging many frames; from a handful of photos the
shared camera pose couples the tags' model errors instead (a miscalibrated lens: a near tag
fitting poorly drags the far ones; seen on the real FRC field photos, 3 frames per group of
tags). So it runs only when ``joint_min_frames`` (30) frames or more see a mapped tag; otherwise
the pose-graph map is kept and the log says so.
Old parameter names (``refine: corners|none``, ``ba_*``) still work with a deprecation line.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tagtrail.errors import DataError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.ippe import map_branches
from tagtrail.geometry.joint import (
    SHIFT_SIGMA_BOUND,
    CornerProblem,
    JointSettings,
    corner_problem,
    link_tags,
    solve_on_corners,
)
from tagtrail.geometry.joint.settings import JOINT_OLD_KEYS
from tagtrail.geometry.posegraph import PoseGraph, PoseGraphResult, relative_residuals, solve
from tagtrail.geometry.reference_path import reference_plane
from tagtrail.geometry.robust import LossName
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import (
    R_from_quat_xyzw,
    inv,
    make_T,
    quat_xyzw_from_R,
    rotation_angle,
    xyz_quat_from_T,
)
from tagtrail.geometry.survey import fit_survey
from tagtrail.schemas.artifacts import (
    CORNER_COLS,
    POSE_COLS,
    both_solutions,
    columns,
    corner_rows,
    poses,
    timed,
)
from tagtrail.schemas.documents import (
    OptimizeReport,
    PlacedComponent,
    RivalPair,
    Summary,
    TagGraph,
)
from tagtrail.schemas.pipeline import SurveyConfig
from tagtrail.stages.base import Export, ExportFiles, Metric, StageParams, refuse_old_keys

log = logging.getLogger(__name__)

TAG_MAP_COLS = columns("optimize.tag_map")
RESIDUAL_COLS = columns("optimize.edge_residuals")


# Fixed, once settings (refused with a line saying so, :data:`OLD_KEYS`): the paper's plain
# stacking of metres and radians in an edge residual; the pose graph converges in 10-30
# evaluations; rival hypotheses are few (the closest 16 are tried, each scored by 10 iterations
# of the joint solve); tags the pose graph left out are always linked through the trajectory
# when the stamps are capture times.
ROT_WEIGHT_M = 1.0
MAX_NFEV = 100
RIVAL_MAX_PAIRS = 16
RIVAL_MAX_ITER = 10

OLD_KEYS = {
    "refine": "use optimize.method (joint | pairwise)",
    "ba_min_frames": "use optimize.joint_min_frames",
    "rot_weight_m": "an edge weighs 1 m per radian (the paper's plain stacking), fixed",
    "max_nfev": "the pose graph stops after 100 evaluations, fixed",
    "rival_max_pairs": "the 16 closest rival pairs are tried, fixed",
    "rival_max_iter": "each rival is scored by 10 iterations of the joint solve, fixed",
    "link_tags": "tags are always linked through the trajectory (stamps that are capture times)",
    **{k: v.format(joint="optimize.joint") for k, v in JOINT_OLD_KEYS.items()},
}


class Params(StageParams):
    method: Literal["joint", "pairwise"] = "joint"
    """``joint`` (default): the pairwise pose graph, then all tag and camera poses jointly on the
    corner reprojection error (needs detections and a camera and ``joint_min_frames``; else the
    pose graph is kept). ``pairwise``: the paper's pose graph alone (Eq. 3.4-3.7)."""
    loss: LossName = "soft_l1"
    """Robust loss on each edge's residual norm (Eq. 3.7): linear, soft_l1, huber, cauchy."""
    f_scale: float = Field(0.1, ge=1e-6, le=100.0)
    """Residual norm (m) where the robust loss turns from quadratic to sub-quadratic."""
    branch_check: Literal["map", "none"] = "map"
    """``map`` (default): after the pose graph's solve, each observation takes the IPPE solution
    the map agrees with in its frame (geometry.ippe.map_branches), the edges it changes are
    rebuilt and the graph solved again (a small, far tag's mirrored solution can look
    unambiguous and bend a map its pair's one or two frames cannot check); ``none``: the
    edges as ``edges`` chose them."""
    rival_search: bool = True
    """Joint solve: decide the tag pairs with a close rival hypothesis (``edges.rival_pairs``)
    by the frames' continuity (``choose_hypotheses``)."""
    joint_min_frames: int = Field(30, ge=1, le=10_000_000)
    """Frames seeing a mapped tag needed for the joint solve; with fewer, the pose graph is
    kept (module docstring)."""
    joint: JointSettings = JointSettings()
    """The joint solve's settings (geometry.joint.settings): corner noise, motion prior, gap,
    ground plane, wheeled drive. ``trajectory`` takes the map's (``optimize.report.joint``)."""

    survey: SurveyConfig | None = None
    """A surveyed world: known tag poses (a ``tagslam.yaml``, a WPILib/PhotonVision field
    layout, a ``tag_map.yaml``, or inline; full or position-only); the map (and so the
    trajectory) is expressed in their frame by a rigid fit (``model: similarity`` adds a scale),
    the residuals at the known tags reported (schemas.pipeline.SurveyConfig)."""

    @model_validator(mode="before")
    @classmethod
    def _old_names(cls, data: Any) -> Any:
        """A key that was once a setting: one line naming its new place."""
        return refuse_old_keys("optimize", data, OLD_KEYS)


INPUTS = {
    "edges": "edges.edges",
    "graph": "edges.graph",
    "observations": "pnp.observations",
    "detections": "extract.detections",
    "camera": "extract.camera",
    "frames": "extract.frames",
}
OUTPUTS = ("tag_map", "edge_residuals", "report")
SCOPE = "all"


def poorly_constrained(tag_map: pd.DataFrame) -> np.ndarray:
    """Tags whose position standard deviation exceeds 3x the map's median (or 5 cm): what the
    diagnostics list and ``map.png`` draws apart. All False when the map has no uncertainty."""
    std = tag_map["std_pos_m"].to_numpy(np.float64) if "std_pos_m" in tag_map else None
    if std is None or not np.isfinite(std).any():
        return np.zeros(len(tag_map), bool)
    med = float(np.nanmedian(std[std > 0])) if (std > 0).any() else 0.0
    return np.asarray(np.isfinite(std) & (std > min(3.0 * med, 0.05)) & (std > 0))


def _per_tag_rms(idx_i: np.ndarray, idx_j: np.ndarray, sq: np.ndarray, n: int) -> np.ndarray:
    """RMS of per-edge values ``sqrt(sq)`` over the edges touching each tag (NaN if none)."""
    s = np.bincount(idx_i, sq, n) + np.bincount(idx_j, sq, n)
    c = np.bincount(idx_i, minlength=n) + np.bincount(idx_j, minlength=n)
    return np.where(c > 0, np.sqrt(s / np.maximum(c, 1)), np.nan)


def surveyed_world(tag_map: pd.DataFrame, cfg: SurveyConfig) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The tag map (anchor frame) re-expressed in the surveyed world of ``cfg`` (geometry.survey:
    rigid or similarity fit on the known tags it holds), and the report block: the fit and the
    residuals at the known tags. A similarity scales every length of the map (positions,
    ``size_m``, ``std_pos_m``, ``res_t_rms_m``: the tags' printed size in the survey's metres);
    the edge residuals stay in the measurements'. :class:`DataError` when the known tags do not
    fix the world."""
    ids = tag_map["tag_id"].to_numpy(np.int64)
    vals = tag_map[POSE_COLS].to_numpy(np.float64)
    map_T_tag = make_T(R_from_quat_xyzw(vals[:, 3:]), vals[:, :3])
    try:
        fit = fit_survey(
            ids,
            map_T_tag,
            cfg.survey(),
            cfg.model == "similarity",
            tag_map["size_m"].to_numpy(np.float64),
        )
    except ValueError as err:
        raise DataError(f"optimize: surveyed world ({cfg.file or 'survey.tags'}): {err}") from err
    W = fit.apply(map_T_tag)
    out = tag_map.copy()
    out[POSE_COLS] = np.concatenate([W[:, :3, 3], quat_xyzw_from_R(W[:, :3, :3])], axis=1)
    for c in ("size_m", "std_pos_m", "res_t_rms_m"):  # lengths in the survey's metres, too
        if c in tag_map.columns:
            out[c] = tag_map[c] * fit.scale
    rot = np.nan_to_num(fit.res_rot_deg, nan=0.0)
    full = np.isfinite(fit.res_rot_deg)
    per_tag = [
        {
            "tag_id": int(i),
            "res_pos_m": float(p),
            "res_rot_deg": float(r) if np.isfinite(r) else None,
        }
        for i, p, r in zip(fit.ids, fit.res_pos_m, fit.res_rot_deg, strict=True)
    ]
    block = {
        "source": cfg.file or "inline",
        "format": cfg.format,
        "model": cfg.model,
        "scale": fit.scale,
        "rotation_deg": float(np.degrees(rotation_angle(fit.R))),
        "translation_m": [float(v) for v in fit.t],
        "tags": fit.ids.astype(int).tolist(),
        "missing": fit.missing,
        "res_pos_rms_m": float(np.sqrt(np.mean(fit.res_pos_m**2))),
        "res_pos_max_m": float(fit.res_pos_m.max()),
        "res_rot_rms_deg": float(np.sqrt(np.mean(rot[full] ** 2))) if full.any() else None,
        "per_tag": per_tag,
    }
    rot_text = (
        "" if block["res_rot_rms_deg"] is None else f", {block['res_rot_rms_deg']:.2f} deg rms"
    )
    log.info(
        "optimize: surveyed world (%s, %s, %s) from known tags %s: residuals %.1f mm rms "
        "(max %.1f mm)%s%s",
        block["source"],
        cfg.format,
        cfg.model,
        block["tags"],
        1e3 * block["res_pos_rms_m"],
        1e3 * block["res_pos_max_m"],
        rot_text,
        f"; known tags not in the map: {fit.missing}" if fit.missing else "",
    )
    return out, block


def _problem(
    m: pd.DataFrame,
    k: np.ndarray,
    cam_T_tag: np.ndarray,
    camera: CameraModel,
    settings: JointSettings,
    timed: bool,
) -> CornerProblem:
    """The joint problem of ``corner_rows`` ``m`` (tag indices ``k``, IPPE solutions
    ``cam_T_tag``)."""
    return corner_problem(
        m["frame_idx"].to_numpy(np.int64),
        m["t_ns"].to_numpy(np.int64),
        k,
        m[CORNER_COLS].to_numpy(np.float64).reshape(-1, 4, 2),
        m["size_m"].to_numpy(np.float64),
        cam_T_tag,
        camera,
        settings,
        timed,
    )


def refine_on_corners(
    R: np.ndarray,
    t: np.ndarray,
    tags: np.ndarray,
    anchor: int,
    observations: pd.DataFrame,
    detections: pd.DataFrame,
    camera: CameraModel,
    params: Params,
    is_timed: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]] | None:
    """The joint solve from the pose-graph map ``R (T, 3, 3)``, ``t (T, 3)`` of the sorted ids
    ``tags``: the ids it maps (``tags`` plus tags linked through the trajectory), their
    ``world_T_tag`` (R, t), standard deviations ``(N, 2)`` (m, rad) and a report block; None when
    too few frames see a mapped tag (``joint_min_frames``). ``is_timed``: the stamps are capture
    times (else no prior and no tag linked through the trajectory)."""
    m = corner_rows(observations, detections, np.unique(observations["tag_id"].to_numpy()))
    n_frames = int(m.loc[m["tag_id"].isin(tags), "frame_idx"].nunique())
    if n_frames < params.joint_min_frames:
        log.info(
            "optimize: only %d frames see a mapped tag (joint_min_frames %d): the map from "
            "tag pairs is kept, not refined over all frames together",
            n_frames,
            params.joint_min_frames,
        )
        return None
    ids = np.union1d(tags, m["tag_id"].to_numpy(np.int64))
    W = np.full((len(ids), 4, 4), np.nan)
    W[np.searchsorted(ids, tags)] = make_T(R, t)
    known = np.isin(ids, tags)
    cam_T_tag = both_solutions(m)
    k = np.searchsorted(ids, m["tag_id"].to_numpy(np.int64))
    linked: list[int] = []
    settings = params.joint
    if is_timed and not known[k].all():
        pb = _problem(m, k, cam_T_tag, camera, settings, is_timed)
        W, now = link_tags(
            W, known, cam_T_tag, pb.ob, pb.t_s, px_per_unit=camera.focal_px, max_gap_s=pb.max_gap_s
        )
        linked = ids[now & ~known].tolist()
        if linked:
            log.info("optimize: tags %s linked to the map through the trajectory", linked)
        known = now
    keep = known[k]
    m, cam_T_tag = m[keep].reset_index(drop=True), cam_T_tag[keep]
    ids, W = ids[known], W[known]
    k = np.searchsorted(ids, m["tag_id"].to_numpy(np.int64))
    pb = _problem(m, k, cam_T_tag, camera, settings, is_timed)
    a = int(np.searchsorted(ids, tags[anchor]))
    free = (np.arange(len(ids)) != a) & (np.bincount(k, minlength=len(ids)) > 0)
    out = solve_on_corners(pb, W, free, settings)
    res = out.res
    for line in [] if out.ground is None else out.ground.lines():
        log.info("optimize: %s", line)
    if not res.converged:
        log.warning(
            "optimize: the joint solve stopped after %d iterations before converging", res.iters
        )
    n_tags = np.bincount(pb.ob.frame, minlength=len(pb.t_ns))
    block = {
        "frames": int(len(pb.t_ns)),
        "single_tag_frames": int((n_tags == 1).sum()),
        "observations": int(len(m)),
        "motion_prior_frames": res.prior_terms,
        "ippe_second_solution": int((out.choice % 2 == 1).sum()),
        "linked_tags": linked,
        "iterations": res.iters,
        "converged": res.converged,
        "cost": res.cost,
        "variance_factor": res.variance_factor,
        "corner_sigma_px": res.sigma_px,
        "rms_px": float(np.sqrt(np.mean(res.res_px**2))),
        "p95_px": float(np.percentile(res.res_px, 95)),
        "ground": None if out.ground is None else dataclasses.asdict(out.ground),
    }
    assert res.tag_std is not None
    fixed = np.where(np.arange(len(ids)) == a, 0.0, np.nan)[:, None]  # the anchor; unobserved
    std = np.where(free[:, None], res.tag_std, fixed)
    return ids, res.R_tag, res.t_tag, std, block


def choose_hypotheses(
    edges: pd.DataFrame,
    hyp: np.ndarray,
    rivals: list[RivalPair],
    graph_of: Callable[[np.ndarray], PoseGraph],
    res: PoseGraphResult,
    tags: np.ndarray,
    edges_anchor: int,
    observations: pd.DataFrame,
    detections: pd.DataFrame,
    camera: CameraModel,
    params: Params,
) -> tuple[np.ndarray, PoseGraphResult, list[list[int]]]:
    """Decide the tag pairs with a rival hypothesis (``edges.rival_pairs``) by the frames'
    continuity: for each, closest call first (at most ``RIVAL_MAX_PAIRS``), the pose graph is
    solved with the pair's rival edges instead and kept if the joint solve from there (corners
    and motion prior, ``RIVAL_MAX_ITER`` iterations from ``initial_cameras``' start) costs
    less. A mirrored tag seen only while
    the view hardly changes agrees with itself across those frames; the frames before and after
    do not agree with it. Returns the edge rows to use, the pose graph's solution and the
    flipped pairs."""
    m = corner_rows(observations, detections, tags)
    k = np.searchsorted(tags, m["tag_id"].to_numpy(np.int64))
    pb = _problem(m, k, both_solutions(m), camera, params.joint, True)
    anchor = int(np.searchsorted(tags, edges_anchor))
    free = (np.arange(len(tags)) != anchor) & (np.bincount(k, minlength=len(tags)) > 0)

    def cost(r: PoseGraphResult) -> float:
        return solve_on_corners(
            pb,
            make_T(r.R, r.t),
            free,
            params.joint,
            max_iter=RIVAL_MAX_ITER,
            covariance=False,
            decide=False,
        ).res.cost

    key = edges["tag_i"].to_numpy(np.int64) * (1 << 32) + edges["tag_j"].to_numpy(np.int64)
    ranked = sorted(rivals, key=lambda p: -p.support_ratio)[:RIVAL_MAX_PAIRS]
    order = [p.tag_i * (1 << 32) + p.tag_j for p in ranked]
    use, best = hyp == 0, cost(res)
    flipped: list[list[int]] = []
    for r in order:
        trial = np.where(key == r, hyp == 1, use)
        r_res = solve(
            graph_of(trial), loss=params.loss, f_scale=params.f_scale, max_nfev=MAX_NFEV
        )  # afresh: a flip turns a whole branch
        c = cost(r_res)
        if c < best:
            use, res, best = trial, r_res, c
            flipped.append([int(r >> 32), int(r & 0xFFFFFFFF)])
    if flipped:
        log.info(
            "optimize: tag pairs %s: the other of the two mirror-image poses fits the "
            "camera's smooth motion better and is used",
            flipped,
        )
    return use, res, flipped


def map_checked_edges(
    edges: pd.DataFrame,
    use: np.ndarray,
    tags: np.ndarray,
    res: PoseGraphResult,
    observations: pd.DataFrame,
    rivals: list[RivalPair],
) -> tuple[pd.DataFrame, int]:
    """``edges`` with the rows in ``use`` rebuilt from the IPPE solutions the map ``res`` (over
    ``tags``) picks for their observations (geometry.ippe.map_branches) where that turns them
    by more than a degree; and the number of rows rebuilt. The map's pick overrides the pair's
    (``edges.branches``): it weighs every edge, the pair only its own frames. Pairs with a rival
    hypothesis are left to ``choose_hypotheses`` (a bridge: the map cannot check it)."""
    obs = observations[observations["tag_id"].isin(tags).to_numpy()]
    obs = obs[~obs.duplicated(["t_ns", "tag_id"], keep=False).to_numpy()]
    S = both_solutions(obs)
    if not np.isfinite(S[:, 1]).all(axis=(1, 2)).any():
        return edges, 0
    k = np.searchsorted(tags, obs["tag_id"].to_numpy(np.int64))
    pick = map_branches(obs["frame_idx"].to_numpy(np.int64), res.R[k], S[:, :, :3, :3])
    chosen = S[np.arange(len(obs)), pick]
    at = pd.MultiIndex.from_arrays([obs["t_ns"].to_numpy(), obs["tag_id"].to_numpy()])
    t_ns = edges["t_ns"].to_numpy()
    ri = at.get_indexer(pd.MultiIndex.from_arrays([t_ns, edges["tag_i"].to_numpy()]))
    rj = at.get_indexer(pd.MultiIndex.from_arrays([t_ns, edges["tag_j"].to_numpy()]))
    pair = edges["tag_i"].to_numpy(np.int64) * (1 << 32) + edges["tag_j"].to_numpy(np.int64)
    rival = np.isin(pair, [r.tag_i * (1 << 32) + r.tag_j for r in rivals])
    rows = np.flatnonzero(use & (ri >= 0) & (rj >= 0) & ~rival)
    T_new = inv(chosen[ri[rows]]) @ chosen[rj[rows]]
    R_old = R_from_quat_xyzw(edges[POSE_COLS[3:]].to_numpy(np.float64)[rows])
    changed = geodesic_angle(R_old, T_new[:, :3, :3]) > np.radians(1.0)
    if not changed.any():
        return edges, 0
    xyz, q = xyz_quat_from_T(T_new[changed])
    edges = edges.copy()
    edges.loc[edges.index[rows[changed]], POSE_COLS] = np.concatenate([xyz, q], axis=1)
    return edges, int(changed.sum())


def components(edges: pd.DataFrame, graph: TagGraph) -> list[np.ndarray]:
    """The tag graph's connected components (tag ids), the anchor's first, then by size."""
    tags = np.asarray(sorted(int(t) for t in graph.get("tags", [])), dtype=np.int64)
    if graph.anchor_id not in tags:
        raise DataError(
            f"optimize: anchor tag {graph.anchor_id} is not among the mapped tags {tags}"
        )
    ti, tj = edges["tag_i"].to_numpy(np.int64), edges["tag_j"].to_numpy(np.int64)
    if not (np.isin(ti, tags).all() and np.isin(tj, tags).all()):
        raise DataError("optimize: edges name tags missing from the graph's tag list")
    ii, jj = np.searchsorted(tags, ti), np.searchsorted(tags, tj)
    adj = coo_matrix((np.ones(len(ii)), (ii, jj)), shape=(len(tags), len(tags)))
    n, label = connected_components(adj, directed=False)
    first = label[np.searchsorted(tags, graph.anchor_id)]
    if n > 1 and n != graph.n_components:  # edges keeps one component, or all of them
        lost = tags[label != first]
        raise DataError(
            f"optimize: tags {lost.tolist()} share no edge path with anchor tag "
            f"{graph.anchor_id} (the edges and graph artifacts disagree; re-run the edges stage)"
        )
    order = sorted(
        range(n), key=lambda c: (c != first, -int((label == c).sum()), int(tags[label == c].min()))
    )
    return [tags[label == c] for c in order]


def run(
    edges: pd.DataFrame,
    graph: TagGraph,
    observations: pd.DataFrame,
    params: Params,
    detections: pd.DataFrame | None = None,
    camera: CameraModel | None = None,
    frames: pd.DataFrame | None = None,
) -> dict[str, Any]:
    """Tag map (``TAG_MAP_COLS``), per-edge residuals (``RESIDUAL_COLS``) and a report dict.

    A tag graph of several components (``edges.on_disconnected: keep``): the anchor's is solved
    as one graph; with a surveyed world, each other component is solved on its own (its most
    observed tag its anchor, only its tags' observations) and placed by the known tags it holds
    (``report.components``); a component no known tag places is left out with a warning, as all
    of them are without a survey."""
    comps = components(edges, graph)
    if len(comps) == 1:
        return _solve(edges, graph, observations, detections, params, camera, frames)
    rest = np.concatenate(comps[1:])
    if params.survey is None:
        log.warning(
            "optimize: tags %s are not linked to anchor tag %d by co-observations and "
            "there is no surveyed world (optimize.survey) to place them: left out",
            rest.tolist(),
            graph.anchor_id,
        )

    def part(
        tags: np.ndarray, anchor: int, obs_all: bool
    ) -> tuple[pd.DataFrame, TagGraph, pd.DataFrame, pd.DataFrame | None]:
        e = edges[edges["tag_i"].isin(tags).to_numpy()]
        g = graph.model_copy(
            update={
                "anchor_id": anchor,
                "tags": [int(t) for t in tags],
                "rival_pairs": [r for r in graph.rival_pairs if r.tag_i in tags],
            }
        )
        if obs_all:  # the anchor's solve keeps every observation: the trajectory may link tags
            return e, g, observations, detections
        return (
            e,
            g,
            observations[observations["tag_id"].isin(tags).to_numpy()],
            None if detections is None else detections[detections["tag_id"].isin(tags).to_numpy()],
        )

    out = _solve(*part(comps[0], graph.anchor_id, True), params, camera=camera, frames=frames)
    if params.survey is None:
        return out
    maps, residuals, placed = [out["tag_map"]], [out["edge_residuals"]], []
    done = set(out["tag_map"]["tag_id"].tolist())
    n_obs = observations.groupby("tag_id").size()
    for tags in comps[1:]:
        if done.issuperset(tags.tolist()):
            continue  # the anchor's joint solve linked it through the trajectory
        counts = n_obs.reindex(tags, fill_value=0).to_numpy()
        anchor = int(tags[int(np.argmax(counts))])
        try:
            sub = _solve(*part(tags, anchor, False), params, camera=camera, frames=frames)
        except DataError as err:
            log.warning(
                "optimize: tags %s (not linked to anchor tag %d) left out: %s",
                tags.tolist(),
                graph.anchor_id,
                err,
            )
            continue
        new = ~sub["tag_map"]["tag_id"].isin(list(done)).to_numpy()
        maps.append(sub["tag_map"][new])
        residuals.append(sub["edge_residuals"])
        done.update(sub["tag_map"]["tag_id"][new].tolist())
        placed.append(
            PlacedComponent(
                anchor_id=anchor, tags=[int(t) for t in tags], survey=sub["report"].survey
            )
        )
    tag_map = pd.concat(maps, ignore_index=True).sort_values("tag_id", ignore_index=True)
    return {
        "tag_map": tag_map,
        "edge_residuals": pd.concat(residuals, ignore_index=True),
        "report": out["report"].model_copy(update={"components": placed}),
    }


def _solve(
    edges: pd.DataFrame,
    graph: TagGraph,
    observations: pd.DataFrame,
    detections: pd.DataFrame | None,
    params: Params,
    camera: CameraModel | None = None,
    frames: pd.DataFrame | None = None,
) -> dict[str, Any]:
    """:func:`run` on one connected tag graph."""
    tags = np.asarray(sorted(int(t) for t in graph.get("tags", [])), dtype=np.int64)
    anchor = graph.anchor_id
    ti, tj = edges["tag_i"].to_numpy(np.int64), edges["tag_j"].to_numpy(np.int64)
    ii, jj = np.searchsorted(tags, ti), np.searchsorted(tags, tj)
    hyp = (
        edges["hypothesis"].to_numpy(np.int64)
        if "hypothesis" in edges.columns
        else np.zeros(len(edges), np.int64)
    )
    use = hyp == 0

    def graph_of(use: np.ndarray) -> PoseGraph:
        vals = edges[POSE_COLS].to_numpy(np.float64)[use]
        return PoseGraph(
            n_tags=len(tags),
            anchor=int(np.searchsorted(tags, anchor)),
            idx_i=ii[use],
            idx_j=jj[use],
            R_obs=R_from_quat_xyzw(vals[:, 3:]),
            t_obs=vals[:, :3],
            weight=edges["weight"].to_numpy(np.float64)[use],
            rot_weight_m=ROT_WEIGHT_M,
        )

    g = graph_of(use)
    res = solve(g, loss=params.loss, f_scale=params.f_scale, max_nfev=MAX_NFEV)
    rebuilt = 0
    for _ in range(3 if params.branch_check == "map" else 0):
        edges, n = map_checked_edges(edges, use, tags, res, observations, graph.rival_pairs)
        if n == 0:
            break
        rebuilt += n
        g = graph_of(use)
        res = solve(g, loss=params.loss, f_scale=params.f_scale, max_nfev=MAX_NFEV)
    if rebuilt:
        log.info(
            "optimize: %d tag-pair links rebuilt from the mirror-image poses the map agrees with",
            rebuilt,
        )
    joint = (
        params.method == "joint"
        and detections is not None
        and len(detections) > 0
        and camera is not None
    )
    flipped: list[list[int]] = []
    if joint and (hyp > 0).any() and params.rival_search and timed(frames):
        assert detections is not None and camera is not None
        use, res, flipped = choose_hypotheses(
            edges,
            hyp,
            graph.rival_pairs,
            graph_of,
            res,
            tags,
            anchor,
            observations,
            detections,
            camera,
            params,
        )
        g = graph_of(use)
    edges = edges[use]
    ti, tj = ti[use], tj[use]
    ii, jj = ii[use], jj[use]
    R_map, t_map, res_t, res_r = res.R, res.t, res.res_t, res.res_r
    bundle, std = None, np.full((len(tags), 2), np.nan)
    std[g.anchor] = 0.0
    if joint:
        assert detections is not None and camera is not None
        is_timed = timed(frames)
        if not is_timed and params.joint.motion != "none":
            log.info(
                "optimize: the stamps are the files' order, not capture times: no motion "
                "prior, no tags linked through the trajectory"
            )
        out = refine_on_corners(
            R_map, t_map, tags, g.anchor, observations, detections, camera, params, is_timed
        )
        if out is not None:
            ids, R_map, t_map, std, bundle = out
            bundle["rival_pairs_flipped"] = flipped
            sel = np.searchsorted(ids, tags)
            res_t, res_r = relative_residuals(R_map[sel], t_map[sel], g)
            tags = ids
            ii, jj = np.searchsorted(tags, ti), np.searchsorted(tags, tj)

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
    tag_map["std_pos_m"] = std[:, 0]
    tag_map["std_rot_deg"] = np.rad2deg(std[:, 1])

    residuals = pd.DataFrame(
        {
            "tag_i": ti.astype(np.int32),
            "tag_j": tj.astype(np.int32),
            "t_ns": edges["t_ns"].to_numpy(np.int64),
            "res_t_m": e_t,
            "res_r_deg": np.rad2deg(e_r),
        }
    )
    survey = None
    if params.survey is not None:
        tag_map, survey = surveyed_world(tag_map, params.survey)
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
        "edges_rebuilt": rebuilt,
        "bundle": bundle,
        "survey": survey,
        "joint": params.joint,
    }
    return {
        "tag_map": tag_map,
        "edge_residuals": residuals,
        "report": OptimizeReport.model_validate(report),
    }


# --- what a sweep ranks by and what a run exports (declared for the runner) ----------------

METRICS = tuple(
    Metric(f"map.{name}", "report", path, unit, default=5 if name == "rms_t_m" else 0)
    for name, path, unit in (
        ("rms_t_m", ("rms_t_m",), "m"),
        ("rms_r_deg", ("rms_r_deg",), "deg"),
        ("rms_px", ("bundle", "rms_px"), "px"),
        ("cost", ("cost",), "1"),
        ("nfev", ("nfev",), "1"),
    )
)


def _tag_map_files(
    tag_map: pd.DataFrame | None, report: OptimizeReport | None
) -> ExportFiles | None:
    """``tag_map.yaml`` and ``tag_map.csv``."""
    if tag_map is None or report is None:
        return None
    return {
        "tag_map.yaml": ("tag_map_yaml", (tag_map, report.anchor_id)),
        "tag_map.csv": ("tag_map_csv", tag_map),
    }


def _evidence_rows(traj: pd.DataFrame) -> list[tuple[str, Any]]:
    """The reference trajectory against its evidence: corner RMS of the output and of the
    frames on their own corners (medians, and their ratio), the temporal step's change, and the
    frames it moved beyond their own uncertainty."""

    def med(c: str) -> Any:
        v = traj[c].to_numpy(np.float64)
        return float(np.nanmedian(v)) if np.isfinite(v).any() else ""

    def top(c: str) -> Any:
        v = traj[c].to_numpy(np.float64)
        return float(np.nanmax(v)) if np.isfinite(v).any() else ""

    rp, ar = med("reproj_px"), med("alone_reproj_px")
    sig = traj["shift_sigma"].to_numpy(np.float64)
    beyond = int(np.sum(sig > SHIFT_SIGMA_BOUND)) if np.isfinite(sig).any() else ""
    return [
        ("frame_reproj_px_median", rp),
        ("frame_alone_reproj_px_median", ar),
        ("frame_reproj_ratio", rp / ar if rp != "" and ar != "" and ar > 0 else ""),
        ("frame_shift_m_median", med("shift_m")),
        ("frame_shift_m_max", top("shift_m")),
        ("frame_shift_deg_max", top("shift_deg")),
        ("frame_shift_sigma_max", top("shift_sigma")),
        ("frames_moved_beyond_evidence", beyond),
    ]


def _diagnostics_file(
    frames: pd.DataFrame | None,
    dets: pd.DataFrame | None,
    obs: pd.DataFrame | None,
    graph: TagGraph | None,
    edges: pd.DataFrame | None,
    tags: pd.DataFrame | None,
    report: OptimizeReport | None,
    traj: pd.DataFrame | None,
) -> ExportFiles | None:
    """``diagnostics.csv`` (metric,value), a superset of the original ``diagnostico_erros.csv``."""
    if frames is None or obs is None:
        return None
    rows: list[tuple[str, Any]] = [
        ("frames_total", len(frames) if len(frames) else obs["frame_idx"].nunique()),
        ("frames_with_detections", int(obs["frame_idx"].nunique())),
        ("frames_with_pose", len(traj) if traj is not None else ""),
        ("detections", len(dets) if dets is not None and len(dets) else len(obs)),
        ("tags_detected", int(obs["tag_id"].nunique())),
        ("tags_mapped", len(tags) if tags is not None else ""),
        ("tags_dropped", len(graph.dropped) if graph is not None else ""),
        ("anchor_tag", f"tag36h11:{report.anchor_id}" if report is not None else ""),
        ("pairwise_edges", len(edges) if edges is not None else ""),
        ("map_residual_rms_t_m", report.rms_t_m if report is not None else ""),
        ("map_residual_rms_r_deg", report.rms_r_deg if report is not None else ""),
    ]
    bundle = report.bundle if report is not None else None
    if bundle is not None:  # the joint solve
        rows += [
            ("map_method", "joint"),
            ("joint_frames", bundle.frames),
            ("joint_single_tag_frames", bundle.single_tag_frames),
            ("joint_motion_prior_frames", bundle.motion_prior_frames),
            ("joint_ippe_second_solution", bundle.ippe_second_solution),
            ("joint_corner_rms_px", bundle.rms_px),
            ("joint_variance_factor", bundle.variance_factor),
            ("joint_corner_sigma_px", bundle.corner_sigma_px),
            (
                "joint_rival_pairs_flipped",
                " ".join(f"tag36h11:{i}-tag36h11:{j}" for i, j in bundle.rival_pairs_flipped),
            ),
        ]
    elif report is not None:
        rows.append(("map_method", report.method))
    if tags is not None and "std_pos_m" in tags.columns:
        weak = tags.loc[poorly_constrained(tags), "tag_id"].astype(int)
        rows += [
            ("tag_std_pos_m_median", float(tags["std_pos_m"].median())),
            ("tag_std_pos_m_max", float(tags["std_pos_m"].max())),
            ("poorly_constrained_tags", " ".join(f"tag36h11:{t}" for t in weak)),
        ]
    survey = report.survey if report is not None else None
    if survey is not None:  # the surveyed world and its residuals at the known tags
        rows += [
            ("survey_source", survey.source),
            ("survey_model", survey.model),
            ("survey_tags", " ".join(f"tag36h11:{t}" for t in survey.tags)),
            ("survey_res_pos_rms_m", survey.res_pos_rms_m),
            ("survey_res_pos_max_m", survey.res_pos_max_m),
            (
                "survey_res_rot_rms_deg",
                "" if survey.res_rot_rms_deg is None else survey.res_rot_rms_deg,
            ),
        ]
    if graph is not None:
        rows.append(
            (
                "weak_links",
                " ".join(
                    f"tag36h11:{w.tag_i}-tag36h11:{w.tag_j}({w.n_frames})" for w in graph.weak_links
                ),
            )
        )
    if traj is not None and "std_pos_m" in traj.columns and traj["std_pos_m"].notna().any():
        rows += [
            ("frame_std_pos_m_median", float(traj["std_pos_m"].median())),
            ("frame_std_pos_m_max", float(traj["std_pos_m"].max())),
        ]
    if traj is not None and "shift_m" in traj.columns:
        rows += _evidence_rows(traj)
    return {"diagnostics.csv": ("metric_value_csv", rows)}


def _recording_map_file(
    traj: pd.DataFrame | None,
    tags: pd.DataFrame | None,
    summary: Summary | None,
    report: Any,
    dataset: str,
) -> ExportFiles | None:
    """``map.png`` of a recording (not a query, whose ``report`` draws its own): its tags and
    trajectory (or photos: camera views) seen from above, in the plane of ``report.plane``."""
    if traj is None or tags is None or len(traj) < 2 or summary is not None:
        return None
    plane_name = str(getattr(report, "plane", "auto"))
    P, R = poses(traj)
    plane = reference_plane(plane_name, P, R)
    return {
        "map.png": (
            "recording_map_png",
            dict(
                dataset=dataset,
                plane_name=plane_name,
                uv=plane.to_uv(P),
                flip_v=bool(plane.n @ R[:, :, 1].mean(axis=0) > 0),
                tags_uv=plane.to_uv(tags[["x_m", "y_m", "z_m"]].to_numpy()),
                tag_ids=tags["tag_id"].astype(int).tolist(),
                weak_tags=poorly_constrained(tags),
                tag_std_m=tags["std_pos_m"].to_numpy(np.float64) if "std_pos_m" in tags else None,
                ref_heading_rad=plane.heading(R),
            ),
        )
    }


EXPORTS = (
    Export(
        "tag_map",
        ("tag_map.yaml", "tag_map.csv"),
        {"tag_map": "optimize.tag_map", "report": "optimize.report"},
        _tag_map_files,
    ),
    Export(
        "diagnostics",
        ("diagnostics.csv",),
        {
            "frames": "extract.frames",
            "dets": "extract.detections",
            "obs": "pnp.observations",
            "graph": "edges.graph",
            "edges": "edges.edges",
            "tags": "optimize.tag_map",
            "report": "optimize.report",
            "traj": "smooth.trajectory",
        },
        _diagnostics_file,
    ),
    Export(
        "recording_map",
        ("map.png",),
        {
            "traj": "smooth.trajectory",
            "tags": "optimize.tag_map",
            "summary": "report.summary",
            "report": "params:report",
        },
        _recording_map_file,
    ),
)
