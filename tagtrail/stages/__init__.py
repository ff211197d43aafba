"""The stage registry: one explicit mapping, in pipeline order (no plugin scan)."""

from __future__ import annotations

from types import ModuleType

REGISTRY: dict[str, ModuleType] = {}
