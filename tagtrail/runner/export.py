"""After a run: the human-facing SPEC files in ``outputs/<dataset>/``, from the artifacts.

Exporters live in ``tagtrail.io.exports`` (I/O at the edge). Each is called per dataset with a
getter ``get(stage, output, reference=False)`` that returns the up-to-date artifact (of this
dataset or of the reference) or ``None``, and writes the files whose artifacts exist, atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tagtrail.runner.execute import Runner


def export_outputs(runner: Runner) -> dict[str, Path]:
    """Write every dataset's files from the up-to-date artifacts; returns dataset → folder."""
    from tagtrail.io.exports import EXPORTERS

    keys = {(s.stage, s.dataset): s.key for s in runner.plan() if s.status == "cached"}
    written: dict[str, Path] = {}
    for dataset in runner.pipe.datasets:
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

        folder = runner.pipe.outputs / dataset
        wrote = False
        for exporter in EXPORTERS:
            wrote |= bool(exporter(get, folder, dataset))
        if wrote:
            written[dataset] = folder
    return written
