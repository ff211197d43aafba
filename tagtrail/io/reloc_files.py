"""SPEC relocalization files: ``relocalization.csv``, ``summary.json``, ``relocalization.png``,
``map.png``.

Every writer goes through :func:`tagtrail.io.layouts.atomic_write`. Plots use matplotlib's Agg
canvas directly (no pyplot state) and PNG metadata without the Software/date entries, so the same
inputs give byte-identical files.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import ArrayLike

from tagtrail.errors import SourceError, one_line
from tagtrail.geometry.reference_path import reference_plane
from tagtrail.io.layouts import atomic_write, atomic_write_text
from tagtrail.schemas.artifacts import poses

RELOC_HEADER = [
    "stamp_sec", "stamp_nanosec", "t_rel_s", "nearest_ref_idx", "distance_m",
    "heading_error_deg", "query_heading_deg", "ref_heading_deg", "query_u", "query_v",
    "ref_u", "ref_v",
]  # fmt: skip
# the path tracker's columns, after the seed's (SPEC): lost is written 0/1
TRACK_HEADER = ["cross_track_m", "progress_m", "curvature_1pm", "lookahead_u", "lookahead_v",
                "lost"]  # fmt: skip
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
        lines.append(f"{s},{n},{float(tr)!r},{k}," + ",".join(repr(float(v)) for v in row)
                     + f",{lo}")
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
    """``relocalization.png``: D(t) (m) and phi(t) (deg) against ``t_rel_s``."""
    fig = Figure(figsize=(8.0, 5.0), dpi=100, layout="constrained")
    ax_d, ax_p = fig.subplots(2, 1, sharex=True)
    t = reloc["t_rel_s"].to_numpy(np.float64)
    style = {"marker": "o", "markersize": 3} if len(t) < 50 else {}
    ax_d.plot(t, reloc["distance_m"].to_numpy(np.float64), color="tab:blue", **style)
    ax_p.plot(t, reloc["heading_error_deg"].to_numpy(np.float64), color="tab:orange", **style)
    ax_p.axhline(0.0, color="0.6", linewidth=0.8)
    if len(t) == 1:  # point mode: one value each, say it in words too
        d, p = float(reloc["distance_m"].iloc[0]), float(reloc["heading_error_deg"].iloc[0])
        ax_d.annotate(f"D = {d:.4f} m", (t[0], d), xytext=(8, 0), textcoords="offset points")
        ax_p.annotate(f"phi = {p:+.2f} deg", (t[0], p), xytext=(8, 0), textcoords="offset points")
    ax_d.set_ylabel("D [m]")
    ax_p.set_ylabel("phi [deg]")
    ax_p.set_xlabel("time since the query's first pose [s]")
    for ax in (ax_d, ax_p):
        ax.grid(alpha=0.3)
    ax_d.set_title(title or "distance and heading error to the reference")
    _save(fig, path)


def write_map_png(
    path: Path,
    ref_uv: ArrayLike,
    query_uv: ArrayLike,
    reloc: pd.DataFrame,
    tags_uv: ArrayLike | None = None,
    tag_ids: Sequence[int] = (),
    axis_names: tuple[str, str] = ("u", "v"),
    flip_v: bool = False,
    title: str = "",
    weak_tags: ArrayLike | None = None,
    tag_std_m: ArrayLike | None = None,
) -> None:
    """``map.png``: the plane seen from above, (u, v) in m.

    ``ref_uv (N, 2)`` reference path; ``query_uv (M, 2)`` every (aligned) query pose; ``reloc``
    the report rows (evaluated poses, headings, nearest reference points → links); ``tags_uv
    (K, 2)`` with ``tag_ids``; ``weak_tags (K,)`` (bool) are drawn apart as poorly constrained,
    labelled with their position standard deviation ``tag_std_m (K,)``. ``flip_v`` draws v
    downwards (when the normal points down, so that the picture is seen from above rather than
    from below).
    """
    ref = np.asarray(ref_uv, dtype=np.float64).reshape(-1, 2)
    qry = np.asarray(query_uv, dtype=np.float64).reshape(-1, 2)
    pq = reloc[["query_u", "query_v"]].to_numpy(np.float64)
    pr = reloc[["ref_u", "ref_v"]].to_numpy(np.float64)
    fig = Figure(figsize=(7.5, 6.5), dpi=100, layout="constrained")
    ax = fig.subplots()
    ax.plot(ref[:, 0], ref[:, 1], color="black", linewidth=1.8, label="reference path", zorder=2)
    ax.plot(*ref[0], marker="^", color="green", markersize=8, linestyle="", label="start")
    ax.plot(*ref[-1], marker="x", color="black", markersize=8, linestyle="", label="end")
    if tags_uv is not None and len(tag_ids):
        tags = np.asarray(tags_uv, dtype=np.float64).reshape(-1, 2)
        weak = (np.zeros(len(tags), bool) if weak_tags is None
                else np.asarray(weak_tags, bool).reshape(-1))
        std = (np.full(len(tags), np.nan) if tag_std_m is None
               else np.asarray(tag_std_m, np.float64).reshape(-1))
        ax.scatter(tags[~weak, 0], tags[~weak, 1], marker="s", s=24, color="tab:orange",
                   label="tags")
        if weak.any():
            ax.scatter(tags[weak, 0], tags[weak, 1], marker="s", s=40, facecolors="none",
                       edgecolors="tab:red", linewidths=1.5, label="poorly constrained tags")
        for (u, v), k, w, sd in zip(tags, tag_ids, weak, std, strict=True):
            text = f"{k} (±{100 * sd:.1f} cm)" if w and np.isfinite(sd) else str(k)
            ax.annotate(text, (u, v), xytext=(0, 5), textcoords="offset points",
                        ha="center", fontsize=7, color="tab:red" if w else "#3a4a6a")
    ax.scatter(qry[:, 0], qry[:, 1], s=6, color="tab:blue", alpha=0.5, label="query poses")
    step = max(1, len(pq) // 120)
    links = np.stack([pq[::step], pr[::step]], axis=1)  # (L, 2, 2)
    for a, b in links:
        ax.plot([a[0], b[0]], [a[1], b[1]], color="tab:red", linewidth=0.8, alpha=0.6, zorder=1)
    span = float(np.ptp(np.vstack([ref, qry]), axis=0).max()) or 1.0
    every = max(1, len(pq) // 30)  # heading arrows: query (blue) and reference (red)
    hq = np.radians(reloc["query_heading_deg"].to_numpy(np.float64))[::every]
    hr = np.radians(reloc["ref_heading_deg"].to_numpy(np.float64))[::every]
    arrow = 0.08 * span
    for p, h, color in ((pq[::every], hq, "tab:blue"), (pr[::every], hr, "tab:red")):
        ax.quiver(p[:, 0], p[:, 1], np.cos(h) * arrow, np.sin(h) * arrow, angles="xy",
                  scale_units="xy", scale=1, color=color, width=0.004)  # fmt: skip
    if len(pq) == 1:
        ax.plot(*pq[0], marker="o", color="tab:blue", markersize=9, label="query (point)")
        ax.plot(*pr[0], marker="o", color="tab:red", markersize=7, label="nearest on reference")
    ax.set_aspect("equal", adjustable="datalim")
    if flip_v:
        ax.invert_yaxis()
    ax.set_xlabel(f"{axis_names[0]} [m]")
    ax.set_ylabel(f"{axis_names[1]} [m]" + (" (pointing down: seen from above)" if flip_v else ""))
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title or "reference path and query (seen from above)")
    _save(fig, path)


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
    names = {"xz": ("x", "z"), "xy": ("x", "y"), "yz": ("y", "z")}.get(plane_name, ("u", "v"))
    # v is drawn downwards when the normal points along the cameras' "down" (seen from above)
    flip_v = bool(plane.n @ ref_R[:, :, 1].mean(axis=0) > 0)
    d, p = summary["distance_m"], summary["abs_heading_error_deg"]
    title = f"{summary['mode']} mode, plane {plane_name}: " + (
        f"D {d['mean']:.4f} m, phi {reloc['heading_error_deg'].iloc[0]:+.2f} deg"
        if len(reloc) == 1
        else f"D mean {d['mean']:.3f} m, |phi| mean {p['mean']:.2f} deg"
    )
    write_relocalization_csv(out / "relocalization.csv", reloc)
    write_summary_json(out / "summary.json", summary)
    write_relocalization_png(out / "relocalization.png", reloc, title)
    tags_uv = None if ref_tags is None else plane.to_uv(ref_tags[["x_m", "y_m", "z_m"]].to_numpy())
    write_map_png(
        out / "map.png", plane.to_uv(ref_P), plane.to_uv(poses(q_traj)[0]), reloc,
        tags_uv, [] if ref_tags is None else ref_tags["tag_id"].astype(int).tolist(),
        names, flip_v, title,
    )  # fmt: skip
