"""The tagtrail command with the real stages: init, run, show, and one-line user errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from tagtrail.cli import main
from tests.cli_helpers import one_error_line


@pytest.fixture(scope="module")
def bags(room_bags: Path) -> Path:
    return room_bags


def test_init_then_run_then_show(bags: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    rc = main(
        [
            "init",
            "--reference",
            str(bags / "reference"),
            "--query",
            str(bags / "query_1"),
            "--tag-size",
            "0.16",
            "--anchor",
            "0",
        ]
    )
    assert rc == 0
    doc = yaml.safe_load(Path("pipeline.yaml").read_text())
    assert doc["datasets"]["reference"]["topics"] == {
        "detections": "/detections",
        "camera_info": "/camera_info",
    }
    assert doc["stages"] == {"pnp": {"tag_size": 0.16}}
    assert doc["datasets"]["reference"]["params"] == {"edges": {"anchor_id": 0}}
    assert main(["init", "--reference", str(bags / "reference")]) == 2
    assert "exists already" in one_error_line(capsys)
    assert main(["run", "report"]) == 0
    out = capsys.readouterr().out
    assert "report [query]" in out and (tmp_path / "outputs" / "query" / "summary.json").is_file()
    assert main(["show", "extract", "--csv", "det.csv"]) == 0
    header = Path("det.csv").read_text().splitlines()[0]
    assert header == (
        "stamp_sec,stamp_nanosec,tag_id,hamming,decision_margin,c0x,c0y,c1x,c1y,c2x,c2y,c3x,c3y"
    )


@pytest.mark.parametrize(
    "stages, message",
    [
        ({"optimize": {"f_scal": 0.1}}, "unknown key 'f_scal' — did you mean 'f_scale'"),
        ({"optimize": {"loss": "l2"}}, "stages.optimize.loss"),
        ({"extrct": {}}, "unknown stage 'extrct' — did you mean 'extract'"),
    ],
)
def test_bad_parameters_one_line_exit_2(bags, tmp_path, monkeypatch, capsys, stages, message):
    monkeypatch.chdir(tmp_path)
    doc = {"datasets": {"reference": {"source": str(bags / "reference")}}, "stages": stages}
    Path("pipeline.yaml").write_text(yaml.safe_dump(doc))
    assert main(["run"]) == 2
    assert message in one_error_line(capsys)


def test_missing_source_and_bad_source(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    Path("pipeline.yaml").write_text("datasets:\n  reference: {source: nowhere}\n")
    assert main(["status"]) == 2
    assert "nowhere does not exist" in one_error_line(capsys)
    Path("empty").mkdir()
    Path("pipeline.yaml").write_text("datasets:\n  reference: {source: empty}\n")
    assert main(["run"]) == 2
    assert "extract [reference]" in one_error_line(capsys)
    assert main(["init", "--reference", "empty", "--tag-size", "0.16", "-o", "p2.yaml"]) == 2
    assert "empty" in one_error_line(capsys)


def test_simulate_bad_option(tmp_path: Path, capsys) -> None:
    assert main(["simulate", "room", "--out", str(tmp_path), "--fps", "-3"]) == 2
    assert "--fps" in one_error_line(capsys)


@pytest.mark.parametrize("argv", [["tagtrail.cli", "simulate"], ["tagtrail.sim.cli"]])
def test_every_entry_point_reports_an_unexpected_error_on_one_line(
    tmp_path: Path, argv: list[str]
) -> None:
    """``tagtrail simulate`` and the standalone ``python -m tagtrail.sim.cli`` share one error
    shell: an unexpected failure (here --out under a file) is one line, exit 1, the traceback in
    a file."""
    import subprocess
    import sys

    (tmp_path / "file").write_text("")
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            *argv,
            "circle",
            "--out",
            str(tmp_path / "file" / "sim"),
            "--frames",
            "4",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    err = res.stderr.strip().splitlines()
    assert res.returncode == 1, res.stderr
    assert len(err) == 1 and err[0].startswith("error: unexpected ") and "Traceback" not in err[0]
    log = Path(err[0].rsplit("(traceback in ", 1)[1].rstrip(")"))
    assert "Traceback" in log.read_text()
    log.unlink()


def test_show_and_dag_take_the_same_overrides_as_run(bags, tmp_path, monkeypatch, capsys):
    """`run extract -S …` then `show extract -S …` inspects the artifact that run just made."""
    monkeypatch.chdir(tmp_path)
    Path("pipeline.yaml").write_text(f"datasets:\n  reference: {{source: {bags / 'reference'}}}\n")
    override = ["-S", "extract.min_decision_margin=5"]
    assert main(["run", "extract", *override]) == 0
    capsys.readouterr()
    assert main(["show", "extract", *override]) == 0
    assert "extract [reference]  artifact" in capsys.readouterr().out
    # the default parameters' artifact was never made: the most recent one, saying so
    assert main(["show", "extract"]) == 0
    out = capsys.readouterr()
    assert "showing the most recent artifact, made with -S extract.min_decision_margin=5" in (
        out.out + out.err
    )
    assert main(["dag", *override]) == 0
    assert main(["dag", "-S", "extract.min_decision_margin=-1"]) == 2
    assert "min_decision_margin" in one_error_line(capsys)


def test_run_json_prints_the_json_alone(bags, tmp_path, monkeypatch, capsys):
    """`run --json`: stdout is the run log as JSON (for scripts), the status lines go to stderr."""
    import json

    monkeypatch.chdir(tmp_path)
    Path("pipeline.yaml").write_text(f"datasets:\n  reference: {{source: {bags / 'reference'}}}\n")
    assert main(["run", "pnp", "--json"]) == 0
    out = capsys.readouterr()
    log = json.loads(out.out)
    assert {s["stage"] for s in log} == {"extract", "pnp"} and "ran" in out.err
