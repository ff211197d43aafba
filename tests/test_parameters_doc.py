"""docs/PARAMETERS.md is what the stages' parameter models say: every parameter, its default,
unit and meaning; the test fails when the page is stale (regenerate: python -m
tagtrail.docs_params)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tagtrail import docs_params
from tagtrail.stages import REGISTRY


def test_the_page_is_up_to_date() -> None:
    assert docs_params.DOC.read_text(encoding="utf-8") == docs_params.render(), (
        "docs/PARAMETERS.md is stale: run python -m tagtrail.docs_params"
    )


def test_every_parameter_has_a_row_with_its_meaning_and_default() -> None:
    text = docs_params.render()
    for stage, module in REGISTRY.items():
        section = text.split(f"\n## {stage}\n", 1)[1].split("\n## ", 1)[0]
        defaults = module.Params().model_dump(mode="json")
        for name, info in module.Params.model_fields.items():
            assert info.description, f"{stage}.{name} has no description (a field docstring)"
            row = next(r for r in section.splitlines() if r.startswith(f"| `{name}` |"))
            cells = [c.strip() for c in row.split(" | ")]
            assert cells[-1].rstrip(" |"), row  # the meaning
            assert f"`{docs_params.json.dumps(defaults[name])}`" in row, row
    assert "| `tag_size` | float | `0.16` | m |" in text
    assert "| `ransac_threshold_m` | float | `0.1` | m |" in text


def test_check_mode_exits_1_on_a_stale_file(tmp_path: Path) -> None:
    stale = tmp_path / "PARAMETERS.md"
    stale.write_text(docs_params.render().replace("0.16", "0.17"), encoding="utf-8")
    cmd = [sys.executable, "-m", "tagtrail.docs_params", "--check", "-o", str(stale)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "stale" in done.stderr
    assert subprocess.run([*cmd[:-1], str(docs_params.DOC)], timeout=120).returncode == 0
