"""Hostile-user input to the tagtrail command (issue 10): every mistake is one ``error:`` line
with exit 2, nothing is written outside the project, damaged outputs are restored."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from subprocess import PIPE

import pytest
import yaml

from tagtrail.cli import main
from tagtrail.errors import SpecError
from tagtrail.runner.cache import Store
from tagtrail.runner.paths import clean_temp_files, inside
from tests.cli_helpers import one_error_line


@pytest.fixture(scope="module")
def bags(room_bags: Path) -> Path:
    return room_bags


def tree(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def write_pipeline(folder: Path, datasets: dict[str, object], stages: object = None) -> None:
    doc: dict[str, object] = {"reference": next(iter(datasets)), "datasets": datasets}
    if stages is not None:
        doc["stages"] = stages
    (folder / "pipeline.yaml").write_text(yaml.safe_dump(doc))


# --- 1. dataset names are never paths --------------------------------------------------------


@pytest.mark.parametrize("name", ["../x", "..", ".", "", "/ABS", "a/b", "x/../../y", "a\\b"])
def test_dataset_name_that_is_a_path_is_refused(bags, tmp_path, monkeypatch, capsys, name):
    outside = tmp_path / "outside"
    (outside / "x").mkdir(parents=True)
    for f in (outside / "trajectory.csv", outside / "x" / "trajectory.csv"):
        f.write_text("stamp_sec,stamp_nanosec,x,y,z,qx,qy,qz,qw\n1,0,0,0,0,0,0,0,1\n")
    project = outside / "project"
    project.mkdir()
    name = name.replace("/ABS", str(outside / "abs"))
    write_pipeline(project, {name: {"source": str(bags / "reference")}})
    before = tree(outside)
    monkeypatch.chdir(project)
    for cmd in (["run"], ["status"], ["dag"], ["show", "extract"]):
        assert main(cmd) == 2
        line = one_error_line(capsys)
        assert f"dataset name {name!r} is not allowed" in line, line
    after = tree(outside)
    assert after == before  # nothing written anywhere, the planted files byte-identical


def test_writers_refuse_paths_outside_their_folder(tmp_path: Path) -> None:
    root = tmp_path / "outputs"
    root.mkdir()
    assert inside(root, "reference") == root / "reference"
    for parts in (("..",), ("../x",), (".",), (str(tmp_path / "abs"),), ("a", "../../b")):
        with pytest.raises(SpecError, match="outside"):
            inside(root, *parts)
    (root / "link").symlink_to(tmp_path)  # a folder that is a door out of outputs/
    with pytest.raises(SpecError, match="outside"):
        inside(root, "link", "trajectory.csv")
    with pytest.raises(SpecError, match="outside"):
        Store(tmp_path / "artifacts").record_path("../../x", "extract")


def test_output_folder_symlinked_outside_is_refused(bags, tmp_path, monkeypatch, capsys):
    planted = tmp_path / "elsewhere"
    planted.mkdir()
    (planted / "trajectory.csv").write_text("mine\n")
    project = tmp_path / "p"
    (project / "outputs").mkdir(parents=True)
    (project / "outputs" / "reference").symlink_to(planted)
    write_pipeline(project, {"reference": {"source": str(bags / "reference")}})
    monkeypatch.chdir(project)
    assert main(["run", "extract"]) == 2
    assert "outside" in one_error_line(capsys)
    assert tree(planted) == {"trajectory.csv": b"mine\n"}


def test_temp_files_of_killed_writes_are_cleaned(tmp_path: Path) -> None:
    (tmp_path / ".tagtrail-tmp-map.png.ab_c12d9").write_bytes(b"")
    (tmp_path / ".tagtrail-tmp-sources.json.x1y2z3w4").write_bytes(b"{")
    (tmp_path / ".keep").write_text("a user's dotfile")
    (tmp_path / ".notes.20241203").write_text("a user's file named like a temp (issue 26)")
    (tmp_path / "map.png").write_bytes(b"png")
    removed = {p.name for p in clean_temp_files(tmp_path)}
    assert removed == {".tagtrail-tmp-map.png.ab_c12d9", ".tagtrail-tmp-sources.json.x1y2z3w4"}
    assert sorted(p.name for p in tmp_path.iterdir()) == [".keep", ".notes.20241203", "map.png"]


# --- 6. parameters are numbers, finite, once -------------------------------------------------


@pytest.mark.parametrize(
    "stages, override, message",
    [
        ({"pnp": {"tag_size": True}}, None, "stages.pnp.tag_size: Input should be a valid number"),
        ({"pnp": {"tag_size": "0.16"}}, None, "stages.pnp.tag_size: Input should be a valid"),
        ({"pnp": {"tag_size": float("inf")}}, None, "tag_size: Input should be a finite number"),
        ({"pnp": {"tag_size": float("nan")}}, None, "tag_size: Input should be a finite number"),
        ({"pnp": {"tag_sizes": {7: True}}}, None, "stages.pnp.tag_sizes.7"),
        ({"optimize": {"joint_min_frames": 10.5}}, None, "stages.optimize.joint_min_frames"),
        ({"extract": {"refit_corners": 1}}, None, "stages.extract.refit_corners"),
        (None, "pnp.tag_size=1e400", "tag_size: Input should be a finite number"),
        (None, "pnp.tag_size=.inf", "tag_size: Input should be a finite number"),
        (None, "pnp.tag_size=true", "tag_size: Input should be a valid number"),
        (None, "pnp.tag_size=[1,", "bad override -S 'pnp.tag_size=[1,': line 1: invalid YAML"),
    ],
)
def test_parameters_must_be_finite_numbers(
    bags, tmp_path, monkeypatch, capsys, stages, override, message
):
    monkeypatch.chdir(tmp_path)
    write_pipeline(tmp_path, {"reference": {"source": str(bags / "reference")}}, stages)
    for cmd in (["run"], ["status"]):
        assert main(cmd + (["-S", override] if override else [])) == 2
        assert message in one_error_line(capsys)
    assert not (tmp_path / "artifacts" / "objects").exists()


def test_tuple_and_int_parameters_still_read_from_yaml(bags, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    stages = {
        "extract": {"tag_ids": [0, 1, 2, 3]},
        "pnp": {"tag_size": 1, "tag_sizes": {3: 0.16}},
        "align": {"scale_range": [0.8, 1.2]},
    }
    write_pipeline(tmp_path, {"reference": {"source": str(bags / "reference")}}, stages)
    assert main(["status"]) == 0


@pytest.mark.parametrize(
    "text, message",
    [
        (
            "datasets:\n  a: {source: x}\n  a: {source: y}\n",
            "key 'a' written twice (lines 2 and 3)",
        ),
        (
            "datasets:\n  a: {source: x}\nstages:\n  pnp: {tag_size: 0.1, tag_size: 0.2}\n",
            "key 'tag_size' written twice",
        ),
        ("datasets:\n  a: {source: x}\nstages: {}\nstages: {}\n", "key 'stages' written twice"),
    ],
)
def test_a_key_written_twice_is_an_error(tmp_path, monkeypatch, capsys, text, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "x").mkdir()
    Path("pipeline.yaml").write_text(text)
    assert main(["status"]) == 2
    assert message in one_error_line(capsys)


def test_yaml_merge_keys_may_override(bags, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    src = str(bags / "reference")
    Path("pipeline.yaml").write_text(
        f"datasets:\n  reference: &r {{source: {src}}}\n  q:\n    <<: *r\n    source: {src}\n"
    )
    assert main(["status"]) == 0


@pytest.mark.parametrize("size", ["-1", "0", "nan", "inf", "-0.0"])
def test_init_refuses_a_bad_tag_size(bags, tmp_path, monkeypatch, capsys, size) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["init", "--reference", str(bags / "reference"), "--tag-size", size]) == 2
    assert "--tag-size" in one_error_line(capsys)
    assert not Path("pipeline.yaml").exists()


# --- 2. damaged outputs are restored ---------------------------------------------------------


def test_damaged_outputs_are_restored_and_force_rewrites(bags, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    write_pipeline(
        tmp_path,
        {
            "reference": {"source": str(bags / "reference")},
            "query": {
                "source": str(bags / "query_1"),
                "inputs": {
                    "trajectory.tag_map": "reference:optimize.tag_map",
                    "trajectory.map_report": "reference:optimize.report",
                    "align.tag_map": "reference:optimize.tag_map",
                },
            },
        },
    )
    assert main(["run"]) == 0
    good = tree(tmp_path / "outputs")
    ref, query = tmp_path / "outputs" / "reference", tmp_path / "outputs" / "query"
    with open(ref / "trajectory.csv", "r+b") as f:
        f.truncate(100)
    (query / "summary.json").write_text("garbage")
    (ref / "map.png").unlink()
    capsys.readouterr()
    assert main(["run"]) == 0
    out = capsys.readouterr().out
    assert "0 ran" in out and f"outputs [reference]: {ref}" in out
    assert tree(tmp_path / "outputs") == good
    # unchanged outputs are left alone; --force writes every file again
    mtime = (ref / "trajectory.csv").stat().st_mtime_ns
    assert main(["run"]) == 0
    assert (ref / "trajectory.csv").stat().st_mtime_ns == mtime
    assert main(["run", "--force"]) == 0
    assert (ref / "trajectory.csv").stat().st_mtime_ns != mtime
    assert tree(tmp_path / "outputs") == good


# --- 7. a read-only project can still be inspected -------------------------------------------


def _read_only(folder: Path) -> tuple[list[str], list[str]]:
    """Commands that make ``folder`` read-only and back: a read-only bind mount where this
    process may mount (root, as in CI), else permission bits (which bind any other user)."""
    probe = subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True)
    if probe.returncode == 0:
        subprocess.run(["umount", str(folder)], check=True)
        return (
            [
                "sh",
                "-c",
                f"mount --bind '{folder}' '{folder}' && mount -o remount,bind,ro '{folder}'",
            ],
            ["umount", str(folder)],
        )
    if os.geteuid() == 0:
        pytest.skip("root without mount rights: permission bits do not bind root")
    return ["chmod", "-R", "a-w", str(folder)], ["chmod", "-R", "u+w", str(folder)]


def test_status_and_show_in_a_read_only_project(bags, tmp_path) -> None:
    project = tmp_path / "p"
    project.mkdir()
    write_pipeline(project, {"reference": {"source": str(bags / "reference")}})
    cli = [sys.executable, "-m", "tagtrail.cli"]
    assert main(["run", "edges", "-p", str(project / "pipeline.yaml")]) == 0
    before = tree(project)
    make_ro, undo = _read_only(project)
    subprocess.run(make_ro, check=True)
    try:  # the three commands started at once, then checked
        procs = [
            subprocess.Popen([*cli, *argv], cwd=project, stdout=PIPE, stderr=PIPE, text=True)
            for argv in (["status"], ["show", "edges"], ["run"])
        ]
        outputs = [p.communicate(timeout=300) for p in procs]
        st, sh, run = [
            subprocess.CompletedProcess(p.args, p.returncode, *out)
            for p, out in zip(procs, outputs, strict=True)
        ]
        assert st.returncode == 0, st.stderr
        assert "extract [reference]" in st.stdout and "up to date" in st.stdout
        assert sh.returncode == 0, sh.stderr
        assert run.returncode == 2
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and "cannot write" in lines[0]
    finally:
        subprocess.run(undo, check=True)
    assert tree(project) == before


def test_exponent_numbers_are_numbers(bags, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    write_pipeline(tmp_path, {"reference": {"source": str(bags / "reference")}})
    text = (tmp_path / "pipeline.yaml").read_text() + "stages:\n  optimize: {f_scale: 5e-2}\n"
    (tmp_path / "pipeline.yaml").write_text(text)
    assert main(["status", "-S", "smooth.pos_sigma_m=1e-3"]) == 0
