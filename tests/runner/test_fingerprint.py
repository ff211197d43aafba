"""The code fingerprint follows the code a stage runs: its whole first-party import closure,
found automatically, hashed without docstrings and comments (issue 11)."""

from __future__ import annotations

import importlib
import sys
import uuid
from pathlib import Path

import pytest

from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.runner.stage import code_closure, code_fingerprint
from tagtrail.stages import REGISTRY

STAGE = '''"""A toy stage: reads the source CSV and scales it by a helper two imports away."""
from __future__ import annotations

import pandas as pd

from {pkg}.helpers import scaled
from tagtrail.stages.base import StageParams

INPUTS = {{"source": "dataset"}}
OUTPUTS = ("table",)


class Params(StageParams):
    pass


def run(source, params: Params) -> dict:
    return {{"table": scaled(pd.read_csv(source.source))}}
'''
HELPERS = '''"""Helpers."""
from __future__ import annotations


def scaled(df):
    from {pkg} import maths  # a lazy import counts too

    return df.assign(value=maths.factor() * df["value"])
'''
MATHS = '''"""The factor."""
from __future__ import annotations


def factor() -> float:
    """Two."""
    return 2.0
'''


@pytest.fixture
def pkg(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[str, Path]:
    name = f"toypkg_{uuid.uuid4().hex[:8]}"
    root = tmp_path / "src" / name
    root.mkdir(parents=True)
    (root / "__init__.py").write_text('"""A first-party package of a plugin."""\n')
    for fname, text in (("stage", STAGE), ("helpers", HELPERS), ("maths", MATHS)):
        (root / f"{fname}.py").write_text(text.format(pkg=name))
    monkeypatch.syspath_prepend(str(tmp_path / "src"))
    yield name, root
    for mod in [m for m in sys.modules if m.startswith(name)]:
        del sys.modules[mod]


def fp(name: str) -> str:
    return code_fingerprint(importlib.import_module(f"{name}.stage"))


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))


def test_closure_is_found_from_the_source(pkg) -> None:
    name, _ = pkg
    closure = code_closure(importlib.import_module(f"{name}.stage"))
    assert set(closure) == {
        ".",
        f"{name}.helpers",
        f"{name}.maths",
        "tagtrail.stages.base",
        "tagtrail.schemas.stage",
    }  # the contract, as stages import it


def test_a_statement_two_imports_away_changes_it(pkg) -> None:
    name, root = pkg
    before = fp(name)
    edit(root / "maths.py", "    return 2.0", "    x = 1\n    return 2.0")
    assert fp(name) != before


def test_docstrings_comments_and_layout_do_not(pkg) -> None:
    name, root = pkg
    before = fp(name)
    edit(root / "maths.py", '"""Two."""', '"""Two, as measured (a long note)."""  # why')
    edit(root / "helpers.py", "def scaled(df):", "# a comment\n\n\ndef scaled(  df  ):")
    edit(root / "stage.py", '"""A toy stage', '"""A toy stage -- reworded')
    (root / "__init__.py").write_text("x = 1  # a package body no stage takes a name from\n")
    assert fp(name) == before


def test_status_names_the_module_that_changed(pkg, tmp_path: Path) -> None:
    name, root = pkg
    project = tmp_path / "proj"
    project.mkdir()
    (project / "a.csv").write_text("value\n1\n2\n")
    (project / "pipeline.yaml").write_text("datasets:\n  reference: {source: a.csv}\n")

    def runner() -> Runner:
        mod = importlib.import_module(f"{name}.stage")
        return Runner(load_pipeline(project / "pipeline.yaml", {"stage": mod}))

    assert [s.status for s in runner().run()] == ["ran"]
    edit(root / "maths.py", '"""Two."""', '"""Two (reworded)."""')
    assert [s.status for s in runner().plan()] == ["cached"]
    edit(root / "maths.py", "return 2.0", "return 3.0")
    (state,) = runner().plan()
    assert state.status == "stale" and state.reason == f"code changed: {name}.maths"
    (state,) = runner().run()
    assert state.status == "ran"


@pytest.mark.parametrize(
    "stage, modules",
    [
        ("extract", {"tagtrail.vision.detector", "tagtrail.vision.corners", "tagtrail.pool"}),
        ("report", {"tagtrail.geometry.se3", "tagtrail.geometry.reference_path"}),
        ("align", {"tagtrail.geometry.registration", "tagtrail.geometry.reference_path"}),
        ("optimize", {"tagtrail.geometry.posegraph", "tagtrail.geometry.se3"}),
    ],
)
def test_real_stages_cover_what_the_hand_lists_missed(stage: str, modules: set[str]) -> None:
    assert modules <= set(code_closure(REGISTRY[stage]))


def test_exports_cover_the_helpers_they_call() -> None:
    from tagtrail.runner import export

    assert {
        "tagtrail.io.reloc_files",
        "tagtrail.io.layouts",
        "tagtrail.geometry.reference_path",
        "tagtrail.schemas.artifacts",
    } <= set(code_closure(export))
