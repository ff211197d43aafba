"""Versioned pyarrow schemas of the stages' table artifacts (units and frames in the names).

The runner conforms every table a stage returns to its schema before it is stored: listed
columns must be present and are cast (safely) to the listed types, so artifacts keep stable
types whatever pandas inferred; extra columns are kept after them. Bump ``VERSION`` (it enters
every cache key) when a schema changes incompatibly.
"""

from __future__ import annotations

import pandas as pd
import pyarrow as pa

VERSION = 1

I32, I64, F64 = pa.int32(), pa.int64(), pa.float64()
POSE = [("x_m", F64), ("y_m", F64), ("z_m", F64), ("qx", F64), ("qy", F64), ("qz", F64),
        ("qw", F64)]  # fmt: skip
ALT_POSE = [(f"alt_{n}", t) for n, t in POSE]
CORNERS = [(f"c{i}{a}", F64) for i in range(4) for a in "xy"]
TRAJECTORY = pa.schema([("t_ns", I64), *POSE, ("n_tags", I32)])

SCHEMAS: dict[str, pa.Schema] = {
    "extract.frames": pa.schema([("t_ns", I64), ("frame_idx", I32), ("n_det", I32)]),
    "extract.detections": pa.schema(
        [("t_ns", I64), ("frame_idx", I32), ("tag_id", I32), ("hamming", I32),
         ("decision_margin", F64), *CORNERS]  # fmt: skip
    ),
    "extract.observations": pa.schema([("t_ns", I64), ("frame_idx", I32), ("tag_id", I32), *POSE]),
    "pnp.observations": pa.schema(
        [("t_ns", I64), ("frame_idx", I32), ("tag_id", I32), ("size_m", F64), *POSE,
         ("reproj_px", F64), *ALT_POSE, ("alt_reproj_px", F64), ("ambiguity", F64)]  # fmt: skip
    ),
    "edges.edges": pa.schema(
        [("t_ns", I64), ("tag_i", I32), ("tag_j", I32), *POSE, ("weight", F64)]
    ),
    "optimize.tag_map": pa.schema(
        [("tag_id", I32), *POSE, ("n_obs", I64), ("size_m", F64), ("res_t_rms_m", F64),
         ("res_r_rms_deg", F64)]  # fmt: skip
    ),
    "optimize.edge_residuals": pa.schema(
        [("tag_i", I32), ("tag_j", I32), ("t_ns", I64), ("res_t_m", F64), ("res_r_deg", F64)]
    ),
    "trajectory.trajectory": TRAJECTORY,
    "smooth.trajectory": TRAJECTORY,
    "align.trajectory": TRAJECTORY,
    "report.relocalization": pa.schema(
        [("t_ns", I64), ("t_rel_s", F64), ("nearest_ref_idx", I64), ("distance_m", F64),
         ("heading_error_deg", F64), ("query_heading_deg", F64), ("ref_heading_deg", F64),
         ("query_u", F64), ("query_v", F64), ("ref_u", F64), ("ref_v", F64)]  # fmt: skip
    ),
}


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
    return pa.Table.from_arrays(
        cols + [table[c] for c in extra], names=schema.names + extra
    )
