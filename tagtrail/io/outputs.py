"""The formats of the files in ``outputs/<dataset>/``: what a stage's ``Export`` names.

A stage declares which files it exports and makes each one's value from its artifacts (pure,
:class:`tagtrail.schemas.stage.Export`); the runner hands each (file, format, value) to
:func:`write`, which turns it into bytes here, through the atomic writers of ``layouts`` and
``reloc_files``. A format writes the one file it is given, except ``relocalization``, which
writes SPEC's ``relocalization.csv``, ``summary.json``, ``relocalization.png`` and ``map.png``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tagtrail.errors import SpecError
from tagtrail.io import layouts, reloc_files
from tagtrail.io.layouts import atomic_write_text
from tagtrail.io.reloc_plots import is_photo_set
from tagtrail.schemas.artifacts import columns

Writer = Callable[[Path, str, Any], None]  # (folder, file name, value)


def _text(make: Callable[[Any], str]) -> Writer:
    return lambda folder, name, value: atomic_write_text(folder / name, make(value))


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def metric_value_csv_text(rows: list[tuple[str, Any]]) -> str:
    """``metric,value`` rows (``diagnostics.csv``): values as Python prints them."""
    return "metric,value\n" + "".join(f"{k},{v}\n" for k, v in rows)


def json_text(doc: Any) -> str:
    """A JSON document, keys sorted, indented by 2, newline-terminated."""
    return json.dumps(doc, sort_keys=True, indent=2, default=_json_default) + "\n"


def _trajectory_csv(folder: Path, name: str, traj: pd.DataFrame) -> None:
    layouts.write_trajectory_csv(folder / name, traj)


def _trajectory_tum(folder: Path, name: str, traj: pd.DataFrame) -> None:
    layouts.write_trajectory_tum(folder / name, traj)


def _map_png(folder: Path, name: str, kwargs: dict[str, Any]) -> None:
    reloc_files.write_map_png(folder / name, **kwargs)


def _recording_map_png(folder: Path, name: str, v: dict[str, Any]) -> None:
    """A recording's ``map.png``: its trajectory (or photos: camera views) and tag map."""
    what = "camera views" if is_photo_set(v["uv"]) else "trajectory"
    empty = pd.DataFrame({c: np.zeros(0) for c in columns("report.relocalization")})
    reloc_files.write_map_png(
        folder / name,
        v["uv"],
        np.zeros((0, 2)),
        empty,
        v["tags_uv"],
        v["tag_ids"],
        reloc_files.plane_axis_names(v["plane_name"]),
        v["flip_v"],
        f"{v['dataset']}: {what} and tag map (plane {v['plane_name']}, seen from above)",
        weak_tags=v["weak_tags"],
        tag_std_m=v["tag_std_m"],
        ref_heading_rad=v["ref_heading_rad"],
    )


def _relocalization(folder: Path, name: str, kwargs: dict[str, Any]) -> None:
    reloc_files.write_outputs(folder, **kwargs)


FORMATS: dict[str, Writer] = {
    "trajectory_csv": _trajectory_csv,  # a DataFrame of t_ns + pose columns (SPEC CSV)
    "trajectory_tum": _trajectory_tum,  # the same, as TUM text
    "trajectory_std_csv": _text(layouts.trajectory_std_csv_text),
    "trajectory_evidence_csv": _text(layouts.trajectory_evidence_csv_text),
    "tag_map_yaml": _text(lambda v: layouts.tag_map_yaml_text(*v)),  # (tags, anchor_id)
    "tag_map_csv": _text(layouts.tag_map_csv_text),
    "metric_value_csv": _text(metric_value_csv_text),  # [(metric, value), ...]
    "json": _text(json_text),  # a JSON-able document
    "map_png": _map_png,  # reloc_files.write_map_png's arguments after the path
    "recording_map_png": _recording_map_png,  # see _recording_map_png
    "relocalization": _relocalization,  # reloc_files.write_outputs's arguments after the folder
}


def write(folder: Path, name: str, fmt: str, value: Any) -> None:
    """Write ``value`` as file ``name`` of ``folder`` in format ``fmt`` (one of :data:`FORMATS`)."""
    writer = FORMATS.get(fmt)
    if writer is None:
        raise SpecError(
            f"{folder / name}: unknown output format {fmt!r} (formats: {', '.join(FORMATS)})"
        )
    writer(Path(folder), name, value)
