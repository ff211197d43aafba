"""The cache key follows the reader (issue 27): the code that reads a dataset's `source` is part
of the key of the stages that take it, so a statement added to a reader module reruns `extract`
while a comment or docstring edit does not.

Edits are made in a copy of the package in `tmp_path` (never in the source tree); every
`tagtrail` call is a subprocess that imports that copy.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from tagtrail.runner.inputs import reader_closure

PACKAGE = Path(__file__).resolve().parents[2] / "tagtrail"
OBSERVATIONS = (
    "stamp_sec,stamp_nanosec,tag,x,y,z,qx,qy,qz,qw\n"
    "1,0,tag36h11:4,0.1,0.2,1.5,0,0,0,1\n1,0,tag36h11:2,0.0,0.1,2.0,1,0,0,0\n"
    "2,0,tag36h11:4,0.1,0.2,1.4,0,0,0,1\n"
)


def test_the_source_reader_covers_what_it_imports() -> None:
    source = reader_closure("source")
    assert {"tagtrail.io.sources", "tagtrail.io.layouts", "tagtrail.io.bags"} <= set(source)
    assert "tagtrail.io.layouts" in reader_closure("ground_truth")
    assert reader_closure("dataset") == {}  # its stage reads the files: its own closure


def test_a_reader_statement_reruns_extract_a_comment_does_not(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    shutil.copytree(PACKAGE, pkg / "tagtrail", ignore=shutil.ignore_patterns("__pycache__"))
    data = tmp_path / "data"
    data.mkdir()
    (data / "observations.csv").write_text(OBSERVATIONS)
    project = tmp_path / "project"
    project.mkdir()
    (project / "pipeline.yaml").write_text(f"datasets:\n  reference:\n    source: {data}\n")
    where = tagtrail(pkg, project, "-c", "import tagtrail; print(tagtrail.__file__)", module=False)
    assert Path(where.strip()).resolve() == (pkg / "tagtrail" / "__init__.py").resolve()
    assert "extract [reference]" in tagtrail(pkg, project, "run", "extract")
    layouts = pkg / "tagtrail" / "io" / "layouts.py"

    # comments and docstrings of the readers (io/layouts.py, io/sources.py): still up to date
    edit(layouts, "\ndef tag_name(", "\n# a comment on why\n\n\ndef tag_name(")
    layouts.write_text(layouts.read_text().replace('"""', '"""Reworded. ', 1))  # the docstring
    edit(
        pkg / "tagtrail" / "io" / "sources.py",
        "\ndef open_source(",
        "\n# a comment\ndef open_source(",
    )
    line = extract_line(tagtrail(pkg, project, "status"))
    assert "up to date" in line, line

    # a statement in a module the source reader imports: stale, because of code
    edit(layouts, "\ndef tag_name(", "\n_EDITED = True\n\n\ndef tag_name(")
    line = extract_line(tagtrail(pkg, project, "status"))
    assert "out of date" in line, line
    assert "(code changed: tagtrail.io.layouts (reads source))" in line, line
    ran = tagtrail(pkg, project, "run", "extract")
    assert re.search(
        r"^extract \[reference\] +ran .*code changed: tagtrail\.io\.layouts", ran, re.M
    ), ran


def tagtrail(pkg: Path, cwd: Path, *args: str, module: bool = True) -> str:
    env = {**os.environ, "PYTHONPATH": str(pkg)}
    env.pop("TAGTRAIL_FAULT", None)
    cmd = [sys.executable, *(["-m", "tagtrail.cli"] if module else []), *args]
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout


def extract_line(status: str) -> str:
    return next(line for line in status.splitlines() if line.startswith("extract [reference]"))


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert text.count(old) == 1
    path.write_text(text.replace(old, new))
