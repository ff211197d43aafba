"""After a run: the human-facing SPEC files in ``outputs/<dataset>/``, from the artifacts.

Exporters live in ``tagtrail.io.exports`` (I/O at the edge). Each is called per dataset with a
getter ``get(stage, output, reference=False)`` that returns the up-to-date artifact (of this
dataset or of the reference) or ``None``, and writes the files whose artifacts exist, atomically.
A dataset whose artifacts and exporter code are unchanged since its last export, and whose
files still hash to what that export wrote (recorded in ``.tagtrail-export.json``), is skipped;
any missing or altered file makes the whole folder be written again (``force`` always does).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from tagtrail import faults
from tagtrail.runner.cache import atomic_write_text, canonical_json, file_sha256, sha256_text
from tagtrail.runner.execute import Runner
from tagtrail.runner.paths import clean_temp_files, inside
from tagtrail.runner.stage import code_fingerprint

STAMP = ".tagtrail-export.json"


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
    """
    with runner.store.lock():
        return _export(runner, force)


def _export(runner: Runner, force: bool) -> dict[str, Path]:
    from tagtrail.io import exports
    from tagtrail.io.exports import EXPORTERS

    keys = {(s.stage, s.dataset): s.key for s in runner.plan() if s.status == "cached"}
    code = code_fingerprint(exports)
    written: dict[str, Path] = {}
    for dataset in runner.pipe.datasets:
        used = sorted(f"{st}/{ds}/{k}" for (st, ds), k in keys.items()
                      if ds in (dataset, runner.pipe.reference))
        stamp = sha256_text(canonical_json({"code": code, "artifacts": used}))
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
