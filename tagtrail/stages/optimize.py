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
Old parameter names (``refine``, ``ba_*``, the joint solve's) are refused with one line naming
their new place (:data:`OLD_KEYS`). The maths lives in geometry: the pose graph
(:mod:`~tagtrail.geometry.posegraph`, its edges, branch check and components in
:mod:`~tagtrail.geometry.tagmap`), the joint solve from it
(:mod:`~tagtrail.geometry.joint.mapping`),
the surveyed world (:mod:`~tagtrail.geometry.survey`).
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator

from tagtrail.errors import DataError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.joint import (
    JointSettings,
    MapRefinement,
    choose_rivals,
    evidence_rows,
    refine_map,
)
from tagtrail.geometry.joint.settings import JOINT_OLD_KEYS
from tagtrail.geometry.posegraph import PoseGraphResult, relative_residuals, solve
from tagtrail.geometry.reference_path import reference_plane
from tagtrail.geometry.robust import LossName
from tagtrail.geometry.se3 import R_from_quat_xyzw, make_T, quat_xyzw_from_R
from tagtrail.geometry.survey import fit_survey
from tagtrail.geometry.tagmap import (
    EdgeSet,
    map_checked_edges,
    pair_key,
    per_tag_rms,
    poorly_constrained,
    tag_components,
)
from tagtrail.schemas.artifacts import (
    EVIDENCE_COLS,
    POSE_COLS,
    both_solutions,
    columns,
    corner_arrays,
    corner_rows,
    poses,
    timed,
)
from tagtrail.schemas.documents import OptimizeReport, PlacedComponent, Summary, TagGraph
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


def surveyed_world(tag_map: pd.DataFrame, cfg: SurveyConfig) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The tag map (anchor frame) re-expressed in the surveyed world of ``cfg`` (geometry.survey:
    rigid or similarity fit on the known tags it holds), and the report block: the fit and the
    residuals at the known tags. A similarity scales every length of the map (positions,
    ``size_m``, ``std_pos_m``, ``res_t_rms_m``: the tags' printed size in the survey's metres);
    the edge residuals stay in the measurements'. :class:`DataError` when the known tags do not
    fix the world."""
    vals = tag_map[POSE_COLS].to_numpy(np.float64)
    map_T_tag = make_T(R_from_quat_xyzw(vals[:, 3:]), vals[:, :3])
    similarity, sizes = cfg.model == "similarity", tag_map["size_m"].to_numpy(np.float64)
    try:
        fit = fit_survey(
            tag_map["tag_id"].to_numpy(np.int64), map_T_tag, cfg.survey(), similarity, sizes
        )
    except ValueError as err:
        raise DataError(f"optimize: surveyed world ({cfg.file or 'survey.tags'}): {err}") from err
    W = fit.apply(map_T_tag)
    out = tag_map.copy()
    out[POSE_COLS] = np.concatenate([W[:, :3, 3], quat_xyzw_from_R(W[:, :3, :3])], axis=1)
    for c in ("size_m", "std_pos_m", "res_t_rms_m"):  # lengths in the survey's metres, too
        if c in tag_map.columns:
            out[c] = tag_map[c] * fit.scale
    fig = fit.report()
    rot_rms = fig["res_rot_rms_deg"]
    log.info(
        "optimize: surveyed world (%s, %s, %s) from known tags %s: residuals %.1f mm rms "
        "(max %.1f mm)%s%s",
        cfg.file or "inline",
        cfg.format,
        cfg.model,
        fig["tags"],
        1e3 * fig["res_pos_rms_m"],
        1e3 * fig["res_pos_max_m"],
        "" if rot_rms is None else f", {rot_rms:.2f} deg rms",
        f"; known tags not in the map: {fit.missing}" if fit.missing else "",
    )
    return out, {"source": cfg.file or "inline", "format": cfg.format, "model": cfg.model, **fig}


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
    tags = np.asarray(sorted(int(t) for t in graph.get("tags", [])), dtype=np.int64)
    if graph.anchor_id not in tags:
        raise DataError(
            f"optimize: anchor tag {graph.anchor_id} is not among the mapped tags {tags}"
        )
    ti, tj = edges["tag_i"].to_numpy(np.int64), edges["tag_j"].to_numpy(np.int64)
    if not (np.isin(ti, tags).all() and np.isin(tj, tags).all()):
        raise DataError("optimize: edges name tags missing from the graph's tag list")
    comps = tag_components(tags, ti, tj, graph.anchor_id)
    if len(comps) > 1 and len(comps) != graph.n_components:  # edges keeps one, or all of them
        raise DataError(
            f"optimize: tags {np.sort(np.concatenate(comps[1:])).tolist()} share no edge path "
            f"with anchor tag {graph.anchor_id} (the edges and graph artifacts disagree; re-run "
            "the edges stage)"
        )
    if len(comps) == 1:
        return _solve(edges, graph, observations, detections, params, camera, frames)
    if params.survey is None:
        log.warning(
            "optimize: tags %s are not linked to anchor tag %d by co-observations and "
            "there is no surveyed world (optimize.survey) to place them: left out",
            np.concatenate(comps[1:]).tolist(),
            graph.anchor_id,
        )

    def part(tags: np.ndarray, anchor: int, obs_all: bool) -> dict[str, Any]:
        """One component's :func:`_solve` (``obs_all``: with every observation, so that the
        anchor's joint solve may link tags through the trajectory)."""
        g = graph.model_copy(
            update={
                "anchor_id": anchor,
                "tags": [int(t) for t in tags],
                "rival_pairs": [r for r in graph.rival_pairs if r.tag_i in tags],
            }
        )
        obs, dets = observations, detections
        if not obs_all:
            obs = obs[obs["tag_id"].isin(tags).to_numpy()]
            dets = None if dets is None else dets[dets["tag_id"].isin(tags).to_numpy()]
        e = edges[edges["tag_i"].isin(tags).to_numpy()]
        return _solve(e, g, obs, dets, params, camera, frames)

    out = part(comps[0], graph.anchor_id, True)
    if params.survey is None:
        return out
    maps, residuals, placed = [out["tag_map"]], [out["edge_residuals"]], []
    done = set(out["tag_map"]["tag_id"].tolist())
    n_obs = observations.groupby("tag_id").size()
    for tags in comps[1:]:
        if done.issuperset(tags.tolist()):
            continue  # the anchor's joint solve linked it through the trajectory
        anchor = int(tags[int(np.argmax(n_obs.reindex(tags, fill_value=0).to_numpy()))])
        try:
            sub = part(tags, anchor, False)
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
            PlacedComponent(anchor_id=anchor, tags=tags.tolist(), survey=sub["report"].survey)
        )
    return {
        "tag_map": pd.concat(maps, ignore_index=True).sort_values("tag_id", ignore_index=True),
        "edge_residuals": pd.concat(residuals, ignore_index=True),
        "report": out["report"].model_copy(update={"components": placed}),
    }


def _edge_set(edges: pd.DataFrame, tags: np.ndarray) -> EdgeSet:
    """``edges.edges`` over the sorted ids ``tags`` as arrays."""
    n = len(edges)
    return EdgeSet(
        tags,
        edges["tag_i"].to_numpy(np.int64),
        edges["tag_j"].to_numpy(np.int64),
        edges["t_ns"].to_numpy(np.int64),
        edges[POSE_COLS].to_numpy(np.float64),
        edges["weight"].to_numpy(np.float64),
        edges["hypothesis"].to_numpy(np.int64) if "hypothesis" in edges else np.zeros(n, np.int64),
    )


def _solve(
    edges: pd.DataFrame,
    graph: TagGraph,
    observations: pd.DataFrame,
    detections: pd.DataFrame | None,
    params: Params,
    camera: CameraModel | None = None,
    frames: pd.DataFrame | None = None,
) -> dict[str, Any]:
    """:func:`run` on one connected tag graph: the pose graph, its branch check, the rival
    hypotheses, the joint solve; the tables and the report."""
    tags = np.asarray(sorted(int(t) for t in graph.get("tags", [])), dtype=np.int64)
    anchor, E = graph.anchor_id, _edge_set(edges, tags)

    def solve_graph(use: np.ndarray) -> PoseGraphResult:
        g = E.graph(use, anchor, ROT_WEIGHT_M)
        return solve(g, loss=params.loss, f_scale=params.f_scale, max_nfev=MAX_NFEV)

    use = E.hypothesis == 0
    res, rebuilt = solve_graph(use), 0
    rivals = np.array([int(pair_key(r.tag_i, r.tag_j)) for r in graph.rival_pairs], np.int64)
    if params.branch_check == "map":
        obs = observations[observations["tag_id"].isin(tags).to_numpy()]
        obs = obs[~obs.duplicated(["t_ns", "tag_id"], keep=False).to_numpy()]
        o_t, o_tag = obs["t_ns"].to_numpy(np.int64), obs["tag_id"].to_numpy(np.int64)
        o_frame, S = obs["frame_idx"].to_numpy(np.int64), both_solutions(obs)
    for _ in range(3 if params.branch_check == "map" else 0):
        R_obs = res.R[np.searchsorted(tags, o_tag)]
        E, n = map_checked_edges(E, use, np.isin(E.key, rivals), o_t, o_tag, o_frame, S, R_obs)
        if n == 0:
            break
        rebuilt += n
        res = solve_graph(use)
    if rebuilt:
        log.info(
            "optimize: %d tag-pair links rebuilt from the mirror-image poses the map agrees with",
            rebuilt,
        )
    joint = params.method == "joint" and detections is not None and len(detections) > 0
    joint = joint and camera is not None
    flipped: list[list[int]] = []
    if joint and (E.hypothesis > 0).any() and params.rival_search and timed(frames):
        assert detections is not None and camera is not None
        ranked = sorted(graph.rival_pairs, key=lambda p: -p.support_ratio)[:RIVAL_MAX_PAIRS]
        use, res, flipped = choose_rivals(
            corner_arrays(corner_rows(observations, detections, tags)),
            tags,
            int(np.searchsorted(tags, anchor)),
            camera,
            params.joint,
            E.key,
            E.hypothesis,
            [int(pair_key(p.tag_i, p.tag_j)) for p in ranked],
            res,
            solve_graph,
            RIVAL_MAX_ITER,
        )
        if flipped:
            log.info(
                "optimize: tag pairs %s: the other of the two mirror-image poses fits the "
                "camera's smooth motion better and is used",
                flipped,
            )
    g = E.graph(use, anchor, ROT_WEIGHT_M)
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
        refined = _refine(
            R_map, t_map, tags, g.anchor, observations, detections, camera, params, is_timed
        )
        if refined is not None:
            R_map, t_map, std, bundle = refined.R, refined.t, refined.std, refined.block
            bundle["rival_pairs_flipped"] = flipped
            sel = np.searchsorted(refined.ids, tags)
            res_t, res_r = relative_residuals(R_map[sel], t_map[sel], g)
            tags = refined.ids
    ti, tj = E.tag_i[use], E.tag_j[use]
    ii, jj = np.searchsorted(tags, ti), np.searchsorted(tags, tj)
    e_t, e_r = np.linalg.norm(res_t, axis=1), np.linalg.norm(res_r, axis=1)
    obs_tag = observations["tag_id"].to_numpy(np.int64)
    n_obs = pd.Series(obs_tag).value_counts().reindex(tags, fill_value=0).to_numpy(np.int64)
    size = np.full(len(tags), np.nan)
    if "size_m" in observations.columns:
        size = observations.groupby("tag_id")["size_m"].median().reindex(tags).to_numpy(float)
    tag_map = pd.DataFrame({"tag_id": tags.astype(np.int32)})
    tag_map[POSE_COLS] = np.concatenate([t_map, quat_xyzw_from_R(R_map)], axis=1)
    tag_map["n_obs"] = n_obs
    tag_map["size_m"] = size
    tag_map["res_t_rms_m"] = per_tag_rms(ii, jj, e_t**2, len(tags))
    tag_map["res_r_rms_deg"] = np.rad2deg(per_tag_rms(ii, jj, e_r**2, len(tags)))
    tag_map["std_pos_m"] = std[:, 0]
    tag_map["std_rot_deg"] = np.rad2deg(std[:, 1])
    residuals = pd.DataFrame(
        {
            "tag_i": ti.astype(np.int32),
            "tag_j": tj.astype(np.int32),
            "t_ns": E.t_ns[use],
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


def _refine(
    R: np.ndarray,
    t: np.ndarray,
    tags: np.ndarray,
    anchor: int,
    observations: pd.DataFrame,
    detections: pd.DataFrame,
    camera: CameraModel,
    params: Params,
    is_timed: bool,
) -> MapRefinement | None:
    """The joint solve from the pose graph's map (geometry.joint.refine_map) on the corners of
    every observed tag, its lines logged; None when fewer than ``joint_min_frames`` frames see
    a mapped tag."""
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
    out = refine_map(R, t, tags, anchor, corner_arrays(m), camera, params.joint, is_timed)
    if out.linked:
        log.info("optimize: tags %s linked to the map through the trajectory", out.linked)
    for line in [] if out.solved.ground is None else out.solved.ground.lines():
        log.info("optimize: %s", line)
    if not out.solved.res.converged:
        log.warning(
            "optimize: the joint solve stopped after %d iterations before converging",
            out.solved.res.iters,
        )
    return out


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
        weak = tags.loc[poorly_constrained(tags["std_pos_m"].to_numpy(np.float64)), "tag_id"]
        rows += [
            ("tag_std_pos_m_median", float(tags["std_pos_m"].median())),
            ("tag_std_pos_m_max", float(tags["std_pos_m"].max())),
            ("poorly_constrained_tags", " ".join(f"tag36h11:{int(t)}" for t in weak)),
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
        rows += evidence_rows(*(traj[c].to_numpy(np.float64) for c in EVIDENCE_COLS))
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
    std = tags["std_pos_m"].to_numpy(np.float64) if "std_pos_m" in tags else None
    view = dict(
        dataset=dataset,
        plane_name=plane_name,
        uv=plane.to_uv(P),
        flip_v=plane.v_down(R),
        tags_uv=plane.to_uv(tags[["x_m", "y_m", "z_m"]].to_numpy()),
        tag_ids=tags["tag_id"].astype(int).tolist(),
        weak_tags=poorly_constrained(np.full(len(tags), np.nan) if std is None else std),
        tag_std_m=std,
        ref_heading_rad=plane.heading(R),
    )
    return {"map.png": ("recording_map_png", view)}


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
