"""The stage contract as stage modules import it: :class:`StageParams` and the declarations
(:class:`Metric`, :class:`Export`). They live in :mod:`tagtrail.schemas.stage`, where the runner
reads them too (the runner imports no module of ``tagtrail.stages``); see that module for what
a stage module exposes. Also :func:`refuse_old_keys`, for a stage's renamed settings."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from tagtrail.schemas.stage import Export, ExportFiles, Metric, StageModule, StageParams

__all__ = ["Export", "ExportFiles", "Metric", "StageModule", "StageParams", "refuse_old_keys"]


def refuse_old_keys(stage: str, data: Any, moved: Mapping[str, str]) -> Any:
    """``data`` (a stage's raw parameters) unchanged unless it holds a key of ``moved`` (a name
    that was once a setting -> where it is now): then a ValueError in one line naming it."""
    if isinstance(data, dict):
        for old, new in moved.items():
            if old in data:
                raise ValueError(f"{stage}.{old} is no longer a setting: {new}")
    return data
