"""The runner on toy stages and real files: what executes, what is cached, and why."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tagtrail.errors import SpecError
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tests.runner.project import ALL, cached, executed, write_project
from tests.runner.toy import copy_stages, load_registry

DRIVER = Path(__file__).parent / "toy" / "driver.py"


@pytest.fixture
def project(tmp_path: Path):
    stages_dir = copy_stages(tmp_path / "stages")
    pipe_file = write_project(tmp_path / "proj")

    def runner(*overrides: str, jobs: int = 1) -> Runner:
        reg = load_registry(stages_dir)
        return Runner(load_pipeline(pipe_file, reg, overrides), jobs=jobs)

    runner.stages_dir = stages_dir  # type: ignore[attr-defined]
    runner.pipe_file = pipe_file  # type: ignore[attr-defined]
    return runner


def test_second_run_executes_nothing(project) -> None:
    assert executed(project().run()) == ALL
    states = project().run()
    assert executed(states) == set()
    assert cached(states) == ALL


def test_param_change_reruns_exactly_stage_and_descendants(project) -> None:
    project().run()
    states = project("scale.factor=3").run()
    assert executed(states) == ALL - {("load", "reference"), ("load", "query")}
    assert project("scale.factor=3").run() and executed(project("scale.factor=3").run()) == set()


def test_status_says_why(project) -> None:
    project().run()
    plan = {(s.stage, s.dataset): s for s in project("scale.factor=3").plan()}
    assert plan[("load", "reference")].status == "cached"
    assert plan[("scale", "reference")].status == "stale"
    assert "params changed: factor: 2.0 → 3.0" in plan[("scale", "reference")].reason
    assert "upstream out of date" in plan[("total", "query")].reason


def test_editing_stage_code_invalidates_that_stage(project) -> None:
    project().run()
    f = project.stages_dir / "total.py"
    f.write_text(f.read_text().replace('"n": len(table)', '"n": len(table), "edited": True'))
    r = project()
    why = {(s.stage, s.dataset): s.reason for s in r.plan() if s.status == "stale"}
    assert why[("total", "reference")].startswith("code changed: toy_total_")
    assert why[("total", "query")] == why[("total", "reference")]
    assert why[("compare", "query")].startswith("upstream out of date")
    assert executed(r.run()) == {("total", "reference"), ("total", "query"), ("compare", "query")}


def test_unchanged_output_stops_propagation(project) -> None:
    """A code edit that changes no output reruns the stage; identical outputs keep descendants
    cached."""
    project().run()
    f = project.stages_dir / "scale.py"
    f.write_text(f.read_text() + "\n_UNUSED = 0\n")
    assert executed(project().run()) == {("scale", "reference"), ("scale", "query")}


def test_source_change_reruns_its_dataset_only(project) -> None:
    project().run()
    src = project.pipe_file.parent / "query.csv"
    src.write_text("value\n4\n6\n")
    states = project().run()
    assert executed(states) == {(s, d) for s, d in ALL if d == "query"}


def test_corrupt_or_partial_artifact_is_a_miss(project) -> None:
    r = project()
    r.run()
    entry = next((r.store.objects / "scale").iterdir())
    pq = entry / "table.parquet"
    pq.write_bytes(pq.read_bytes()[:-7])  # truncated, as after a crash mid-copy
    (next((r.store.objects / "total").iterdir()) / "manifest.json").unlink()
    states = project().run()
    assert {s for s, _ in executed(states)} == {"scale", "total"}


def test_parallel_run_matches_serial(project, tmp_path: Path) -> None:
    states = project(jobs=2).run()
    assert executed(states) == ALL
    assert executed(project(jobs=2).run()) == set()


def test_dry_run_and_plan_write_nothing(project) -> None:
    r = project()
    plan = r.plan()
    assert {s.status for s in plan} == {"stale"}
    assert not (r.store.objects).exists()


def test_ground_truth_and_scope_skips(project) -> None:
    r = project()
    assert (
        "runs on query datasets only"
        in r.graph.skipped[next(n for n in r.graph.skipped if n.stage == "compare")]
    )


def test_bad_specs_raise_spec_errors(project, tmp_path: Path) -> None:
    reg = load_registry(project.stages_dir)
    with pytest.raises(SpecError, match="did you mean 'factor'"):
        load_pipeline(project.pipe_file, reg, ["scale.facter=2"])
    with pytest.raises(SpecError, match="greater than 0"):
        load_pipeline(project.pipe_file, reg, ["scale.factor=-1"])
    with pytest.raises(SpecError, match="unknown stage 'scal'.*did you mean 'scale'"):
        load_pipeline(project.pipe_file, reg, ["scal.factor=2"])


def _cli(stages_dir: Path, cwd: Path, *args: str, **kw) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(DRIVER), str(stages_dir), *args],
        cwd=cwd,
        env=_cli_env(),
        capture_output=True,
        text=True,
        timeout=120,
        **kw,
    )


def _cli_env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}


def _cli_at_once(
    stages_dir: Path, cwd: Path, argvs: list[tuple[str, ...]]
) -> list[subprocess.CompletedProcess[str]]:
    """``_cli`` of each of ``argvs``, all started before any is waited for."""
    procs = [
        subprocess.Popen(
            [sys.executable, str(DRIVER), str(stages_dir), *argv],
            cwd=cwd,
            env=_cli_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for argv in argvs
    ]
    done = []
    for proc in procs:
        out, err = proc.communicate(timeout=120)
        done.append(subprocess.CompletedProcess(proc.args, proc.returncode, out, err))
    return done


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda t: t.replace("datasets:", "datasets: [oops"), "invalid YAML"),
        (lambda t: t + "  scale:\n    fctor: 1\n", None),
        (
            lambda t: t.replace("factor: 2.0", "fctor: 2.0"),
            "unknown key 'fctor' — did you mean 'factor'",
        ),
        (
            lambda t: t.replace("source: query.csv", "source: nowhere.csv"),
            "nowhere.csv does not exist",
        ),
        (lambda t: t.replace("factor: 2.0", "factor: lots"), "factor"),
    ],
)
def test_cli_user_errors_are_one_line_exit_2(project, mutate, message) -> None:
    f = project.pipe_file
    text = mutate(f.read_text())
    f.write_text(text)
    res = _cli(project.stages_dir, f.parent, "run")
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert "Traceback" not in res.stderr
    if message:
        assert message in lines[0]


def test_cli_run_status_dag_show(project, tmp_path: Path) -> None:
    cwd = project.pipe_file.parent
    res = _cli(project.stages_dir, cwd, "run")
    assert res.returncode == 0, res.stderr
    assert "scale [reference]" in res.stdout and "ran" in res.stdout
    out = tmp_path / "scale.csv"
    reads = [  # commands that only read the finished run: started at once, then checked
        ("run", "-S", "scale.factor=5", "--dry-run"),
        ("status",),
        ("dag", "--mermaid"),
        ("show", "scale", "--dataset", "query", "--csv", str(out)),
        ("show", "scael"),
    ]
    dry, status, dag, show, typo = _cli_at_once(project.stages_dir, cwd, reads)
    assert "would run" in dry.stdout and "factor: 2.0 → 5" in dry.stdout
    assert status.returncode == 0 and "out of date" not in status.stdout
    assert dag.stdout.startswith("flowchart LR") and "-->" in dag.stdout
    assert show.returncode == 0, show.stderr
    assert "rows: 2" in show.stdout
    assert out.read_text() == "value\n8.0\n10.0\n"
    assert typo.returncode == 2 and "did you mean 'scale'" in typo.stderr


def test_stage_failure_names_stage_and_keeps_finished_artifacts(project) -> None:
    (project.pipe_file.parent / "query.csv").write_text("other\n1\n")
    res = _cli(project.stages_dir, project.pipe_file.parent, "run")
    assert res.returncode == 1
    assert "load [query]" in res.stderr and "traceback in" in res.stderr
    r = project()
    plan = {(s.stage, s.dataset): s.status for s in r.plan()}
    assert plan[("load", "reference")] == "cached"


@pytest.mark.slow
def test_kill_9_mid_stage_then_rerun_is_identical(project, tmp_path: Path) -> None:
    cwd = project.pipe_file.parent
    proc = subprocess.Popen(
        [sys.executable, str(DRIVER), str(project.stages_dir), "run", "-S", "slow.seconds=0.6"],
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    marker = cwd / "artifacts" / "runs" / "reference" / "scale.json"
    deadline = time.time() + 60
    while not marker.exists() and time.time() < deadline:
        time.sleep(0.02)
    time.sleep(0.3)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert _cli(project.stages_dir, cwd, "run", "-S", "slow.seconds=0.6").returncode == 0
    # An uninterrupted run in a fresh copy of the project gives byte-identical artifacts.
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    for f in ("pipeline.yaml", "reference.csv", "query.csv"):
        (fresh / f).write_bytes((cwd / f).read_bytes())
    assert _cli(project.stages_dir, fresh, "run", "-S", "slow.seconds=0.6").returncode == 0

    def entries(root: Path) -> dict[str, bytes]:
        return {
            str(p.relative_to(root)): p.read_bytes()
            for p in (root / "artifacts" / "objects").rglob("*")
            if p.is_file() and p.name != "manifest.json"
        }

    assert entries(cwd) == entries(fresh)
    assert not any((cwd / "artifacts" / "tmp").iterdir())


def test_per_dataset_params_override_only_that_dataset(project) -> None:
    project().run()
    doc = yaml.safe_load(project.pipe_file.read_text())
    doc["datasets"]["query"]["params"] = {"scale": {"factor": 10}}
    project.pipe_file.write_text(yaml.safe_dump(doc))
    states = project().run()
    assert executed(states) == {(s, d) for s, d in ALL if d == "query" and s != "load"}
    doc["datasets"]["query"]["params"] = {"scale": {"factr": 10}}
    project.pipe_file.write_text(yaml.safe_dump(doc))
    with pytest.raises(SpecError, match="datasets.query.params.scale.*did you mean 'factor'"):
        project()


def test_execution_only_params_do_not_invalidate(tmp_path: Path) -> None:
    from tagtrail.stages import REGISTRY

    pipe = tmp_path / "p.yaml"
    (tmp_path / "imgs").mkdir()
    pipe.write_text("datasets:\n  reference: {source: imgs}\n")
    a = Runner(load_pipeline(pipe, REGISTRY, ["extract.workers=1"])).record_for
    b = Runner(load_pipeline(pipe, REGISTRY, ["extract.workers=2", "extract.chunk_size=4"]))
    from tagtrail.runner.dag import Node

    node = Node("extract", "reference")
    assert b.record_for(node, {}) == a(node, {})
    c = Runner(load_pipeline(pipe, REGISTRY, ["extract.quad_decimate=1.0"]))
    assert c.record_for(node, {}) != a(node, {})


def test_a_second_run_waits_for_the_lock(project) -> None:
    r = project()
    cwd = project.pipe_file.parent
    with r.store.lock():
        proc = subprocess.Popen(
            [sys.executable, str(DRIVER), str(project.stages_dir), "run"],
            cwd=cwd,
            env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        # blocked while we hold the store: it says so (however slowly a loaded machine starts it)
        first = proc.stderr.readline() if proc.stderr is not None else ""
        assert "waiting for another tagtrail run" in first and proc.poll() is None
        assert not (r.store.objects).exists()
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0
    assert executed(project().run()) == set()
