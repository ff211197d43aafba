"""A new user's first ten minutes (issue 30): no silent tag size, paths as typed, compressed
inputs named with the command that unpacks them, and ``tagtrail run`` ending with the answer."""

from __future__ import annotations

import bz2
import csv
import json
import re
from pathlib import Path

import pytest
import yaml

from tagtrail.cli import main
from tests.cli_helpers import one_error_line


@pytest.fixture(scope="module")
def bags(room_bags: Path) -> Path:
    return room_bags  # read, never written


def test_init_without_a_tag_size_stops_naming_the_flag(
    bags: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    """A detections bag carries no tag size: init writes nothing and names --tag-size; a
    profile that documents no size (limo) does the same; the sim profile's size is written."""
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(bags / "reference")]) == 2
    line = one_error_line(capsys)
    assert "--tag-size" in line and "printed size is not known" in line
    assert not Path("pipeline.yaml").exists()
    assert main(["init", "--profile", "limo", "--reference", str(bags / "reference")]) == 2
    assert "--tag-size" in one_error_line(capsys)
    assert main(["init", "--reference", str(bags / "reference"), "--tag-size", "0.2"]) == 0
    assert yaml.safe_load(Path("pipeline.yaml").read_text())["stages"] == {"pnp": {"tag_size": 0.2}}


def test_init_survey_without_sizes_needs_the_flag(
    realdata: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    """A field layout gives poses, no sizes: without --tag-size, one line naming it."""
    photos = realdata / "photonvision_frc2024_field"
    monkeypatch.chdir(tmp_path)
    assert (
        main(
            [
                "init",
                "--reference",
                str(photos / "images"),
                "--survey",
                str(photos / "2024-crescendo.json"),
            ]
        )
        == 2
    )
    line = one_error_line(capsys)
    assert "--tag-size" in line and "gives no tag sizes" in line
    assert not Path("pipeline.yaml").exists()


def test_init_writes_paths_as_typed(
    bags: Path, realdata: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    """A symlinked data folder stays named by the link, relative to the pipeline file, for
    source, camera and survey alike; `run` reads the file it wrote."""
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "data").symlink_to(realdata / "tagslam_test_16")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "tag_detections.bag").write_bytes(
        bz2.decompress((realdata / "tagslam_test_16" / "tag_detections.bag.bz2").read_bytes())
    )
    assert (
        main(
            [
                "init",
                "--reference",
                "tag_detections.bag",
                "--camera",
                "lab/data/cameras.yaml",
                "--survey",
                "lab/data/tagslam.yaml",
                "-o",
                "lab/pipeline.yaml",
            ]
        )
        == 0
    )
    doc = yaml.safe_load((lab / "pipeline.yaml").read_text())
    assert doc["datasets"]["reference"]["source"] == "../tag_detections.bag"
    assert doc["datasets"]["reference"]["camera"] == "data/cameras.yaml"
    assert doc["stages"]["optimize"]["survey"]["file"] == "data/tagslam.yaml"
    assert doc["stages"]["pnp"] == {"tag_sizes_from": "data/tagslam.yaml"}  # no stale default
    capsys.readouterr()
    assert main(["status", "-p", "lab/pipeline.yaml"]) == 0


def test_compressed_source_names_the_unpack_command(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    Path("tag_detections.bag.bz2").write_bytes(bz2.compress(b"not a bag"))
    assert main(["init", "--reference", "tag_detections.bag.bz2", "--tag-size", "0.2"]) == 2
    line = one_error_line(capsys)
    assert "`bunzip2 -k " in line and "tag_detections.bag.bz2`" in line
    Path("packed").mkdir()
    Path("packed/run.bag.gz").write_bytes(b"")
    assert main(["init", "--reference", "packed", "--tag-size", "0.2"]) == 2
    assert "`gunzip -k " in one_error_line(capsys)


def test_run_ends_with_the_answer(bags: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    """Per parked query, the D and phi `run` prints agree with summary.json (1 mm, 0.1 deg),
    and the reference block gives tags mapped, frames posed and the errors vs ground truth."""
    monkeypatch.chdir(tmp_path)
    assert (
        main(
            [
                "init",
                "--reference",
                str(bags / "reference"),
                "--query",
                str(bags / "query_1"),
                "--query",
                str(bags / "query_2"),
                "--tag-size",
                "0.16",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["run"]) == 0
    out = capsys.readouterr().out
    answer = out[out.index("== answer") :]
    diag = {
        r["metric"]: r["value"]
        for r in csv.DictReader(open("outputs/reference/diagnostics.csv", newline=""))
    }
    assert (
        f"reference: {diag['tags_mapped']} tags mapped, "
        f"{diag['frames_with_pose']}/{diag['frames_total']} frames posed, corner RMS" in answer
    )
    assert "vs ground truth: trajectory rmse" in answer
    for name in ("query", "query_2"):
        summary = json.loads(Path(f"outputs/{name}/summary.json").read_text())
        m = re.search(
            rf"^{name}: parked \(point mode\): D = ([-\d.]+) m, phi = ([-+\d.]+) deg\n"
            r"  phi vs the heading of the nearest reference segment",
            answer,
            re.M,
        )
        assert m, answer
        assert float(m[1]) == pytest.approx(summary["distance_m"]["mean"], abs=1e-3)
        assert abs(float(m[2])) == pytest.approx(summary["abs_heading_error_deg"]["mean"], abs=0.1)
    # trajectory mode: mean / max of D and |phi|, and the per-sample heading named
    assert main(["run", "-S", "report.mode=trajectory"]) == 0
    out = capsys.readouterr().out
    summary = json.loads(Path("outputs/query/summary.json").read_text())
    m = re.search(
        r"^query: trajectory mode, \d+ poses: D mean ([\d.]+) m, max ([\d.]+) m; "
        r"\|phi\| mean ([\d.]+) deg, max ([\d.]+) deg\n"
        r"  phi vs the reference heading at the matched sample \(progress "
        r"association, plane auto\)",
        out,
        re.M,
    )
    assert m, out
    assert float(m[1]) == pytest.approx(summary["distance_m"]["mean"], abs=1e-3)
    assert float(m[2]) == pytest.approx(summary["distance_m"]["max"], abs=1e-3)
    assert float(m[3]) == pytest.approx(summary["abs_heading_error_deg"]["mean"], abs=0.1)
    assert float(m[4]) == pytest.approx(summary["abs_heading_error_deg"]["max"], abs=0.1)


def test_a_sweep_of_a_parameter_that_changes_nothing_marks_no_best(
    bags: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    """optimize.f_scale under the linear loss (which ignores it) moves the reference metrics by
    float noise only: the table prints one value for them, no point is "best", the table fits
    100 columns, and sweep.png draws flat lines (the plotted values are one)."""
    from tagtrail.commands import sweep as sweep_cmd
    from tagtrail.runner.sweep import read_table, within_noise

    monkeypatch.chdir(tmp_path)
    assert (
        main(
            [
                "init",
                "--reference",
                str(bags / "reference"),
                "--query",
                str(bags / "query_1"),
                "--tag-size",
                "0.16",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "sweep",
                "-S",
                "optimize.loss=linear",
                "-S",
                "optimize.f_scale=0.05,0.1,0.2",
                "--metric",
                "trajectory.rmse_m",
                "--metric",
                "D.mean_m",
                "--metric",
                "gauge_free.trajectory.rmse_m",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    rows = read_table(next(Path("sweeps").glob("*/sweep.csv")))
    first = [float(r["trajectory.rmse_m[reference]"]) for r in rows]
    assert all(within_noise(a, first[0]) for a in first)
    assert [r["best"] for r in rows] == ["false"] * 3
    assert "best: none: points 1, 2, 3 give the same trajectory.rmse_m" in out
    lines = out[: out.index("\nbest")].splitlines()
    assert max(len(line) for line in lines) <= 100
    head = next(i for i, line in enumerate(lines) if line.startswith("point"))
    block = lines[head : head + 4]  # the first block: header and three points
    col = block[0].split().index("trajectory.rmse_m[reference]")
    assert len({line.split()[col] for line in block[1:]}) == 1  # one value for the three
    assert sweep_cmd.denoised(first) == [sum(first) / 3] * 3


def test_sweep_values_to_the_digits_that_tell_them_apart() -> None:
    from tagtrail.commands.sweep import denoised, digits

    assert digits([0.1416, 0.14160000001, None]) == ["0.1416", "0.1416", "-"]
    assert digits([0.1416, 0.14161]) == ["0.1416", "0.14161"]  # 7e-5 apart: both shown
    assert digits([1.0, 1.0 + 3e-7]) == ["1", "1"]  # below the noise: the same
    assert denoised([1.0, 1.0 + 1e-3]) == [1.0, 1.0 + 1e-3]  # a real difference stays


def test_an_error_caused_by_dash_s_names_dash_s(
    bags: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    """A -S typo or bad value blames -S; the same mistake in the file blames the file."""
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(bags / "reference"), "--tag-size", "0.16"]) == 0
    capsys.readouterr()
    for given, expected in (
        (
            "optimize.f_scal=0.1",
            "error: -S optimize.f_scal=0.1: stages.optimize: unknown key "
            "'f_scal' — did you mean 'f_scale'?",
        ),
        ("optimize.f_scale=-1", "error: -S optimize.f_scale=-1: stages.optimize.f_scale: "),
        (
            "optimiz.f_scale=1",
            "error: -S optimiz.f_scale=1: unknown stage 'optimiz' — did you mean 'optimize'?",
        ),
    ):
        assert main(["status", "-S", given]) == 2
        line = one_error_line(capsys)
        assert line.startswith(expected) and "pipeline.yaml" not in line, line
    doc = yaml.safe_load(Path("pipeline.yaml").read_text())
    doc["stages"]["optimize"] = {"f_scal": 0.1}
    Path("pipeline.yaml").write_text(yaml.safe_dump(doc))
    assert main(["status", "-S", "optimize.f_scale=0.2"]) == 2
    assert one_error_line(capsys).startswith("error: pipeline.yaml: stages.optimize: unknown key")


def test_change_lines_are_bounded(bags: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    """A known-poses file added to a run's parameters: `status` says so in one short line (the
    block summarised by its keys), not thousands of characters of poses."""
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(bags / "reference"), "--tag-size", "0.16"]) == 0
    assert main(["run", "optimize"]) == 0
    capsys.readouterr()
    survey = bags / "reference" / "ground_truth" / "tag_map.yaml"
    assert main(["status", "-S", f"optimize.survey.file={survey}"]) == 0
    lines = capsys.readouterr().out.splitlines()
    line = next(x for x in lines if x.startswith("optimize [reference]"))
    assert "params changed: survey: None → {file, " in line
    assert max(len(x) for x in lines) <= 250
