"""Versioned pyarrow schemas of the stages' table artifacts (units and frames in the names).

The runner conforms every table a stage returns to its schema before it is stored: listed
columns must be present and are cast (safely) to the listed types, so artifacts keep stable
types whatever pandas inferred; extra columns are kept after them. Bump ``VERSION`` (it enters
every cache key) when a schema changes incompatibly.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
from numpy.typing import NDArray

from tagtrail.geometry.joint.problem import CornerRows
from tagtrail.geometry.se3 import R_from_quat_xyzw, T_from_xyz_quat
from tagtrail.geometry.tagmap import EdgeSet, Sightings

VERSION = 4

I32, I64, F64 = pa.int32(), pa.int64(), pa.float64()
POSE = [
    ("x_m", F64),
    ("y_m", F64),
    ("z_m", F64),
    ("qx", F64),
    ("qy", F64),
    ("qz", F64),
    ("qw", F64),
]
ALT_POSE = [(f"alt_{n}", t) for n, t in POSE]
CORNERS = [(f"c{i}{a}", F64) for i in range(4) for a in "xy"]
TRAJECTORY = pa.schema([("t_ns", I64), *POSE, ("n_tags", I32)])

SCHEMAS: dict[str, pa.Schema] = {
    "extract.frames": pa.schema(
        [("t_ns", I64), ("frame_idx", I32), ("n_det", I32), ("timed", pa.bool_())]
    ),
    "extract.detections": pa.schema(
        [
            ("t_ns", I64),
            ("frame_idx", I32),
            ("tag_id", I32),
            ("hamming", I32),
            ("decision_margin", F64),
            *CORNERS,
        ]
    ),
    "extract.observations": pa.schema([("t_ns", I64), ("frame_idx", I32), ("tag_id", I32), *POSE]),
    # wheel odometry, one row per nav_msgs/Odometry message in bag order: header stamp (the
    # host's publication time on the LIMO), odom_T_base, the twist (base frame), and the pose
    # covariance's x, y, yaw variances -- NaN where unusable (stages.extract.odometry_table)
    "extract.odometry": pa.schema(
        [
            ("t_ns", I64),
            *POSE,
            ("vx_mps", F64),
            ("vy_mps", F64),
            ("wz_rps", F64),
            ("var_x_m2", F64),
            ("var_y_m2", F64),
            ("var_yaw_rad2", F64),
        ]
    ),
    "pnp.observations": pa.schema(
        [
            ("t_ns", I64),
            ("frame_idx", I32),
            ("tag_id", I32),
            ("size_m", F64),
            *POSE,
            ("reproj_px", F64),
            *ALT_POSE,
            ("alt_reproj_px", F64),
            ("ambiguity", F64),
        ]
    ),
    "edges.edges": pa.schema(
        [("t_ns", I64), ("tag_i", I32), ("tag_j", I32), *POSE, ("weight", F64), ("hypothesis", I32)]
    ),
    "optimize.tag_map": pa.schema(
        [
            ("tag_id", I32),
            *POSE,
            ("n_obs", I64),
            ("size_m", F64),
            ("res_t_rms_m", F64),
            ("res_r_rms_deg", F64),
            ("std_pos_m", F64),
            ("std_rot_deg", F64),
        ]
    ),
    "optimize.edge_residuals": pa.schema(
        [("tag_i", I32), ("tag_j", I32), ("t_ns", I64), ("res_t_m", F64), ("res_r_deg", F64)]
    ),
    "trajectory.trajectory": TRAJECTORY,
    "smooth.trajectory": TRAJECTORY,
    "align.trajectory": TRAJECTORY,
    "report.relocalization": pa.schema(
        [
            ("t_ns", I64),
            ("t_rel_s", F64),
            ("nearest_ref_idx", I64),
            ("distance_m", F64),
            ("heading_error_deg", F64),
            ("query_heading_deg", F64),
            ("ref_heading_deg", F64),
            ("query_u", F64),
            ("query_v", F64),
            ("ref_u", F64),
            ("ref_v", F64),
            ("cross_track_m", F64),
            ("progress_m", F64),
            ("curvature_1pm", F64),
            ("lookahead_u", F64),
            ("lookahead_v", F64),
            ("lost", pa.bool_()),
        ]
    ),
}


POSE_COLS = [n for n, _ in POSE]  # a pose: position (m) and quaternion (qx, qy, qz, qw)
ALT_POSE_COLS = [n for n, _ in ALT_POSE]  # pnp's second IPPE solution
CORNER_COLS = [n for n, _ in CORNERS]  # c0x, c0y, ..., c3x, c3y (px)
STD_COLS = ["std_pos_m", "std_rot_deg"]  # a tag's or frame's standard deviation, when known
# a trajectory frame's evidence (geometry.joint.FrameEvidence), when the trajectory carries it
EVIDENCE_COLS = ["reproj_px", "alone_reproj_px", "shift_m", "shift_deg", "shift_sigma"]
ALONE_POSE_COLS = [f"alone_{n}" for n in POSE_COLS]  # the frame on its own corners (world_T_cam)


def per_frame(traj: pd.DataFrame) -> pd.DataFrame:
    """A trajectory table with each frame's own pose (its ``ALONE_POSE_COLS``, when it has
    them) as its pose: the trajectory before any temporal step."""
    if not all(c in traj.columns for c in ALONE_POSE_COLS):
        return traj
    return traj.drop(columns=POSE_COLS).rename(
        columns=dict(zip(ALONE_POSE_COLS, POSE_COLS, strict=True))
    )


def columns(name: str) -> list[str]:
    """The column names of artifact ``name`` (``stage.output``), in order."""
    return list(SCHEMAS[name].names)


def ippe_solutions(
    obs: pd.DataFrame,
) -> tuple[
    NDArray[np.float64],
    NDArray[np.float64] | None,
    NDArray[np.float64] | None,
    NDArray[np.float64] | None,
]:
    """(pose, alt_pose, reproj_px, alt_reproj_px) arrays of ``pnp.observations`` rows, for
    :func:`tagtrail.geometry.ippe.best_pose`; the alternative is None where it is absent."""
    pose = obs[POSE_COLS].to_numpy(np.float64)
    if not all(c in obs.columns for c in [*ALT_POSE_COLS, "reproj_px", "alt_reproj_px"]):
        return pose, None, None, None
    return (
        pose,
        obs[ALT_POSE_COLS].to_numpy(np.float64),
        obs["reproj_px"].to_numpy(np.float64),
        obs["alt_reproj_px"].to_numpy(np.float64),
    )


def poses(traj: pd.DataFrame) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Positions ``(N, 3)`` (m) and rotations ``(N, 3, 3)`` of a table of poses (a trajectory's
    world_T_cam, a tag map's world_T_tag)."""
    P = traj[POSE_COLS[:3]].to_numpy(np.float64)
    return P, R_from_quat_xyzw(traj[POSE_COLS[3:]].to_numpy(np.float64))


def conform(name: str, df: pd.DataFrame) -> pa.Table:
    """``df`` as a table of the schema of ``name`` (``stage.output``), extra columns after.

    Raises ``TypeError`` naming the artifact when listed columns are missing or cannot be cast.
    """
    table = pa.Table.from_pandas(df, preserve_index=False)
    schema = SCHEMAS.get(name)
    if schema is None:
        return table
    missing = [f.name for f in schema if f.name not in table.column_names]
    if missing:
        raise TypeError(f"artifact {name} lacks columns {missing} (schema v{VERSION})")
    try:
        cols = [table[f.name].cast(f.type) for f in schema]
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as err:
        raise TypeError(f"artifact {name} does not fit its schema: {err}") from err
    extra = [c for c in table.column_names if c not in schema.names]
    return pa.Table.from_arrays(cols + [table[c] for c in extra], names=schema.names + extra)


def timed(frames: pd.DataFrame | None) -> bool:
    """Whether ``extract.frames`` stamps are capture times (an image folder without stamps.csv
    has only its files' order: no motion links its frames)."""
    return frames is None or "timed" not in frames.columns or bool(frames["timed"].all())


def corner_rows(
    observations: pd.DataFrame, detections: pd.DataFrame, tags: NDArray[np.int64]
) -> pd.DataFrame:
    """``pnp.observations`` rows of the mapped ``tags`` joined with their corners
    (``CORNER_COLS``), with a finite pose and size; one row per (frame, tag) -- a tag seen
    twice in a frame is ambiguous and left out -- in (time, frame, tag) order."""
    obs = observations[observations["tag_id"].isin(tags)]
    obs = obs[~obs.duplicated(["frame_idx", "tag_id"], keep=False)]
    det = detections.drop_duplicates(["frame_idx", "tag_id"], keep=False)
    m = obs.merge(det[["frame_idx", "tag_id", *CORNER_COLS]], on=["frame_idx", "tag_id"])
    m = m[
        np.isfinite(m[CORNER_COLS].to_numpy(np.float64)).all(axis=1)
        & np.isfinite(m[POSE_COLS].to_numpy(np.float64)).all(axis=1)
    ]
    m = m[np.isfinite(m["size_m"].to_numpy(np.float64)) & (m["size_m"] > 0)]
    out: pd.DataFrame = m.sort_values(["t_ns", "frame_idx", "tag_id"], kind="stable")
    return out.reset_index(drop=True)


def both_solutions(rows: pd.DataFrame) -> NDArray[np.float64]:
    """``cam_T_tag`` ``(N, 2, 4, 4)``: both IPPE solutions of ``pnp.observations`` rows, the
    lower-reprojection one first (the second NaN where the source gave one pose)."""
    pose, alt, err, alt_err = ippe_solutions(rows)
    out = np.full((len(rows), 2, 4, 4), np.nan)
    out[:, 0] = T_from_xyz_quat(pose[:, :3], pose[:, 3:])
    if alt is not None and err is not None and alt_err is not None:
        ok = np.isfinite(alt).all(axis=1)
        out[ok, 1] = T_from_xyz_quat(alt[ok, :3], alt[ok, 3:])
        swap = ok & (alt_err < err)
        out[swap] = out[swap][:, ::-1]
    return out


def corner_arrays(rows: pd.DataFrame) -> CornerRows:
    """:func:`corner_rows` as the joint solve's arrays (:class:`CornerRows`)."""
    return CornerRows(
        rows["frame_idx"].to_numpy(np.int64),
        rows["t_ns"].to_numpy(np.int64),
        rows["tag_id"].to_numpy(np.int64),
        rows[CORNER_COLS].to_numpy(np.float64).reshape(-1, 4, 2),
        rows["size_m"].to_numpy(np.float64),
        both_solutions(rows),
    )


def edge_arrays(edges: pd.DataFrame, tags: NDArray[np.int64]) -> EdgeSet:
    """``edges.edges`` over the sorted tag ids ``tags`` as arrays (no ``hypothesis``: all 0)."""
    hyp = edges["hypothesis"] if "hypothesis" in edges.columns else np.zeros(len(edges))
    return EdgeSet(
        tags,
        edges["tag_i"].to_numpy(np.int64),
        edges["tag_j"].to_numpy(np.int64),
        edges["t_ns"].to_numpy(np.int64),
        edges[POSE_COLS].to_numpy(np.float64),
        edges["weight"].to_numpy(np.float64),
        np.asarray(hyp, dtype=np.int64),
    )


def sightings(observations: pd.DataFrame, tags: NDArray[np.int64]) -> Sightings:
    """``pnp.observations`` of the ``tags`` as arrays, a tag seen twice at one stamp left out."""
    obs = observations[observations["tag_id"].isin(tags).to_numpy()]
    obs = obs[~obs.duplicated(["t_ns", "tag_id"], keep=False).to_numpy()]
    return Sightings(
        obs["t_ns"].to_numpy(np.int64),
        obs["tag_id"].to_numpy(np.int64),
        obs["frame_idx"].to_numpy(np.int64),
        both_solutions(obs),
    )
