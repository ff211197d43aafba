"""After a run: the human-facing SPEC files in ``outputs/<dataset>/``, from the artifacts.

Each exporter is called per dataset with a getter ``get(stage, output, reference=False)`` that
returns the up-to-date artifact (of this dataset or of the reference) or ``None``, writes the
files whose artifacts exist (atomically, through ``io``'s writers) and says whether it wrote any.
A dataset whose artifacts and exporter code are unchanged since its last export, and whose
files still hash to what that export wrote (recorded in ``.tagtrail-export.json``), is skipped;
any missing or altered file makes the whole folder be written again (``force`` always does).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tagtrail import faults
from tagtrail.geometry.joint import SHIFT_SIGMA_BOUND
from tagtrail.geometry.reference_path import reference_plane
from tagtrail.io import layouts, reloc_files
from tagtrail.io.layouts import atomic_write_text
from tagtrail.io.reloc_plots import is_photo_set
from tagtrail.runner.cache import (
    canonical_json,
    file_sha256,
    pretty_json,
    sha256_text,
)
from tagtrail.runner.execute import Runner
from tagtrail.runner.paths import (
    EXPORT_STAMP,
    check_project,
    clean_temp_files,
    clear_obstacles,
    inside,
)
from tagtrail.runner.stage import code_fingerprint
from tagtrail.schemas.artifacts import EVIDENCE_COLS, columns, per_frame, poses
from tagtrail.stages import optimize

STAMP = EXPORT_STAMP
#: stages whose parameters the exporters read (``get("params", stage)``); in the export stamp
DRAWN_WITH = ("report",)


def _hashes(folder: Path) -> dict[str, str]:
    return {p.name: file_sha256(p) for p in sorted(folder.iterdir())
            if p.is_file() and not p.name.startswith(".")}


def _unchanged(folder: Path, stamp: str) -> bool:
    """True when ``folder`` was exported from the same artifacts and code and every file it
    wrote is still there, byte for byte."""
    try:
        doc = json.loads((folder / STAMP).read_text())
        files = doc["files"]
        return bool(doc["stamp"] == stamp and isinstance(files, dict) and all(
            file_sha256(folder / name) == digest for name, digest in files.items()))
    except (OSError, ValueError, KeyError, TypeError):
        return False


def export_outputs(runner: Runner, force: bool = False) -> dict[str, Path]:
    """Write every dataset's files from the up-to-date artifacts; returns dataset → folder.

    Runs under the store's lock, like the stages: leftovers of a killed export are removed.
    The paths are checked first (:func:`tagtrail.runner.paths.check_project`).
    """
    check_project(runner.pipe, ("outputs",))
    with runner.store.lock():
        clear_obstacles(runner.pipe, ("outputs",))
        return _export(runner, force)


def _export(runner: Runner, force: bool) -> dict[str, Path]:
    keys = {(s.stage, s.dataset): s.key for s in runner.plan() if s.status == "cached"}
    code = code_fingerprint(sys.modules[__name__])
    written: dict[str, Path] = {}
    for dataset in runner.pipe.datasets:
        used = sorted(f"{st}/{ds}/{k}" for (st, ds), k in keys.items()
                      if ds in (dataset, runner.pipe.reference))
        # the parameters the exporters draw with (report.plane for map.png): a change redraws
        drawn = {st: runner.pipe.params_for(st, dataset).model_dump(mode="json")
                 for st in DRAWN_WITH if st in runner.pipe.stages}  # fmt: skip
        stamp = sha256_text(canonical_json({"code": code, "artifacts": used, "params": drawn}))
        folder = inside(runner.pipe.outputs, dataset)
        clean_temp_files(folder)
        if not force and _unchanged(folder, stamp):
            written[dataset] = folder
            continue
        cache: dict[tuple[str, str], Any] = {}

        def get(
            stage: str,
            output: str,
            reference: bool = False,
            dataset: str = dataset,
            cache: dict[Any, Any] = cache,
        ) -> Any:
            ds = runner.pipe.reference if reference else dataset
            if stage == "params":  # get("params", STAGE): the stage's parameters (DRAWN_WITH)
                return runner.pipe.params_for(output, ds) if output in DRAWN_WITH else None
            key = keys.get((stage, ds))
            if key is None or output not in runner.pipe.stages[stage].outputs:
                return None
            if (stage, output, ds) not in cache:
                cache[(stage, output, ds)] = runner.store.load(stage, key, output)
            return cache[(stage, output, ds)]

        wrote = False
        for exporter in EXPORTERS:
            wrote |= bool(exporter(get, folder, dataset))
            faults.point(f"export:{exporter.__name__}")
        if wrote:
            written[dataset] = folder
            doc = {"stamp": stamp, "files": _hashes(folder)}
            atomic_write_text(folder / STAMP, json.dumps(doc, indent=1, sort_keys=True))
    return written


# --- the exporters: SPEC files from a dataset's artifacts ---------------------------------

Getter = Callable[..., Any]


def trajectories(get: Getter, folder: Path, dataset: str) -> bool:
    """``trajectory.csv``, ``trajectory.tum`` (smoothed) and ``trajectory_raw.csv`` (each frame on
    its own: before the motion prior or the smoother); with them
    ``trajectory_std.csv`` (each frame's standard deviation) and ``trajectory_evidence.csv``
    (each frame's fit to its own corners) when the trajectory has them."""
    wrote = False
    smooth = get("smooth", "trajectory")
    if smooth is not None:
        layouts.write_trajectory_csv(folder / "trajectory.csv", smooth)
        layouts.write_trajectory_tum(folder / "trajectory.tum", smooth)
        for name, cols, text in (
                ("trajectory_std.csv", layouts.STD_COLS, layouts.trajectory_std_csv_text),
                ("trajectory_evidence.csv", EVIDENCE_COLS,
                 layouts.trajectory_evidence_csv_text)):
            if all(c in smooth.columns for c in cols) and smooth[cols[0]].notna().any():
                layouts.atomic_write_text(folder / name, text(smooth))
            else:
                (folder / name).unlink(missing_ok=True)  # not a stale one from another run
        wrote = True
    raw = get("trajectory", "trajectory")
    if raw is not None:  # before any temporal step: each frame on its own corners
        layouts.write_trajectory_csv(folder / "trajectory_raw.csv", per_frame(raw))
        wrote = True
    return wrote


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
    return [("frame_reproj_px_median", rp), ("frame_alone_reproj_px_median", ar),
            ("frame_reproj_ratio", rp / ar if rp != "" and ar != "" and ar > 0 else ""),
            ("frame_shift_m_median", med("shift_m")), ("frame_shift_m_max", top("shift_m")),
            ("frame_shift_deg_max", top("shift_deg")),
            ("frame_shift_sigma_max", top("shift_sigma")),
            ("frames_moved_beyond_evidence", beyond)]


def tag_map(get: Getter, folder: Path, dataset: str) -> bool:
    """``tag_map.yaml`` and ``tag_map.csv``."""
    tags, report = get("optimize", "tag_map"), get("optimize", "report")
    if tags is None or report is None:
        return False
    layouts.write_tag_map(folder, tags, report.anchor_id)
    return True


def diagnostics(get: Getter, folder: Path, dataset: str) -> bool:
    """``diagnostics.csv`` (metric,value), a superset of the original ``diagnostico_erros.csv``."""
    frames, dets = get("extract", "frames"), get("extract", "detections")
    obs, graph = get("pnp", "observations"), get("edges", "graph")
    edges, tags = get("edges", "edges"), get("optimize", "tag_map")
    report = get("optimize", "report")
    traj = get("smooth", "trajectory")
    if frames is None or obs is None:
        return False
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
        rows += [("map_method", "joint"), ("joint_frames", bundle.frames),
                 ("joint_single_tag_frames", bundle.single_tag_frames),
                 ("joint_motion_prior_frames", bundle.motion_prior_frames),
                 ("joint_ippe_second_solution", bundle.ippe_second_solution),
                 ("joint_corner_rms_px", bundle.rms_px),
                 ("joint_variance_factor", bundle.variance_factor),
                 ("joint_corner_sigma_px", bundle.corner_sigma_px),
                 ("joint_rival_pairs_flipped", " ".join(
                     f"tag36h11:{i}-tag36h11:{j}" for i, j in bundle.rival_pairs_flipped))]
    elif report is not None:
        rows.append(("map_method", report.method))
    if tags is not None and "std_pos_m" in tags.columns:
        weak = tags.loc[optimize.poorly_constrained(tags), "tag_id"].astype(int)
        rows += [("tag_std_pos_m_median", float(tags["std_pos_m"].median())),
                 ("tag_std_pos_m_max", float(tags["std_pos_m"].max())),
                 ("poorly_constrained_tags", " ".join(f"tag36h11:{t}" for t in weak))]
    survey = report.survey if report is not None else None
    if survey is not None:  # the surveyed world and its residuals at the known tags
        rows += [("survey_source", survey.source), ("survey_model", survey.model),
                 ("survey_tags", " ".join(f"tag36h11:{t}" for t in survey.tags)),
                 ("survey_res_pos_rms_m", survey.res_pos_rms_m),
                 ("survey_res_pos_max_m", survey.res_pos_max_m),
                 ("survey_res_rot_rms_deg", "" if survey.res_rot_rms_deg is None
                  else survey.res_rot_rms_deg)]
    if graph is not None:
        rows.append(("weak_links", " ".join(f"tag36h11:{w.tag_i}-tag36h11:{w.tag_j}"
                                            f"({w.n_frames})" for w in graph.weak_links)))
    if traj is not None and "std_pos_m" in traj.columns and traj["std_pos_m"].notna().any():
        rows += [("frame_std_pos_m_median", float(traj["std_pos_m"].median())),
                 ("frame_std_pos_m_max", float(traj["std_pos_m"].max()))]
    if traj is not None and "shift_m" in traj.columns:
        rows += _evidence_rows(traj)
    text = "metric,value\n" + "".join(f"{k},{v}\n" for k, v in rows)
    layouts.atomic_write_text(folder / "diagnostics.csv", text)
    return True


def recording_map(get: Getter, folder: Path, dataset: str) -> bool:
    """``map.png`` of a recording: its tags and trajectory (or photos: camera views) seen from
    above, in the plane of ``report.plane``."""
    from tagtrail.io import reloc_files

    traj, tags = get("smooth", "trajectory"), get("optimize", "tag_map")
    if traj is None or tags is None or len(traj) < 2 or get("report", "summary") is not None:
        return False
    report = get("params", "report")
    plane_name = str(getattr(report, "plane", "auto"))
    P, R = poses(traj)
    plane = reference_plane(plane_name, P, R)
    flip_v = bool(plane.n @ R[:, :, 1].mean(axis=0) > 0)
    empty = pd.DataFrame({c: np.zeros(0) for c in columns("report.relocalization")})
    uv = plane.to_uv(P)
    what = "camera views" if is_photo_set(uv) else "trajectory"
    reloc_files.write_map_png(
        folder / "map.png", uv, np.zeros((0, 2)), empty,
        plane.to_uv(tags[["x_m", "y_m", "z_m"]].to_numpy()), tags["tag_id"].astype(int).tolist(),
        reloc_files.plane_axis_names(plane_name), flip_v,
        f"{dataset}: {what} and tag map (plane {plane_name}, seen from above)",
        weak_tags=optimize.poorly_constrained(tags),
        tag_std_m=tags["std_pos_m"].to_numpy(np.float64) if "std_pos_m" in tags else None,
        ref_heading_rad=plane.heading(R),
    )  # fmt: skip
    return True


def evaluation(get: Getter, folder: Path, dataset: str) -> bool:
    """``evaluation.json``: errors vs ground truth (datasets that have it)."""
    ev = get("eval", "evaluation")
    if ev is None:
        return False
    layouts.atomic_write_text(folder / "evaluation.json", pretty_json(ev.model_dump(mode="json")))
    return True


def relocalization(get: Getter, folder: Path, dataset: str) -> bool:
    """``relocalization.csv``, ``summary.json``, ``relocalization.png``, ``map.png`` (queries)."""
    reloc, summary = get("report", "relocalization"), get("report", "summary")
    q_traj, ref_traj = get("align", "trajectory"), get("smooth", "trajectory", reference=True)
    if reloc is None or summary is None or q_traj is None or ref_traj is None:
        return False
    ref_tags = get("optimize", "tag_map", reference=True)
    doc = json.loads(canonical_json(summary.model_dump(mode="json")))  # keys sorted, as stored
    reloc_files.write_outputs(folder, reloc, doc, q_traj, ref_traj, ref_tags, summary.plane)
    return True


EXPORTERS: list[Callable[[Getter, Path, str], bool]] = [
    trajectories, tag_map, diagnostics, recording_map, evaluation, relocalization,
]
