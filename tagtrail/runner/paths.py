"""Where tagtrail writes and deletes, checked before any work.

The rule (README, "What tagtrail guarantees"): tagtrail writes only below the top folders
``outputs/``, ``artifacts/`` and ``sweeps/`` next to the pipeline file (and a file you name). A
top folder may be a symlink you made (``artifacts/`` on a bigger disk): it is then the project's
own, provided it leads to an existing folder that neither holds the project nor overlaps another
top folder. Below a top folder, no path tagtrail writes or deletes may be a symlink (one leading
out of it would take a write or a delete elsewhere; one leading nowhere fails the write; one
leading to another of tagtrail's paths makes two of them one). A file where tagtrail keeps a
folder, or a folder where it keeps a file, is replaced when empty and refused otherwise. Every
path is resolved through every symlink at every level, and all are checked before a stage runs
or a file is written (:func:`check_project`).

Dataset names are validated when the pipeline is loaded; :func:`inside` is the second line of
defence, so that no later code path can turn a name into a path outside its folder.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from tagtrail.errors import SpecError
from tagtrail.io.layouts import TEMP_PREFIX, remove_stale_temps

if TYPE_CHECKING:
    from tagtrail.runner.spec import Pipeline

TOPS = ("outputs", "artifacts", "sweeps")
ARTIFACT_FOLDERS = ("tmp", "objects", "runs", "logs")
ARTIFACT_FILES = ("sources.json", ".lock")
RUN_LOG = "last_run.json"  # in artifacts/runs/, beside the datasets' folders
EXPORT_STAMP = ".tagtrail-export.json"
OUTPUT_FILES = (  # what the exporters write in outputs/<dataset>/ (tests/test_reliability_paths)
    "trajectory.csv",
    "trajectory.tum",
    "trajectory_std.csv",
    "trajectory_evidence.csv",
    "trajectory_raw.csv",
    "tag_map.yaml",
    "tag_map.csv",
    "ground.json",
    "diagnostics.csv",
    "map.png",
    "evaluation.json",
    "relocalization.csv",
    "summary.json",
    "relocalization.png",
    EXPORT_STAMP,
)
SWEEP_FILES = ("sweep.json", "sweep.csv", "sweep.png", "runs.json", "times.json")


def inside(root: Path, *parts: str) -> Path:
    """``root / parts…``, refusing a result that is ``root`` itself or resolves outside it."""
    path = Path(root).joinpath(*parts)
    base = Path(root).resolve()
    target = path.resolve()
    if target == base or base not in target.parents:
        raise SpecError(f"refusing to write {path}: it resolves outside {root} ({target})")
    return path


def clean_temp_files(folder: Path, names: Collection[str] | None = None) -> list[Path]:
    """Delete the temporary files killed writes left in ``folder`` (tagtrail's own names only,
    ``.tagtrail-tmp-…``, and none a running write holds); returns what was removed."""
    return remove_stale_temps(folder, names)


def is_temp_dir(name: str) -> bool:
    """A store entry being written (``artifacts/tmp/.tagtrail-tmp-<stage>-<key>-XXXXXXXX``)."""
    return name.startswith(TEMP_PREFIX)


def _short(name: str) -> str:
    return name if len(name) <= 40 else f"{name[:37]}…"


def check_top(root: Path, top: str) -> Path:
    """The resolved folder of top folder ``top``; refuses a file, a symlink leading nowhere or to
    a file, and a symlink to a folder that holds the project."""
    path = Path(root) / top
    if path.is_symlink():
        target = path.resolve()
        if not target.exists():
            raise SpecError(
                f"{path} is a symlink to {target}, which does not exist: create "
                "that folder or remove the link"
            )
        if not target.is_dir():
            raise SpecError(f"{path} is a symlink to {target}, which is not a folder")
        project = Path(root).resolve()
        if target == project or target in project.parents:
            raise SpecError(
                f"{path} is a symlink to {target}, which holds the project; "
                "link it to a folder of its own"
            )
        return target
    if path.exists() and not path.is_dir():
        raise SpecError(f"{path} is not a folder: tagtrail keeps its {top} there; move it away")
    return path.resolve()


def check_tops(root: Path, tops: Iterable[str] = TOPS) -> dict[str, Path]:
    """Each of ``tops`` resolved (:func:`check_top`); refuses one that overlaps any top folder."""
    resolved = {top: check_top(root, top) for top in tops}
    every = {top: resolved.get(top) or (Path(root) / top).resolve() for top in TOPS}
    for a in resolved:
        for b in TOPS:
            if a != b and (
                every[a] == every[b] or every[b] in every[a].parents or every[a] in every[b].parents
            ):
                raise SpecError(
                    f"{Path(root) / a} leads to {every[a]}, which overlaps "
                    f"{Path(root) / b} ({every[b]}): each of {', '.join(TOPS)} "
                    "needs a folder of its own"
                )
    return resolved


def _has_content(path: Path) -> bool:
    if path.is_dir():
        return any(os.scandir(path))
    return path.stat().st_size > 0


def _refuse_link(step: Path, top: Path, resolved_top: Path) -> None:
    target = step.resolve()
    if target == resolved_top or resolved_top not in target.parents:
        raise SpecError(
            f"{step} is a symlink leading outside {top} (to {target}); tagtrail "
            "writes there: remove the link"
        )
    if not target.exists():
        raise SpecError(
            f"{step} is a symlink to {target}, which does not exist; tagtrail "
            "writes there: remove the link"
        )
    raise SpecError(
        f"{step} is a symlink (to {target}); tagtrail writes there and follows no "
        f"symlink below {top}: remove the link"
    )


def check_below(
    root: Path, top: str, parts: tuple[str, ...], folder: bool, resolved_top: Path
) -> None:
    """Refuse ``root/top/parts…`` if it, or any folder on the way, is a symlink (leading out
    of the top folder, nowhere, or to another of tagtrail's own paths), or if a non-empty file
    holds a folder's place (or the reverse)."""
    for i in range(1, len(parts) + 1):
        step = Path(root, top, *parts[:i])
        if step.is_symlink():
            _refuse_link(step, Path(root) / top, resolved_top)
        if not step.exists():
            return  # made by tagtrail when needed
        wants_dir = folder or i < len(parts)
        if wants_dir != step.is_dir() and _has_content(step):
            kind, held = ("folder", "file") if wants_dir else ("file", "folder")
            raise SpecError(
                f"{step} is a {held} where tagtrail writes a {kind}, and it is not "
                "empty: move it away (an empty one is replaced)"
            )


def clear_empty_obstacle(path: Path, folder: bool) -> None:
    """Remove an empty file where a folder goes, or an empty folder where a file goes (what
    :func:`check_below` lets through); anything else is left alone."""
    if path.is_symlink():
        return
    try:
        if folder and path.is_file() and path.stat().st_size == 0:
            path.unlink()
        elif not folder and path.is_dir():
            path.rmdir()  # fails, and is left, if it is not empty
    except OSError:
        pass


def planned(
    pipe: Pipeline, tops: Iterable[str] = TOPS, sweep: str | None = None
) -> list[tuple[str, tuple[str, ...], bool]]:
    """(top, parts, is a folder) of every path a run (``tops``) writes or deletes, but the
    cache entries (``objects/<stage>/<key>``, checked as each is written)."""
    out: list[tuple[str, tuple[str, ...], bool]] = []
    tops = set(tops)
    datasets, stages = list(pipe.datasets), list(pipe.stages)
    if "artifacts" in tops:
        out += [("artifacts", (f,), True) for f in ARTIFACT_FOLDERS]
        out += [("artifacts", (f,), False) for f in ARTIFACT_FILES]
        out.append(("artifacts", ("runs", RUN_LOG), False))
        out += [("artifacts", ("objects", s), True) for s in stages]
        for ds in datasets:
            out.append(("artifacts", ("runs", ds), True))
            out += [("artifacts", ("runs", ds, f"{s}.json"), False) for s in stages]
    if "outputs" in tops:
        for ds in datasets:
            out.append(("outputs", (ds,), True))
            out += [("outputs", (ds, f), False) for f in OUTPUT_FILES]
    if "sweeps" in tops and sweep is not None:
        out.append(("sweeps", (sweep,), True))
        out += [("sweeps", (sweep, f), False) for f in SWEEP_FILES]
    return out


def check_project(pipe: Pipeline, tops: Iterable[str] = TOPS, sweep: str | None = None) -> None:
    """Refuse, with one :class:`SpecError` line and before any work, a project where a path
    tagtrail would write or delete breaks the rule of this module."""
    tops = tuple(tops)
    resolved = check_tops(pipe.root, tops)
    for top, parts, folder in planned(pipe, tops, sweep):
        check_below(pipe.root, top, parts, folder, resolved[top])
    if "artifacts" in tops:  # the cache entries: objects/<stage>/<key>
        objects = Path(pipe.root, "artifacts", "objects")
        for stage in pipe.stages:
            entries = objects / stage
            if entries.is_dir() and not entries.is_symlink():
                for e in os.scandir(entries):
                    if e.is_symlink():
                        _refuse_link(Path(e.path), objects.parent, resolved["artifacts"])


def clear_obstacles(pipe: Pipeline, tops: Iterable[str], sweep: str | None = None) -> None:
    """Remove the empty obstacles :func:`check_project` let through (under the store's lock)."""
    tops = tuple(tops)
    for top, parts, folder in planned(pipe, tops, sweep):
        for i in range(1, len(parts)):
            clear_empty_obstacle(Path(pipe.root, top, *parts[:i]), True)
        clear_empty_obstacle(Path(pipe.root, top, *parts), folder)
