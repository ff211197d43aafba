"""The stage registry: one explicit mapping, in pipeline order (no plugin scan)."""

from __future__ import annotations

from types import ModuleType

from tagtrail.stages import (
    align,
    edges,
    eval,
    extract,
    optimize,
    pnp,
    report,
    smooth,
    trajectory,
)

REGISTRY: dict[str, ModuleType] = {
    "extract": extract,
    "pnp": pnp,
    "edges": edges,
    "optimize": optimize,
    "trajectory": trajectory,
    "smooth": smooth,
    "eval": eval,
    "align": align,
    "report": report,
}
