"""The stage registry: one explicit mapping, in pipeline order (no plugin scan)."""

from __future__ import annotations

from tagtrail.stages import (
    align,
    edges,
    evaluate,
    extract,
    optimize,
    pnp,
    report,
    smooth,
    trajectory,
)
from tagtrail.stages.base import StageModule

REGISTRY: dict[str, StageModule] = {
    "extract": extract,
    "pnp": pnp,
    "edges": edges,
    "optimize": optimize,
    "trajectory": trajectory,
    "smooth": smooth,
    "eval": evaluate,
    "align": align,
    "report": report,
}
