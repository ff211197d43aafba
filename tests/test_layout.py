"""The import rules of the house (docs/ARCHITECTURE.md), read from the package's own source:
each room imports only the rooms below it, so the layout keeps saying where things live."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "tagtrail"

# room -> the tagtrail modules/packages it may import (besides itself)
ALLOWED: dict[str, set[str]] = {
    "errors": set(),
    "faults": set(),
    "signals": set(),
    "geometry": {"errors"},
    "schemas": {"errors", "geometry"},
    "vision": {"errors", "geometry", "schemas"},
    "pool": {"errors", ""},  # "": the top-level package (for its path)
    "io": {"errors", "faults", "geometry", "schemas", "vision"},
    "stages": {"errors", "geometry", "schemas", "vision", "pool", "stages.base"},
    "runner": {"errors", "faults", "geometry", "schemas", "vision", "pool", "io"},
}


def room_of(path: Path) -> str:
    rel = path.relative_to(PACKAGE)
    return rel.parts[0] if len(rel.parts) > 1 else rel.stem


def is_module(name: str) -> bool:
    rel = Path(*name.split(".")[1:])
    return (PACKAGE / rel).with_suffix(".py").is_file() or (PACKAGE / rel / "__init__.py").is_file()


def imports(path: Path) -> set[str]:
    """tagtrail modules imported by ``path`` (relative to ``tagtrail.``; lazy imports too):
    ``from pkg import name`` counts as ``pkg.name`` when that is a module, else as ``pkg``."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                names.add(sub if is_module(sub) else node.module)
    return {
        n.removeprefix("tagtrail").removeprefix(".")
        for n in names
        if n == "tagtrail" or n.startswith("tagtrail.")
    }


def allowed(room: str, target: str, module: str) -> bool:
    if target == module or target.split(".")[0] == room and room != "stages":
        return True
    if module == "stages":  # the registry
        return target.startswith("stages")
    if room == "stages":  # a stage imports no other stage, only the contract
        if target in ("stages", "stages.base"):
            return True
        if target.startswith("stages."):
            return False
    rules = ALLOWED[room]
    return any(target == r or target.startswith(r + ".") for r in rules) or (
        "" in rules and target == ""
    )


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if room_of(p) in ALLOWED)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_follow_the_rules(path: Path) -> None:
    room = room_of(path)
    module = ".".join(path.relative_to(PACKAGE).with_suffix("").parts).removesuffix(".__init__")
    bad = sorted(t for t in imports(path) if not allowed(room, t, module))
    assert not bad, f"{room}/ may not import {bad} (rules: {sorted(ALLOWED[room])})"


def test_the_rules_cover_every_room() -> None:
    rooms = {room_of(p) for p in PACKAGE.rglob("*.py")}
    top = {"cli", "commands", "sim", "stream", "docs_params", "__init__"}  # shells: import any room
    assert rooms <= set(ALLOWED) | top, rooms - set(ALLOWED) - top


def test_detector_settings_do_not_load_the_c_library() -> None:
    assert "pupil_apriltags" not in {
        n
        for n in ast.walk(ast.parse((PACKAGE / "vision" / "detector.py").read_text()))
        for n in [getattr(n, "module", None)]
    }
    import subprocess
    import sys

    code = (
        "import sys, tagtrail.vision.detector, tagtrail.io.sources, tagtrail.stream.localize;"
        "print('pupil_apriltags' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


RUNNER_GEOMETRY = {"geometry.camera"}  # what a source hands a stage; nothing stage-specific


def test_the_runner_knows_no_stage() -> None:
    """``runner/`` imports no module of ``tagtrail.stages`` (not even the contract, which lives
    in ``schemas.stage``) and no stage-specific geometry: metrics and exports are declared by
    the stages, the registry is handed in by the shells."""
    found: dict[str, set[str]] = {}
    for path in sorted((PACKAGE / "runner").glob("*.py")):
        names: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module:
                base = "." * node.level + node.module
                names |= {base, *(f"{base}.{a.name}" for a in node.names)}
            elif isinstance(node, ast.ImportFrom):  # from . import x
                names |= {"." * node.level + a.name for a in node.names}
        bad = {
            n
            for n in names
            if n.split(".")[:2] == ["tagtrail", "stages"]
            or n.lstrip(".").startswith("stages")
            and n.startswith("..")
        }
        bad |= {n for n in imports(path) if n.startswith("geometry") and n not in RUNNER_GEOMETRY}
        if bad:
            found[path.name] = bad
    assert not found, f"runner/ imports stage code: {found}"
