"""The relocalization pictures: ``map.png`` (the plane from above) and ``relocalization.png``.

``map.png``: tags, the reference and the query in the plane of ``report.plane`` (axes named after
it), seen from above (v drawn downwards when the normal points along the cameras' "down"). A
reference that is a set of separate photos rather than a recorded path (:func:`is_photo_set`) is
drawn as camera views — a dot and a viewing direction per photo, numbered — not as a connected
path. ``relocalization.png``: in trajectory mode D(t), phi(t) and the signed cross-track error;
in point mode (a parked robot) a close-up from above: the query samples and their spread, the
parked pose (median) and its heading, the nearest reference point and segment with its heading,
and the D segment between them. Legends list only what is drawn.

The ``*_figure`` functions return the matplotlib :class:`~matplotlib.figure.Figure` (tests read
its artists); the writers in :mod:`tagtrail.io.reloc_files` save it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from numpy.typing import ArrayLike

#: A reference whose median step between consecutive camera positions exceeds this share of its
#: extent is a set of photos, not a path. Measured: a robot recording at 10-30 Hz steps 0.3-2 %
#: of its extent (the demo's 0.3 %); the FRC field photos 14 %, the hand-held photos of a room
#: (swatbotics, 72 photos 0.8 m apart on a 4.7 m room) 18 %.
PHOTO_STEP_SHARE = 0.05


def is_photo_set(uv: ArrayLike) -> bool:
    """True when planar camera positions ``(N, 2)`` (m) in time order are separate photos: fewer
    than 3, or consecutive ones apart by a median of more than :data:`PHOTO_STEP_SHARE` of the
    positions' extent."""
    p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(p) < 3:
        return len(p) > 0
    extent = float(np.ptp(p, axis=0).max())
    if extent <= 0:
        return False
    return float(np.median(np.hypot(*np.diff(p, axis=0).T))) > PHOTO_STEP_SHARE * extent


def _arrows(
    ax: Axes, p: np.ndarray, heading: np.ndarray, length: float, color: str, width: float = 0.004
) -> None:
    ax.quiver(
        p[:, 0],
        p[:, 1],
        np.cos(heading) * length,
        np.sin(heading) * length,
        angles="xy",
        scale_units="xy",
        scale=1,
        color=color,
        width=width,
    )


def _plane_axes(ax: Axes, axis_names: tuple[str, str], flip_v: bool) -> None:
    """The plane's axes named, v drawn downwards with ``flip_v`` (seen from above), a grid."""
    if flip_v:
        ax.invert_yaxis()
    ax.set_xlabel(f"{axis_names[0]} [m]")
    ax.set_ylabel(f"{axis_names[1]} [m]" + (" (pointing down: seen from above)" if flip_v else ""))
    ax.grid(alpha=0.3)


def _dot(ax: Axes, p: np.ndarray, color: str, size: float, label: str, **kw: Any) -> None:
    """One labelled point ``p (2,)``."""
    ax.plot(*p, marker="o", color=color, markersize=size, linestyle="", label=label, **kw)


def map_figure(
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
    ref_heading_rad: ArrayLike | None = None,
    photos: bool | None = None,
) -> Figure:
    """``map.png``'s figure: the plane seen from above, (u, v) in m.

    ``ref_uv (N, 2)`` reference path (or photos: drawn as separate camera views with their
    headings ``ref_heading_rad (N,)``; ``photos`` None = decided by :func:`is_photo_set`);
    ``query_uv (M, 2)`` every (aligned) query pose; ``reloc`` the report rows (evaluated poses,
    headings, nearest reference points → links); ``tags_uv (K, 2)`` with ``tag_ids``;
    ``weak_tags (K,)`` (bool) are drawn apart as poorly constrained, labelled with their position
    standard deviation ``tag_std_m (K,)``. ``flip_v`` draws v downwards (when the normal points
    down, so that the picture is seen from above rather than from below)."""
    ref = np.asarray(ref_uv, dtype=np.float64).reshape(-1, 2)
    qry = np.asarray(query_uv, dtype=np.float64).reshape(-1, 2)
    pq = reloc[["query_u", "query_v"]].to_numpy(np.float64)
    pr = reloc[["ref_u", "ref_v"]].to_numpy(np.float64)
    photos = is_photo_set(ref) if photos is None else photos
    fig = Figure(figsize=(7.5, 6.5), dpi=100, layout="constrained")
    ax = fig.subplots()
    span = float(np.ptp(np.vstack([ref, qry]), axis=0).max()) if len(ref) + len(qry) else 1.0
    span = span or 1.0
    if photos:
        ax.plot(
            ref[:, 0],
            ref[:, 1],
            marker="o",
            color="black",
            markersize=5,
            linestyle="",
            label=f"camera views ({len(ref)} photos; #: file order)",
            zorder=3,
        )
        if ref_heading_rad is not None:
            h = np.asarray(ref_heading_rad, dtype=np.float64).reshape(-1)
            _arrows(ax, ref, h, 0.06 * span, "black")
        for i, (u, v) in enumerate(ref):
            ax.annotate(
                f"#{i + 1}",
                (u, v),
                xytext=(4, -9),
                textcoords="offset points",
                fontsize=7,
                color="0.3",
            )
    elif len(ref):
        ax.plot(
            ref[:, 0], ref[:, 1], color="black", linewidth=1.8, label="reference path", zorder=2
        )
        ax.plot(*ref[0], marker="^", color="green", markersize=8, linestyle="", label="start")
        ax.plot(*ref[-1], marker="x", color="black", markersize=8, linestyle="", label="end")
    if tags_uv is not None and len(tag_ids):
        tags = np.asarray(tags_uv, dtype=np.float64).reshape(-1, 2)
        weak = (
            np.zeros(len(tags), bool)
            if weak_tags is None
            else np.asarray(weak_tags, bool).reshape(-1)
        )
        std = (
            np.full(len(tags), np.nan)
            if tag_std_m is None
            else np.asarray(tag_std_m, np.float64).reshape(-1)
        )
        if (~weak).any():
            ax.scatter(
                tags[~weak, 0], tags[~weak, 1], marker="s", s=24, color="tab:orange", label="tags"
            )
        if weak.any():
            ax.scatter(
                tags[weak, 0],
                tags[weak, 1],
                marker="s",
                s=40,
                facecolors="none",
                edgecolors="tab:red",
                linewidths=1.5,
                label="poorly constrained tags",
            )
        for (u, v), k, w, sd in zip(tags, tag_ids, weak, std, strict=True):
            text = f"{k} (±{100 * sd:.1f} cm)" if w and np.isfinite(sd) else str(k)
            ax.annotate(
                text,
                (u, v),
                xytext=(0, 5),
                textcoords="offset points",
                ha="center",
                fontsize=7,
                color="tab:red" if w else "#3a4a6a",
            )
    if len(pq) == 1:  # a parked query: its samples, its pose and the nearest reference point
        if len(qry):
            ax.scatter(
                qry[:, 0], qry[:, 1], s=6, color="tab:blue", alpha=0.5, label="query samples"
            )
        _dot(ax, pq[0], "tab:blue", 9, "query (parked, median)")
        _dot(ax, pr[0], "tab:red", 7, "nearest on reference")
    elif len(qry):
        ax.scatter(qry[:, 0], qry[:, 1], s=6, color="tab:blue", alpha=0.5, label="query poses")
    if len(pq):
        step = max(1, len(pq) // 120)
        for i, (a, b) in enumerate(np.stack([pq[::step], pr[::step]], axis=1)):
            ax.plot(
                [a[0], b[0]],
                [a[1], b[1]],
                color="tab:red",
                linewidth=0.8,
                alpha=0.6,
                zorder=1,
                label="D (to the reference)" if i == 0 else None,
            )
        every = max(1, len(pq) // 30)  # heading arrows: query (blue) and reference (red)
        hq = np.radians(reloc["query_heading_deg"].to_numpy(np.float64))[::every]
        hr = np.radians(reloc["ref_heading_deg"].to_numpy(np.float64))[::every]
        _arrows(ax, pq[::every], hq, 0.08 * span, "tab:blue")
        _arrows(ax, pr[::every], hr, 0.08 * span, "tab:red")
    ax.set_aspect("equal", adjustable="datalim")
    _plane_axes(ax, axis_names, flip_v)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)
    ax.set_title(title or "reference path and query (seen from above)")
    return fig


def timeline_figure(reloc: pd.DataFrame, title: str = "") -> Figure:
    """Trajectory mode: D(t) (m), phi(t) (deg) and the signed cross-track error (m)."""
    fig = Figure(figsize=(8.0, 6.5), dpi=100, layout="constrained")
    ax_d, ax_c, ax_p = fig.subplots(3, 1, sharex=True)
    t = reloc["t_rel_s"].to_numpy(np.float64)
    style = {"marker": "o", "markersize": 3} if len(t) < 50 else {}
    ax_d.plot(t, reloc["distance_m"].to_numpy(np.float64), color="tab:blue", **style)
    ax_c.plot(t, reloc["cross_track_m"].to_numpy(np.float64), color="tab:green", **style)
    ax_p.plot(t, reloc["heading_error_deg"].to_numpy(np.float64), color="tab:orange", **style)
    lost = reloc["lost"].to_numpy(bool)
    if lost.any():  # where the association had no match within lost_m, or re-acquired
        ax_d.plot(
            t[lost],
            reloc["distance_m"].to_numpy(np.float64)[lost],
            "x",
            color="tab:red",
            label="lost / re-acquired",
        )
        ax_d.legend(loc="best", fontsize=8)
    for ax in (ax_c, ax_p):
        ax.axhline(0.0, color="0.6", linewidth=0.8)
    ax_d.set_ylabel("D [m]")
    ax_c.set_ylabel("cross-track [m]\n(> 0: left)")
    ax_p.set_ylabel("phi [deg]")
    ax_p.set_xlabel("time since the query's first pose [s]")
    for ax in (ax_d, ax_c, ax_p):
        ax.grid(alpha=0.3)
    ax_d.set_title(title or "distance and heading error to the reference")
    return fig


def point_figure(
    row: pd.Series,
    ref_uv: ArrayLike,
    query_uv: ArrayLike,
    query_heading_rad: ArrayLike,
    axis_names: tuple[str, str] = ("u", "v"),
    flip_v: bool = False,
    title: str = "",
) -> Figure:
    """Point mode: a close-up from above of the parked pose against the reference.

    ``row``: the one report row (``nearest_ref_idx`` = the segment ``[k, k+1]``); ``ref_uv
    (N, 2)`` the reference; ``query_uv (M, 2)``, ``query_heading_rad (M,)`` every sample of the
    (aligned) parked query."""
    ref = np.asarray(ref_uv, dtype=np.float64).reshape(-1, 2)
    qry = np.asarray(query_uv, dtype=np.float64).reshape(-1, 2)
    hq_all = np.asarray(query_heading_rad, dtype=np.float64).reshape(-1)
    pq = np.array([row["query_u"], row["query_v"]], dtype=np.float64)
    pr = np.array([row["ref_u"], row["ref_v"]], dtype=np.float64)
    d, phi = float(row["distance_m"]), float(row["heading_error_deg"])
    k = int(row["nearest_ref_idx"])
    radius = np.hypot(*(qry - pq).T) if len(qry) else np.zeros(1)
    r95 = float(np.percentile(radius, 95))
    dev = np.degrees(np.angle(np.exp(1j * (hq_all - np.radians(row["query_heading_deg"])))))
    h95 = float(np.percentile(np.abs(dev), 95)) if len(dev) else 0.0
    half = max(1.6 * d, 6 * r95, 0.25)
    centre = (pq + pr) / 2
    fig = Figure(figsize=(10.5, 6.5), dpi=100, layout="constrained")
    ax = fig.subplots()
    ax.plot(ref[:, 0], ref[:, 1], color="black", linewidth=1.5, label="reference path", zorder=2)
    seen = np.all(np.abs(ref - centre) <= half, axis=1)
    if 0 < seen.sum() <= 60:  # the samples, where they are few enough to tell apart
        ax.plot(ref[seen, 0], ref[seen, 1], "o", color="black", markersize=2.5, zorder=2)
    seg = ref[k : k + 2]
    ax.plot(
        seg[:, 0],
        seg[:, 1],
        color="tab:orange",
        linewidth=4,
        alpha=0.8,
        zorder=3,
        label=f"nearest segment (samples {k}, {k + 1})",
    )
    if len(qry):
        ax.scatter(
            qry[:, 0],
            qry[:, 1],
            s=10,
            color="tab:blue",
            alpha=0.35,
            zorder=4,
            label=f"query samples (n={len(qry)})",
        )
    ax.add_patch(
        Circle(
            tuple(pq),
            r95,
            fill=False,
            linestyle=":",
            color="tab:blue",
            zorder=4,
            label=f"spread: p95 radius {1000 * r95:.1f} mm, heading ±{h95:.2f} deg",
        )
    )
    ax.plot(
        [pq[0], pr[0]],
        [pq[1], pr[1]],
        "--",
        color="tab:red",
        linewidth=1.5,
        zorder=5,
        label=f"D = {d:.4f} m (cross-track {float(row['cross_track_m']):+.4f} m, > 0: left)",
    )
    _dot(ax, pq, "tab:blue", 10, "parked pose (median position)", zorder=6)
    _dot(ax, pr, "tab:red", 8, "nearest point of the reference", zorder=6)
    arrow = 0.45 * half
    hq, hr = np.radians(row["query_heading_deg"]), np.radians(row["ref_heading_deg"])
    for p, h, color, name in (
        (pq, hq, "tab:blue", "query heading (circular mean)"),
        (pr, hr, "tab:orange", "segment heading"),
    ):
        ax.annotate(
            "",
            xy=(p[0] + arrow * np.cos(h), p[1] + arrow * np.sin(h)),
            xytext=tuple(p),
            arrowprops={"arrowstyle": "-|>", "color": color, "lw": 2},
            zorder=7,
        )
        ax.plot(
            [], [], color=color, marker=">", linewidth=2, label=f"{name} {np.degrees(h):+.2f} deg"
        )
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect("equal", adjustable="box")
    _plane_axes(ax, axis_names, flip_v)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, borderaxespad=0)
    ax.set_title(
        title or f"parked pose: D {d:.4f} m, phi {phi:+.2f} deg (vs the segment)", fontsize=10
    )
    return fig
