"""After a run: the human-facing SPEC files in ``outputs/<dataset>/``, from the artifacts.

Exporters live in ``tagtrail.io.exports`` (I/O at the edge). Each is called per dataset with a
getter ``get(stage, output, reference=False)`` that returns the up-to-date artifact (of this
dataset or of the reference) or ``None``, and writes the files whose artifacts exist, atomically.
A dataset whose artifacts and exporter code are unchanged since its last export is skipped.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from tagtrail.io.layouts import atomic_write_text
from tagtrail.runner.cache import canonical_json, sha256_text
from tagtrail.runner.execute import Runner
from tagtrail.runner.stage import code_fingerprint

STAMP = ".tagtrail-export.json"


def _unchanged(folder: Path, stamp: str) -> bool:
    """True when ``folder`` was exported from the same artifacts and code and is intact."""
    try:
        doc = json.loads((folder / STAMP).read_text())
    except (OSError, ValueError):
        return False
    return doc.get("stamp") == stamp and all((folder / f).is_file() for f in doc.get("files", []))


def export_outputs(runner: Runner) -> dict[str, Path]:
    """Write every dataset's files from the up-to-date artifacts; returns dataset → folder."""
    from tagtrail.io import exports
    from tagtrail.io.exports import EXPORTERS

    keys = {(s.stage, s.dataset): s.key for s in runner.plan() if s.status == "cached"}
    code = code_fingerprint(exports, exports.DEPENDS)
    written: dict[str, Path] = {}
    for dataset in runner.pipe.datasets:
        used = sorted(f"{st}/{ds}/{k}" for (st, ds), k in keys.items()
                      if ds in (dataset, runner.pipe.reference))
        stamp = sha256_text(canonical_json({"code": code, "artifacts": used}))
        folder = runner.pipe.outputs / dataset
        if _unchanged(folder, stamp):
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
        if wrote:
            written[dataset] = folder
            names = sorted(p.name for p in folder.iterdir() if p.is_file() and p.name != STAMP)
            atomic_write_text(folder / STAMP, json.dumps({"stamp": stamp, "files": names}))
    return written
