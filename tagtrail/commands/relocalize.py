"""``tagtrail relocalize REFERENCE QUERY``: relocalization on existing files, without a pipeline.

REFERENCE and QUERY are folders (or trajectory files inside folders) in tagtrail's or the original
tool's layouts: ``trajectory.csv`` / ``trajetoria_camera.csv`` plus, for tag alignment,
``tag_map.csv`` / ``mapa_tags.csv`` / ``tag_map.yaml`` next to it. The work is done by the same
functions the pipeline runs (:func:`tagtrail.stages.align.run`, :func:`tagtrail.stages.report.run`);
this module only reads, writes and prints.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd

from tagtrail.errors import DataError, SourceError, SpecError
from tagtrail.geometry.reference_path import PLANES, PlaneName
from tagtrail.io import reloc_files
from tagtrail.io.layouts import TAG_MAP_NAMES, read_tag_map, read_trajectory
from tagtrail.schemas.artifacts import POSE_COLS
from tagtrail.stages import align as align_stage
from tagtrail.stages import report as report_stage

log = logging.getLogger(__name__)
# the choices of report.Params.mode, align.Params.align and align.Params.model
Mode = Literal["auto", "trajectory", "point"]
Align = Literal["auto", "none", "tags"]
AlignModel = Literal["similarity", "rigid", "se3", "sim3"]
Assoc = Literal["progress", "nearest"]
OUTPUT_FILES = ("relocalization.csv", "summary.json", "relocalization.png", "map.png")
EXAMPLES = """examples:
  tagtrail relocalize outputs/reference outputs/query -o reloc
  tagtrail relocalize ref/trajetoria_camera.csv query/ --mode point --plane xz
  tagtrail relocalize ref query --align none --mode trajectory
  tagtrail relocalize ref query --mode trajectory --association nearest   # the paper's Eq. 3.12
"""


def load_dataset(path: Path) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """A trajectory (folder or file) and the tag map of its folder (None when it has none)."""
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    traj = read_trajectory(path)
    if len(traj) == 0:
        raise DataError(f"{path}: the trajectory has no poses")
    folder = path if path.is_dir() else path.parent
    if not any((folder / name).is_file() for name in TAG_MAP_NAMES):
        return traj, None
    return traj, read_tag_map(folder)[0]


def _empty_tags() -> pd.DataFrame:
    return pd.DataFrame({c: pd.Series(dtype=float) for c in ["tag_id", *POSE_COLS, "n_obs"]})


def relocalize(
    reference: Path,
    query: Path,
    out: Path,
    mode: Mode = "auto",
    align: Align = "auto",
    align_model: AlignModel = "similarity",
    plane: PlaneName = "auto",
    allow_scale: bool = False,
    association: Assoc = "progress",
) -> dict[str, Any]:
    """Relocalize ``query`` against ``reference`` and write the SPEC files into ``out``.

    Returns the ``summary.json`` dict. Raises :class:`SourceError` (missing/unreadable input) or
    :class:`DataError` (no common tags with ``align="tags"``, scale out of range, …).
    """
    summary: dict[str, Any] = _relocalize(
        reference, query, out, mode, align, align_model, plane, allow_scale, association
    )["summary"]
    return summary


def _relocalize(
    reference: Path,
    query: Path,
    out: Path,
    mode: Mode,
    align: Align,
    align_model: AlignModel,
    plane: PlaneName,
    allow_scale: bool,
    association: Assoc = "progress",
) -> dict[str, Any]:
    check_out(Path(out))
    ref_traj, ref_tags = load_dataset(reference)
    q_traj, q_tags = load_dataset(query)
    if ref_tags is None or q_tags is None:
        missing = reference if ref_tags is None else query
        msg = f"{missing}: no tag map ({', '.join(TAG_MAP_NAMES)})"
        if align == "tags":
            raise DataError(f"{msg}; --align tags needs the tag maps of both datasets")
        if align == "auto":
            log.warning("%s; the query is evaluated in its own frame", msg)
    a_params = align_stage.Params(
        align=align, model=align_model, plane=plane, allow_scale=allow_scale
    )
    r_params = report_stage.Params(mode=mode, plane=plane, association=association)
    try:
        aligned = align_stage.run(
            q_tags if q_tags is not None else _empty_tags(),
            ref_tags if ref_tags is not None else _empty_tags(),
            q_traj,
            ref_traj,
            a_params,
        )
        result = report_stage.run(aligned["trajectory"], ref_traj, aligned["alignment"], r_params)
    except DataError as err:  # say which files the problem is about
        raise DataError(f"reference {reference}, query {query}: {err}") from err
    reloc, summary = result["relocalization"], result["summary"].model_dump(mode="json")
    try:
        reloc_files.write_outputs(
            Path(out), reloc, summary, aligned["trajectory"], ref_traj, ref_tags, plane
        )
    except OSError as err:
        raise SourceError(f"{out}: cannot write the outputs: {err.strerror or err}") from err
    return {**result, "summary": summary}


def check_out(out: Path) -> None:
    """Refuse an output folder that is a file (or lies under one) before any work is done."""
    for p in (out, *out.parents):
        if p.exists():
            if not p.is_dir():
                where = "is" if p == out else f"lies under {p}, which is"
                raise SpecError(
                    f"-o {out}: {where} a file, not a folder; name a folder for the "
                    "outputs (it is created if missing)"
                )
            return


def summary_text(summary: dict[str, Any], reloc: pd.DataFrame, out: Path) -> str:
    """A short human summary: D, phi, the alignment and the files written."""
    d, p, a = summary["distance_m"], summary["abs_heading_error_deg"], summary["alignment"]
    assoc = summary.get("association", "nearest")
    how = "nearest point of the path" if assoc == "polyline" else f"{assoc} association"
    lines = [
        f"relocalization: {summary['mode']} mode ({how}), plane {summary['plane']}, "
        f"n={summary['n']}"
    ]
    ref_heading = (
        "the nearest segment's heading"
        if summary.get("ref_heading") == "segment"
        else "the path's heading at the sample, by centred difference"
    )
    if summary["n"] == 1:
        phi = float(reloc["heading_error_deg"].iloc[0])
        cross = float(reloc["cross_track_m"].iloc[0])
        lines += [
            f"  D   = {d['mean']:.4f} m  (cross-track {cross:+.4f} m, > 0: left)",
            f"  phi = {phi:+.2f} deg  (against {ref_heading})",
        ]
    else:
        c = summary["cross_track_m"]
        lines += [
            f"  D    mean {d['mean']:.4f} m, median {d['median']:.4f}, p95 {d['p95']:.4f}, "
            f"max {d['max']:.4f}",
            f"  |phi| mean {p['mean']:.2f} deg, median {p['median']:.2f}, p95 {p['p95']:.2f}, "
            f"max {p['max']:.2f}  (against {ref_heading})",
            f"  cross-track mean {c['mean']:+.4f} m (> 0: left), rmse {c['rmse']:.4f}; "
            f"lost {summary['lost']} of {summary['n']}",
        ]
    if a["model"] == "none":
        lines.append(f"  alignment: none ({a['common_tags']} common tags)")
    else:
        lines.append(
            f"  alignment: {a['model']} on {a['inliers']}/{a['common_tags']} common tags, "
            f"scale {a['scale']:.4f}, rotation {a['rotation_deg']:.2f} deg, "
            f"translation {np.round(a['translation'], 4).tolist()} m, "
            f"rms {1000 * a['rms_m']:.1f} mm"
        )
    lines.append("wrote:")
    lines += [f"  {out / name}" for name in OUTPUT_FILES]
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``relocalize`` arguments to ``parser`` (returned)."""
    parser.epilog = EXAMPLES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("reference", type=Path, help="reference folder or trajectory file")
    parser.add_argument("query", type=Path, help="query folder or trajectory file")
    parser.add_argument(
        "-o",
        "--out",
        type=Path,
        default=Path("relocalization"),
        help="output folder (default: ./relocalization)",
    )
    parser.add_argument(
        "--mode",
        choices=["auto", "trajectory", "point"],
        default="auto",
        help="point = a parked robot; auto picks point when the query stays "
        "within 0.20 m (default: auto)",
    )
    parser.add_argument(
        "--align",
        choices=["auto", "none", "tags"],
        default="auto",
        help="align the query map onto the reference map with the common tags "
        "(default: auto = when there are 2 or more)",
    )
    parser.add_argument(
        "--align-model",
        choices=["similarity", "rigid", "sim3", "se3"],
        default="similarity",
        help="default: similarity",
    )
    parser.add_argument(
        "--plane",
        choices=list(PLANES),
        default="auto",
        help="plane of D and phi (default: auto, fitted to the reference)",
    )
    parser.add_argument(
        "--association",
        choices=["progress", "nearest"],
        default="progress",
        help="trajectory mode: progress = the nearest sample near the previous "
        "match (no jumps where the path crosses itself), nearest = the paper's "
        "Eq. 3.12 (default: progress)",
    )
    parser.add_argument(
        "--allow-scale", action="store_true", help="accept an alignment scale outside [0.9, 1.1]"
    )
    return parser


def build_parser() -> argparse.ArgumentParser:
    return add_arguments(
        argparse.ArgumentParser(
            prog="tagtrail relocalize",
            description="Distance D and heading error phi of a query against a reference "
            "trajectory (files of tagtrail or of the original tool).",
            epilog=EXAMPLES,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
    )


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """Run from parsed arguments (or an argv list); 0 on success, the error's exit code else."""
    from tagtrail.cli import run_command

    ns = args if isinstance(args, argparse.Namespace) else build_parser().parse_args(args)
    return run_command(lambda: _main(ns))


def _main(ns: argparse.Namespace) -> int:
    result = _relocalize(
        ns.reference,
        ns.query,
        ns.out,
        ns.mode,
        ns.align,
        ns.align_model,
        ns.plane,
        getattr(ns, "allow_scale", False),
        getattr(ns, "association", "progress"),
    )
    print(summary_text(result["summary"], result["relocalization"], Path(ns.out)))
    return 0
