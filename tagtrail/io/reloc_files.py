"""SPEC relocalization files: ``relocalization.csv``, ``summary.json``, ``relocalization.png``,
``map.png``.

Every writer goes through :func:`tagtrail.io.layouts.atomic_write`. Plots use matplotlib's Agg
canvas directly (no pyplot state) and PNG metadata without the Software/date entries, so the same
inputs give byte-identical files.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from tagtrail.errors import SourceError, one_line
from tagtrail.geometry.reference_path import reference_plane
from tagtrail.io.layouts import atomic_write, atomic_write_text
from tagtrail.io.reloc_plots import map_figure, point_figure, timeline_figure
from tagtrail.schemas.artifacts import poses

RELOC_HEADER = [
    "stamp_sec",
    "stamp_nanosec",
    "t_rel_s",
    "nearest_ref_idx",
    "distance_m",
    "heading_error_deg",
    "query_heading_deg",
    "ref_heading_deg",
    "query_u",
    "query_v",
    "ref_u",
    "ref_v",
]
# the path tracker's columns, after the seed's (SPEC): lost is written 0/1
TRACK_HEADER = [
    "cross_track_m",
    "progress_m",
    "curvature_1pm",
    "lookahead_u",
    "lookahead_v",
    "lost",
]
_FLOATS = RELOC_HEADER[4:] + TRACK_HEADER[:-1]
_PNG_META = {"Software": None}


def relocalization_csv_text(reloc: pd.DataFrame) -> str:
    """CSV text with the SPEC header from a report.relocalization frame (``t_ns`` …)."""
    sec, nsec = np.divmod(reloc["t_ns"].to_numpy(np.int64), 1_000_000_000)
    t_rel = reloc["t_rel_s"].to_numpy(np.float64)
    idx = reloc["nearest_ref_idx"].to_numpy(np.int64)
    vals = reloc[_FLOATS].to_numpy(np.float64)
    lost = reloc["lost"].to_numpy(bool).astype(int)
    lines = [",".join(RELOC_HEADER + TRACK_HEADER)]
    for s, n, tr, k, row, lo in zip(sec, nsec, t_rel, idx, vals, lost, strict=True):
        lines.append(
            f"{s},{n},{float(tr)!r},{k}," + ",".join(repr(float(v)) for v in row) + f",{lo}"
        )
    return "\n".join(lines) + "\n"


def write_relocalization_csv(path: Path, reloc: pd.DataFrame) -> None:
    atomic_write_text(Path(path), relocalization_csv_text(reloc))


def read_relocalization_csv(path: Path) -> pd.DataFrame:
    """Read a ``relocalization.csv`` back into report.relocalization columns (``t_ns`` …); a
    file of the seed's columns only (before the tracker's) is read too."""
    try:
        df = pd.read_csv(path)
    except (OSError, ValueError) as err:
        raise SourceError(f"{path}: cannot read relocalization CSV: {one_line(err)}") from err
    if list(df.columns) not in (RELOC_HEADER, RELOC_HEADER + TRACK_HEADER):
        raise SourceError(f"{path}: not a relocalization CSV (header {list(df.columns)})")
    t_ns = df["stamp_sec"].to_numpy(np.int64) * 1_000_000_000 + df["stamp_nanosec"].to_numpy(
        np.int64
    )
    if "lost" in df.columns:
        df["lost"] = df["lost"].astype(bool)
    return pd.concat([pd.DataFrame({"t_ns": t_ns}), df.iloc[:, 2:]], axis=1)


def write_summary_json(path: Path, summary: dict[str, Any]) -> None:
    """``summary.json`` (indented, keys in SPEC order; NaN is written as null)."""

    def clean(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        if isinstance(x, float | np.floating):
            return float(x) if np.isfinite(x) else None
        if isinstance(x, np.integer):
            return int(x)
        return x

    atomic_write_text(Path(path), json.dumps(clean(summary), indent=2, allow_nan=False) + "\n")


def _save(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)
    atomic_write(Path(path), lambda tmp: fig.savefig(tmp, format="png", metadata=_PNG_META))


def write_relocalization_png(path: Path, reloc: pd.DataFrame, title: str = "") -> None:
    """``relocalization.png`` of trajectory mode: D(t) (m), phi(t) (deg), cross-track (m)."""
    _save(timeline_figure(reloc, title), path)


def write_point_png(path: Path, *args: Any, **kwargs: Any) -> None:
    """``relocalization.png`` of point mode: :func:`reloc_plots.point_figure` of ``args`` and
    ``kwargs`` (the close-up of the parked pose against the reference)."""
    _save(point_figure(*args, **kwargs), path)


def write_map_png(path: Path, *args: Any, **kwargs: Any) -> None:
    """``map.png``: :func:`reloc_plots.map_figure` of ``args`` and ``kwargs`` (the plane seen
    from above)."""
    _save(map_figure(*args, **kwargs), path)


def plane_axis_names(plane_name: str) -> tuple[str, str]:
    """The names of a plane's in-plane axes (``auto``: u, v)."""
    return {"xz": ("x", "z"), "xy": ("x", "y"), "yz": ("y", "z")}.get(plane_name, ("u", "v"))


def write_outputs(
    out: Path,
    reloc: pd.DataFrame,
    summary: dict[str, Any],
    q_traj: pd.DataFrame,
    ref_traj: pd.DataFrame,
    ref_tags: pd.DataFrame | None,
    plane_name: str,
) -> None:
    """Write SPEC's relocalization files into ``out`` (also used by the pipeline's exports)."""
    plane = reference_plane(plane_name, *poses(ref_traj))
    ref_P, ref_R = poses(ref_traj)
    names = plane_axis_names(plane_name)
    flip_v = plane.v_down(ref_R)
    d, p = summary["distance_m"], summary["abs_heading_error_deg"]
    assoc = summary.get("association")
    how = f" ({assoc} association)" if summary["mode"] == "trajectory" and assoc else ""
    title = f"{summary['mode']} mode{how}, plane {plane_name}: " + (
        f"D {d['mean']:.4f} m, phi {reloc['heading_error_deg'].iloc[0]:+.2f} deg"
        if len(reloc) == 1
        else f"D mean {d['mean']:.3f} m, |phi| mean {p['mean']:.2f} deg"
    )
    write_relocalization_csv(out / "relocalization.csv", reloc)
    write_summary_json(out / "summary.json", summary)
    q_P, q_R = poses(q_traj)
    if summary["mode"] == "point":
        write_point_png(
            out / "relocalization.png",
            reloc.iloc[0],
            plane.to_uv(ref_P),
            plane.to_uv(q_P),
            plane.heading(q_R),
            names,
            flip_v,
            title + "\nparked pose against the nearest segment",
        )
    else:
        write_relocalization_png(out / "relocalization.png", reloc, title)
    tags_uv = None if ref_tags is None else plane.to_uv(ref_tags[["x_m", "y_m", "z_m"]].to_numpy())
    write_map_png(
        out / "map.png",
        plane.to_uv(ref_P),
        plane.to_uv(q_P),
        reloc,
        tags_uv,
        [] if ref_tags is None else ref_tags["tag_id"].astype(int).tolist(),
        names,
        flip_v,
        title,
        ref_heading_rad=plane.heading(ref_R),
    )
