"""optimize: the tag map ``world_T_tag`` (Eq. 3.4-3.7), its per-edge residuals and a report.

Per connected tag graph (:func:`tagtrail.geometry.tagmap.build_map`, where the method is told in
full): the pose graph of the pairwise edges (robust ``loss`` with scale ``f_scale``, the anchor
tag fixed at the identity) and its check of each observation's IPPE solution
(``branch_check``); ``method="joint"`` (the default; datasets with detections and a camera,
``joint_min_frames`` frames or more seeing a mapped tag, else the pose graph is kept and the log
says so) then the tag and camera poses jointly on the corners, held in time by the priors of
:mod:`tagtrail.geometry.joint` (settings ``joint``, which ``trajectory`` takes too), the tags the
pose graph left out linked through the trajectory, close rival pairs decided
(``branch_check``). Each tag gets its standard deviation (``std_pos_m``, ``std_rot_deg``; the
anchor 0); the edge residuals and per-tag RMS are those of the final map. ``"pairwise"``: the
paper's pose graph alone, also what observation-only datasets get. With ``survey``, the map is
put in the surveyed world (:mod:`tagtrail.geometry.survey`). Old parameter names are refused
with one line naming their new place (:data:`OLD_KEYS`).
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator

from tagtrail.errors import DataError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.joint import JointSettings, OdometryData, odometry_input
from tagtrail.geometry.joint.settings import JOINT_OLD_KEYS
from tagtrail.geometry.robust import LossName
from tagtrail.geometry.se3 import R_from_quat_xyzw, make_T, quat_xyzw_from_R
from tagtrail.geometry.survey import fit_survey
from tagtrail.geometry.tagmap import (
    GraphSettings,
    JointInputs,
    build_map,
    pair_key,
    per_tag_rms,
    tag_components,
)
from tagtrail.schemas.artifacts import (
    POSE_COLS,
    columns,
    corner_arrays,
    corner_rows,
    edge_arrays,
    sightings,
    timed,
)
from tagtrail.schemas.documents import MountDoc, OptimizeReport, PlacedComponent, TagGraph
from tagtrail.schemas.pipeline import SurveyConfig
from tagtrail.schemas.recording_files import diagnostics_file, recording_map_file
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
    "rival_search": "use optimize.branch_check (no_rivals: the map's check without the rival "
    "pairs' decision)",
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
    branch_check: Literal["map", "no_rivals", "none"] = "map"
    """``map`` (default): after the pose graph's solve, each observation takes the IPPE solution
    the map agrees with in its frame (geometry.ippe.map_branches), the edges it changes are
    rebuilt and the graph solved again (a small, far tag's mirrored solution can look
    unambiguous and bend a map its pair's one or two frames cannot check); then the joint
    solve decides the tag pairs with a close rival hypothesis (``edges.rival_pairs``) by the
    frames' continuity (``choose_hypotheses``). ``no_rivals``: the map's check without the
    rival pairs' decision; ``none``: the edges as ``edges`` chose them (the rival pairs still
    decided by the frames)."""
    joint_min_frames: int = Field(30, ge=1, le=10_000_000)
    """Frames seeing a mapped tag needed for the joint solve; with fewer, the pose graph is
    kept (module docstring)."""
    joint: JointSettings = JointSettings()
    """The joint solve's settings (geometry.joint.settings): corner noise, motion prior, gap,
    ground plane, wheeled drive, wheel odometry. ``trajectory`` takes the map's
    (``optimize.report.joint``)."""

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
    "odometry": "extract.odometry",
    "mount": "extract.mount",
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
    log.info("optimize: %s", fit.line(f"{cfg.file or 'inline'}, {cfg.format}, {cfg.model}"))
    return out, {"source": cfg.file or "inline", "format": cfg.format, "model": cfg.model, **fig}


def run(
    edges: pd.DataFrame,
    graph: TagGraph,
    observations: pd.DataFrame,
    params: Params,
    detections: pd.DataFrame | None = None,
    camera: CameraModel | None = None,
    frames: pd.DataFrame | None = None,
    odometry: pd.DataFrame | None = None,
    mount: MountDoc | None = None,
) -> dict[str, Any]:
    """Tag map (``TAG_MAP_COLS``), per-edge residuals (``RESIDUAL_COLS``) and a report dict;
    ``odometry``/``mount``: ``extract.odometry`` and ``extract.mount`` (the wheel-odometry
    prior of the joint solve, when the dataset has odometry).

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
    blind = None
    if frames is not None and len(frames):
        seen = observations["frame_idx"]
        blind = frames.loc[~frames["frame_idx"].isin(seen), "t_ns"].to_numpy(np.int64)
    odo = odometry_input(odometry, mount, blind)
    if len(comps) == 1:
        return _solve(edges, graph, observations, detections, params, camera, frames, odo)
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
        return _solve(e, g, obs, dets, params, camera, frames, odo if obs_all else None)

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


def _solve(
    edges: pd.DataFrame,
    graph: TagGraph,
    observations: pd.DataFrame,
    detections: pd.DataFrame | None,
    params: Params,
    camera: CameraModel | None = None,
    frames: pd.DataFrame | None = None,
    odometry: OdometryData | None = None,
) -> dict[str, Any]:
    """:func:`run` on one connected tag graph (geometry.tagmap.build_map): the tables and the
    report; ``odometry``: the wheel-odometry prior's data (the anchor's graph only)."""
    tags = np.asarray(sorted(int(t) for t in graph.get("tags", [])), dtype=np.int64)
    joint, is_timed = None, timed(frames)
    has_pix = detections is not None and len(detections) > 0 and camera is not None
    if params.method == "joint" and has_pix:
        assert detections is not None and camera is not None
        ranked = sorted(graph.rival_pairs, key=lambda p: -p.support_ratio)[:RIVAL_MAX_PAIRS]
        rivals = [int(pair_key(p.tag_i, p.tag_j)) for p in ranked]
        rows = corner_rows(observations, detections, np.unique(observations["tag_id"].to_numpy()))
        joint = JointInputs(
            corner_arrays(rows),
            camera,
            params.joint,
            is_timed,
            params.joint_min_frames,
            rivals if params.branch_check != "no_rivals" and is_timed else None,
            RIVAL_MAX_ITER,
            odometry,
        )
    check = sightings(observations, tags) if params.branch_check != "none" else None
    skip = np.array([int(pair_key(r.tag_i, r.tag_j)) for r in graph.rival_pairs], np.int64)
    gs = GraphSettings(params.loss, params.f_scale, MAX_NFEV, ROT_WEIGHT_M)
    E = edge_arrays(edges, tags)
    m = build_map(E, graph.anchor_id, gs, check, skip, joint)
    for line in m.lines():
        log.info("optimize: %s", line)
    for line in m.warnings():
        log.warning("optimize: %s", line)
    tags, ti, tj = m.tags, E.tag_i[m.use], E.tag_j[m.use]
    ii, jj = np.searchsorted(tags, ti), np.searchsorted(tags, tj)
    e_t, e_r = np.linalg.norm(m.res_t, axis=1), np.linalg.norm(m.res_r, axis=1)
    obs_tag = observations["tag_id"].to_numpy(np.int64)
    size = np.full(len(tags), np.nan)
    if "size_m" in observations.columns:
        size = observations.groupby("tag_id")["size_m"].median().reindex(tags).to_numpy(float)
    tag_map = pd.DataFrame({"tag_id": tags.astype(np.int32)})
    tag_map[POSE_COLS] = np.concatenate([m.t, quat_xyzw_from_R(m.R)], axis=1)
    n_obs = pd.Series(obs_tag).value_counts().reindex(tags, fill_value=0)
    tag_map["n_obs"] = n_obs.to_numpy(np.int64)
    tag_map["size_m"] = size
    tag_map["res_t_rms_m"] = per_tag_rms(ii, jj, e_t**2, len(tags))
    tag_map["res_r_rms_deg"] = np.rad2deg(per_tag_rms(ii, jj, e_r**2, len(tags)))
    tag_map["std_pos_m"] = m.std[:, 0]
    tag_map["std_rot_deg"] = np.rad2deg(m.std[:, 1])
    residuals = pd.DataFrame(
        {
            "tag_i": ti.astype(np.int32),
            "tag_j": tj.astype(np.int32),
            "t_ns": E.t_ns[m.use],
            "res_t_m": e_t,
            "res_r_deg": np.rad2deg(e_r),
        }
    )
    survey = None
    if params.survey is not None:
        tag_map, survey = surveyed_world(tag_map, params.survey)
    flipped = {"rival_pairs_flipped": m.flipped}
    report = {
        "anchor_id": graph.anchor_id,
        "loss": params.loss,
        "f_scale": params.f_scale,
        "cost": m.graph.cost,
        "nfev": m.graph.nfev,
        "status": m.graph.status,
        "rms_t_m": float(np.sqrt(np.mean(e_t**2))) if len(e_t) else 0.0,
        "rms_r_deg": float(np.rad2deg(np.sqrt(np.mean(e_r**2)))) if len(e_r) else 0.0,
        "method": "pairwise" if m.refined is None else "joint",
        "edges_rebuilt": m.rebuilt,
        "bundle": None if m.refined is None else {**m.refined.block, **flipped},
        "survey": survey,
        "joint": params.joint,
    }
    return {
        "tag_map": tag_map,
        "edge_residuals": residuals,
        "report": OptimizeReport.model_validate(report),
    }


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


def _ground_file(report: OptimizeReport | None) -> ExportFiles | None:
    """``ground.json`` (:class:`~tagtrail.schemas.documents.KnownGround`): the plane and mount
    the joint solve held, for the live smoother; none when the ground prior was not applied."""
    g = None if report is None or report.bundle is None else report.bundle.ground
    doc = None if g is None else g.known()
    if doc is None:
        return None
    return {"ground.json": ("json", doc.model_dump(mode="json"))}


EXPORTS = (
    Export(
        "tag_map",
        ("tag_map.yaml", "tag_map.csv"),
        {"tag_map": "optimize.tag_map", "report": "optimize.report"},
        _tag_map_files,
    ),
    Export("ground", ("ground.json",), {"report": "optimize.report"}, _ground_file),
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
        diagnostics_file,
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
        recording_map_file,
    ),
)
