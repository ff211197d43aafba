"""Run the extract stage on a source path as the runner does (the source opened for it)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tagtrail.io.sources import open_source
from tagtrail.schemas.pipeline import DatasetConfig
from tagtrail.stages import extract


def extract_from(source: Path | str | DatasetConfig, params: Any = None) -> dict[str, Any]:
    cfg = source if isinstance(source, DatasetConfig) else DatasetConfig(source=Path(source))
    with open_source(cfg) as src:
        return extract.run(src, params or extract.Params())
