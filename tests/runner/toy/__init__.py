"""Toy stages for runner tests, loaded from a copy so tests can edit their code."""

from __future__ import annotations

import importlib.util
import shutil
import sys
import uuid
from pathlib import Path
from types import ModuleType

HERE = Path(__file__).parent
NAMES = ("load", "scale", "slow", "total", "compare")


def load_registry(folder: Path) -> dict[str, ModuleType]:
    """Import the toy stage files found in ``folder`` under fresh module names."""
    reg = {}
    tag = uuid.uuid4().hex[:8]
    for name in NAMES:
        spec = importlib.util.spec_from_file_location(f"toy_{name}_{tag}", folder / f"{name}.py")
        assert spec and spec.loader
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod
        spec.loader.exec_module(mod)
        reg[name] = mod
    return reg


def copy_stages(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in NAMES:
        shutil.copy(HERE / f"{name}.py", folder / f"{name}.py")
    return folder
