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
from tests.cli_helpers import detection_bags, one_error_line


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return detection_bags(tmp_path_factory.mktemp("newcomer_bags"))


def test_init_without_a_tag_size_stops_naming_the_flag(bags: Path, tmp_path: Path,
                                                       monkeypatch, capsys) -> None:
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
    assert yaml.safe_load(Path("pipeline.yaml").read_text())["stages"] == {
        "pnp": {"tag_size": 0.2}}


def test_init_survey_without_sizes_needs_the_flag(realdata: Path, tmp_path: Path,
                                                  monkeypatch, capsys) -> None:
    """A field layout gives poses, no sizes: without --tag-size, one line naming it."""
    photos = realdata / "photonvision_frc2024_field"
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(photos / "images"),
                 "--survey", str(photos / "2024-crescendo.json")]) == 2
    line = one_error_line(capsys)
    assert "--tag-size" in line and "gives no tag sizes" in line
    assert not Path("pipeline.yaml").exists()


def test_init_writes_paths_as_typed(bags: Path, realdata: Path, tmp_path: Path,
                                    monkeypatch, capsys) -> None:
    """A symlinked data folder stays named by the link, relative to the pipeline file, for
    source, camera and survey alike; `run` reads the file it wrote."""
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "data").symlink_to(realdata / "tagslam_test_16")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "tag_detections.bag").write_bytes(
        bz2.decompress((realdata / "tagslam_test_16" / "tag_detections.bag.bz2").read_bytes()))
    assert main(["init", "--reference", "tag_detections.bag", "--camera",
                 "lab/data/cameras.yaml", "--survey", "lab/data/tagslam.yaml",
                 "-o", "lab/pipeline.yaml"]) == 0
    doc = yaml.safe_load((lab / "pipeline.yaml").read_text())
    assert doc["datasets"]["reference"]["source"] == "../tag_detections.bag"
    assert doc["datasets"]["reference"]["camera"] == "data/cameras.yaml"
    assert doc["stages"]["optimize"]["survey"]["file"] == "data/tagslam.yaml"
    assert doc["stages"]["pnp"] == {"tag_sizes_from": "data/tagslam.yaml"}  # no stale default
    capsys.readouterr()
    assert main(["status", "-p", "lab/pipeline.yaml"]) == 0


def test_compressed_source_names_the_unpack_command(tmp_path: Path, monkeypatch,
                                                    capsys) -> None:
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
    assert main(["init", "--reference", str(bags / "reference"), "--query",
                 str(bags / "query_1"), "--query", str(bags / "query_2"),
                 "--tag-size", "0.16"]) == 0
    capsys.readouterr()
    assert main(["run"]) == 0
    out = capsys.readouterr().out
    answer = out[out.index("== answer"):]
    diag = {r["metric"]: r["value"]
            for r in csv.DictReader(open("outputs/reference/diagnostics.csv", newline=""))}
    assert f"reference: {diag['tags_mapped']} tags mapped, " \
        f"{diag['frames_with_pose']}/{diag['frames_total']} frames posed, corner RMS" in answer
    assert "vs ground truth: trajectory rmse" in answer
    for name in ("query", "query_2"):
        summary = json.loads(Path(f"outputs/{name}/summary.json").read_text())
        m = re.search(rf"^{name}: parked \(point mode\): D = ([-\d.]+) m, phi = ([-+\d.]+) deg\n"
                      r"  phi vs the heading of the nearest reference segment", answer, re.M)
        assert m, answer
        assert float(m[1]) == pytest.approx(summary["distance_m"]["mean"], abs=1e-3)
        assert abs(float(m[2])) == pytest.approx(summary["abs_heading_error_deg"]["mean"],
                                                 abs=0.1)
    # trajectory mode: mean / max of D and |phi|, and the per-sample heading named
    assert main(["run", "-S", "report.mode=trajectory"]) == 0
    out = capsys.readouterr().out
    summary = json.loads(Path("outputs/query/summary.json").read_text())
    m = re.search(r"^query: trajectory mode, \d+ poses: D mean ([\d.]+) m, max ([\d.]+) m; "
                  r"\|phi\| mean ([\d.]+) deg, max ([\d.]+) deg\n"
                  r"  phi vs the reference heading at the nearest sample", out, re.M)
    assert m, out
    assert float(m[1]) == pytest.approx(summary["distance_m"]["mean"], abs=1e-3)
    assert float(m[2]) == pytest.approx(summary["distance_m"]["max"], abs=1e-3)
    assert float(m[3]) == pytest.approx(summary["abs_heading_error_deg"]["mean"], abs=0.1)
    assert float(m[4]) == pytest.approx(summary["abs_heading_error_deg"]["max"], abs=0.1)
