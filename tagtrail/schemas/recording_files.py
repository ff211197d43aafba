"""A recording's own files beside its tables, which stage ``optimize`` declares as exports
(``EXPORTS``; the runner writes them through ``io.outputs``): ``diagnostics.csv``, what its
artifacts say about its map and trajectory, one metric per row (the frames and detections, the
tag graph, the map's residuals and method, the joint solve, the tags' uncertainty, the surveyed
world, the trajectory against its evidence); ``map.png``, its tags and trajectory from above."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from tagtrail.geometry.joint.evidence import evidence_rows
from tagtrail.geometry.reference_path import reference_plane
from tagtrail.geometry.tagmap import poorly_constrained
from tagtrail.schemas.artifacts import EVIDENCE_COLS, poses
from tagtrail.schemas.documents import OptimizeReport, Summary, TagGraph
from tagtrail.schemas.stage import ExportFiles


def diagnostics_file(
    frames: pd.DataFrame | None,
    dets: pd.DataFrame | None,
    obs: pd.DataFrame | None,
    graph: TagGraph | None,
    edges: pd.DataFrame | None,
    tags: pd.DataFrame | None,
    report: OptimizeReport | None,
    traj: pd.DataFrame | None,
) -> ExportFiles | None:
    """``diagnostics.csv`` (metric,value), a superset of the original ``diagnostico_erros.csv``:
    ``optimize``'s export of these artifacts (``""``: the artifact is missing)."""
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


def recording_map_file(
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
