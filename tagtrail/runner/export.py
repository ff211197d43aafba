"""After a run: the human-facing SPEC files in ``outputs/<dataset>/``, from the artifacts.

The runner knows no stage: each stage declares the files it exports (``EXPORTS``, a
:class:`~tagtrail.schemas.stage.Export` each: its artifact inputs and a pure ``make`` that
returns each file's format and value). Per dataset, in registry order, an export gets its inputs
(the up-to-date artifacts of this dataset or of the reference, ``None`` where there is none), and
the files it makes are written atomically by :mod:`tagtrail.io.outputs`; a file it names with
no value is removed (no stale copy of another run stays).
A dataset whose artifacts and exporter code are unchanged since its last export, and whose
files still hash to what that export wrote (recorded in ``.tagtrail-export.json``), is skipped;
any missing or altered file makes the whole folder be written again (``force`` always does).
"""

from __future__ import annotations

import inspect
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tagtrail import faults
from tagtrail.errors import SpecError
from tagtrail.io import outputs
from tagtrail.io.layouts import atomic_write_text
from tagtrail.runner.cache import canonical_json, file_sha256, sha256_text
from tagtrail.runner.execute import Runner
from tagtrail.runner.paths import (
    EXPORT_STAMP,
    check_project,
    clean_temp_files,
    clear_obstacles,
    inside,
)
from tagtrail.runner.stage import InputRef, code_fingerprint
from tagtrail.schemas.stage import PARAMS, Export

STAMP = EXPORT_STAMP


def _hashes(folder: Path) -> dict[str, str]:
    return {
        p.name: file_sha256(p)
        for p in sorted(folder.iterdir())
        if p.is_file() and not p.name.startswith(".")
    }


def _unchanged(folder: Path, stamp: str) -> bool:
    """True when ``folder`` was exported from the same artifacts and code and every file it
    wrote is still there, byte for byte."""
    try:
        doc = json.loads((folder / STAMP).read_text())
        files = doc["files"]
        return bool(
            doc["stamp"] == stamp
            and isinstance(files, dict)
            and all(file_sha256(folder / name) == digest for name, digest in files.items())
        )
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
    exporting = [spec for spec in runner.pipe.stages.values() if spec.exports]
    drawn_with = sorted(
        {
            ref.removeprefix(PARAMS)
            for spec in exporting
            for e in spec.exports
            for ref in e.inputs.values()
            if ref.startswith(PARAMS)
        }
    )
    code = sha256_text(
        canonical_json(
            {  # this module and io's writers; each stage's makers
                "export": code_fingerprint(sys.modules[__name__]),
                "stages": {spec.name: spec.code_fingerprint for spec in exporting},
            }
        )
    )
    written: dict[str, Path] = {}
    for dataset in runner.pipe.datasets:
        used = sorted(
            f"{st}/{ds}/{k}"
            for (st, ds), k in keys.items()
            if ds in (dataset, runner.pipe.reference)
        )
        # the parameters the exporters draw with (report.plane for map.png): a change redraws
        drawn = {
            st: runner.pipe.params_for(st, dataset).model_dump(mode="json")
            for st in drawn_with
            if st in runner.pipe.stages
        }
        stamp = sha256_text(canonical_json({"code": code, "artifacts": used, "params": drawn}))
        folder = inside(runner.pipe.outputs, dataset)
        clean_temp_files(folder)
        if not force and _unchanged(folder, stamp):
            written[dataset] = folder
            continue
        cache: dict[tuple[str, str, str], Any] = {}

        def get(
            text: str, dataset: str = dataset, cache: dict[tuple[str, str, str], Any] = cache
        ) -> Any:
            if text.startswith(PARAMS):  # a stage's parameters for this dataset
                stage = text.removeprefix(PARAMS)
                return (
                    runner.pipe.params_for(stage, dataset) if stage in runner.pipe.stages else None
                )
            ref = InputRef.parse(text)
            ds = runner.pipe.reference if ref.from_reference else dataset
            assert ref.stage is not None and ref.output is not None
            key = keys.get((ref.stage, ds))
            if key is None or ref.output not in runner.pipe.stages[ref.stage].outputs:
                return None
            if (ref.stage, ref.output, ds) not in cache:
                cache[(ref.stage, ref.output, ds)] = runner.store.load(ref.stage, key, ref.output)
            return cache[(ref.stage, ref.output, ds)]

        wrote = False
        for spec in exporting:
            for export in spec.exports:
                wrote |= _write(export, get, folder, dataset)
                faults.point(f"export:{export.name}")
        if wrote:
            written[dataset] = folder
            doc = {"stamp": stamp, "files": _hashes(folder)}
            atomic_write_text(folder / STAMP, json.dumps(doc, indent=1, sort_keys=True))
    return written


def _write(export: Export, get: Callable[[str], Any], folder: Path, dataset: str) -> bool:
    """Make one export's files from its inputs and write them; True when it wrote any."""
    args = {arg: get(ref) for arg, ref in export.inputs.items()}
    if "dataset" in inspect.signature(export.make).parameters:
        args["dataset"] = dataset
    made = export.make(**args)
    if made is None:
        return False
    for name, what in made.items():
        if name not in export.files:
            raise SpecError(
                f"export {export.name} made {name!r}, which it does not declare "
                f"(files: {', '.join(export.files)})"
            )
        if what is None:
            (folder / name).unlink(missing_ok=True)  # not a stale one from another run
        else:
            outputs.write(folder, name, *what)
    return any(what is not None for what in made.values())
