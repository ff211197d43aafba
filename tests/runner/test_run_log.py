"""The run log's per-node seconds, and `show` on a node whose current artifact was never made."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from tagtrail.errors import SpecError
from tagtrail.runner.execute import Runner
from tagtrail.runner.show import show
from tagtrail.runner.spec import load_pipeline
from tests.runner.project import write_project
from tests.runner.toy import copy_stages, load_registry

SLEEP = 0.4


@pytest.fixture
def make(tmp_path: Path):
    stages = copy_stages(tmp_path / "stages")
    pipe_file = write_project(
        tmp_path / "proj", {"scale": {"factor": 2.0}, "slow": {"seconds": SLEEP}}
    )

    def runner(*overrides: str, jobs: int = 1) -> Runner:
        return Runner(load_pipeline(pipe_file, load_registry(stages), overrides), jobs=jobs)

    return runner


@pytest.mark.parametrize("jobs", [1, 2])
def test_run_log_seconds_are_each_nodes_own(make, jobs: int) -> None:
    """-j 1 (the serial executor runs a node inside `submit`) times each node, not ~0 s, and no
    node's seconds include another's: they add up to at most the run's wall time."""
    runner = make(jobs=jobs)
    t0 = time.perf_counter()
    states = runner.run()
    wall = time.perf_counter() - t0
    log = json.loads((runner.pipe.artifacts / "runs" / "last_run.json").read_text())
    by = {(s["stage"], s["dataset"]): s["seconds"] for s in log}
    assert by == {(s.stage, s.dataset): s.seconds for s in states}
    assert all(by[("slow", d)] >= SLEEP for d in ("reference", "query"))
    assert all(sec < SLEEP for (stage, _), sec in by.items() if stage != "slow")
    if jobs == 1:
        assert sum(by.values()) <= wall


def test_show_without_the_runs_flags_shows_the_most_recent_artifact(make, capsys) -> None:
    make("scale.factor=5").run()
    capsys.readouterr()
    assert show(make(), "scale", "query", None, None) == 0
    out = capsys.readouterr().out.splitlines()
    key = make("scale.factor=5").key_of("scale", "query")
    assert key is not None and out[0].startswith(f"scale [query]  artifact {key[:12]}")
    assert out[1] == (
        "note: not up to date; showing the most recent artifact, made with -S scale.factor=5.0"
    )
    assert show(make("scale.factor=5"), "scale", "query", None, None) == 0  # matching flags
    assert "note:" not in capsys.readouterr().out


def test_show_of_a_node_never_run_is_one_error(make) -> None:
    with pytest.raises(SpecError, match=r"scale \[query\] is not up to date"):
        show(make(), "scale", "query", None, None)


def test_show_after_a_code_change_says_the_parameters_are_the_same(make, capsys) -> None:
    runner = make()
    runner.run()
    stage_file = Path(runner.pipe.stages["scale"].module.__file__ or "")
    code = stage_file.read_text()
    stage_file.write_text(code.replace("* params.factor", "* params.factor * 1.0"))
    capsys.readouterr()
    assert show(make(), "scale", "reference", None, None) == 0
    assert (
        "made with the same parameters, before its code or inputs changed"
        in capsys.readouterr().out
    )
