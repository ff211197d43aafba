"""``tagtrail relocalize`` on the real LIMO runs of the original tool (PAPER Table 4.3).

Which query is which case: ``query_pontobranco`` = case 1, ``query_metric_8`` = case 2,
``query_quadrad_2`` = case 3. The published numbers are reproduced by the original tool's
convention: the smoothed trajectories (``trajetoria_camera.csv``), a 2-D similarity fitted to
all common tags in (x, z), the parked query reduced to its median position and circular-mean
heading, D to the nearest point of the reference polyline and phi against that segment's heading
(at a vertex shared by two segments, the earlier one).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tagtrail.commands.relocalize import main, relocalize
from tagtrail.geometry.reference_path import resolve_plane
from tagtrail.io.layouts import read_tag_map, read_trajectory, write_tag_map, write_trajectory_csv
from tagtrail.schemas.artifacts import poses
from tagtrail.stages import align as align_stage
from tagtrail.stages import report as report_stage

TABLE_4_3 = {  # query folder: (case, D [m], phi [deg]) as published
    "query_pontobranco": (1, 0.2998, -31.38),
    "query_metric_8": (2, 0.4284, -10.34),
    "query_quadrad_2": (3, 0.3567, -1.63),
}
COMMON_TAGS = {"query_pontobranco": 4, "query_metric_8": 3, "query_quadrad_2": 4}
HEADER = (
    "stamp_sec,stamp_nanosec,t_rel_s,nearest_ref_idx,distance_m,heading_error_deg,"
    "query_heading_deg,ref_heading_deg,query_u,query_v,ref_u,ref_v"
)
FILES = ("relocalization.csv", "summary.json", "relocalization.png", "map.png")


@pytest.fixture(scope="module")
def limo(realdata: Path) -> Path:
    return realdata / "limo_seed_runs"


def result(out: Path) -> tuple[float, float, dict]:
    rel = pd.read_csv(out / "relocalization.csv")
    summary = json.loads((out / "summary.json").read_text())
    return float(rel["distance_m"].iloc[0]), float(rel["heading_error_deg"].iloc[0]), summary


@pytest.mark.parametrize("query", sorted(TABLE_4_3))
def test_limo_reproduces_table_4_3(limo: Path, query: str, tmp_path: Path) -> None:
    _, D_pub, phi_pub = TABLE_4_3[query]
    summary = relocalize(
        limo / "reference_three_letric",
        limo / query,
        tmp_path,
        mode="point",
        align="tags",
        align_model="similarity",
        plane="xz",
    )
    D, phi, written = result(tmp_path)
    assert written == summary and summary["mode"] == "point" and summary["n"] == 1
    assert abs(D - D_pub) <= 0.002, (query, D, D_pub)
    assert abs(phi - phi_pub) <= 0.2, (query, phi, phi_pub)
    al = summary["alignment"]
    assert al["model"] == "similarity" and al["common_tags"] == al["inliers"] == COMMON_TAGS[query]
    assert 0.99 < al["scale"] < 1.0 and al["rms_m"] < 0.003


@pytest.mark.parametrize("query", sorted(TABLE_4_3))
def test_limo_defaults_auto_plane_equal_xz(limo: Path, query: str, tmp_path: Path) -> None:
    _, D_pub, phi_pub = TABLE_4_3[query]
    summary = relocalize(limo / "reference_three_letric", limo / query, tmp_path)  # all auto
    D, phi, _ = result(tmp_path)
    assert summary["mode"] == "point" and summary["plane"] == "auto"
    assert abs(D - D_pub) <= 0.002 and abs(phi - phi_pub) <= 0.2


def test_limo_auto_plane_is_xz(limo: Path) -> None:
    plane = resolve_plane("auto", *poses(read_trajectory(limo / "reference_three_letric")))
    cos1 = math.cos(math.radians(1.0))
    assert plane.n @ [0, -1, 0] > cos1 and plane.e1 @ [1, 0, 0] > cos1
    assert plane.e2 @ [0, 0, 1] > cos1


def test_cli_writes_spec_files(limo: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    args = [
        str(limo / "reference_three_letric"),
        str(limo / "query_metric_8"),
        "--mode",
        "point",
        "--plane",
        "xz",
        "--align",
        "tags",
        "--align-model",
        "similarity",
    ]
    assert main([*args, "-o", str(tmp_path / "a")]) == 0
    printed = capsys.readouterr().out
    assert "D   = 0.428" in printed and "phi = -10.3" in printed and "similarity on 3/3" in printed
    for name in FILES:
        assert str(tmp_path / "a" / name) in printed
    # the seed's columns and keys first, in their order (the tracker's follow)
    assert (
        (tmp_path / "a" / "relocalization.csv").read_text().splitlines()[0].startswith(HEADER + ",")
    )
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert list(summary)[:6] == [
        "mode",
        "plane",
        "n",
        "distance_m",
        "abs_heading_error_deg",
        "alignment",
    ]
    assert list(summary["distance_m"]) == ["mean", "median", "p90", "p95", "max", "rmse"]
    assert list(summary["alignment"]) == [
        "model",
        "scale",
        "rotation_deg",
        "translation",
        "inliers",
        "common_tags",
        "rms_m",
    ]
    assert main([*args, "-o", str(tmp_path / "b")]) == 0  # byte-reproducible, PNGs included
    for name in FILES:
        a, b = (tmp_path / "a" / name).read_bytes(), (tmp_path / "b" / name).read_bytes()
        assert a == b, name
    for name in FILES[2:]:
        assert (tmp_path / "a" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_uses_the_stage_functions(
    limo: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []

    def spy(mod):
        real = mod.run

        def run(*args, **kwargs):
            calls.append(mod.__name__)
            return real(*args, **kwargs)

        return run

    for mod in (align_stage, report_stage):
        monkeypatch.setattr(mod, "run", spy(mod))
    relocalize(limo / "reference_three_letric", limo / "query_metric_8", tmp_path)
    assert calls == ["tagtrail.stages.align", "tagtrail.stages.report"]


def test_accepts_trajectory_files_and_tagtrail_layouts(limo: Path, tmp_path: Path) -> None:
    ref, qry = limo / "reference_three_letric", limo / "query_quadrad_2"
    base = relocalize(ref, qry, tmp_path / "orig", plane="xz")
    by_file = relocalize(
        ref / "trajetoria_camera.csv", qry / "trajetoria_camera.csv", tmp_path / "files", plane="xz"
    )
    assert by_file == base
    for src in (ref, qry):  # tagtrail's own names: trajectory.csv + tag_map.yaml/.csv
        tags, anchor = read_tag_map(src)
        write_trajectory_csv(tmp_path / src.name / "trajectory.csv", read_trajectory(src))
        write_tag_map(tmp_path / src.name, tags, anchor if anchor is not None else 0)
    (tmp_path / qry.name / "tag_map.csv").unlink()  # the YAML alone is enough
    ours = relocalize(tmp_path / ref.name, tmp_path / qry.name, tmp_path / "ours", plane="xz")
    assert ours["distance_m"]["mean"] == pytest.approx(base["distance_m"]["mean"], abs=1e-12)
    assert ours["alignment"]["scale"] == pytest.approx(base["alignment"]["scale"], abs=1e-12)


def copy_query(limo: Path, tmp_path: Path, edit=None, tags: bool = True) -> Path:
    dst = tmp_path / "query"
    dst.mkdir()
    shutil.copy(limo / "query_metric_8" / "trajetoria_camera.csv", dst)
    if tags:
        df = pd.read_csv(limo / "query_metric_8" / "mapa_tags.csv")
        (edit(df) if edit else df).to_csv(dst / "mapa_tags.csv", index=False)
    return dst


def run_cli(ref: Path, query: Path, out: Path, *extra: str) -> int:
    return main([str(ref), str(query), "-o", str(out), *extra])


def test_bad_input(limo: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    ref = limo / "reference_three_letric"
    assert run_cli(ref, tmp_path / "nope", tmp_path / "o1") == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "nope: no such file or folder" in err

    def renamed(df: pd.DataFrame) -> pd.DataFrame:
        return df.assign(tag=[f"tag36h11:{100 + i}" for i in range(len(df))])

    q = copy_query(limo, tmp_path, renamed)
    assert run_cli(ref, q, tmp_path / "o2", "--align", "tags") == 2
    assert "only 0 common tag(s)" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()  # nothing half-written
    assert run_cli(ref, q, tmp_path / "o3") == 0  # auto: falls back to the query frame
    assert result(tmp_path / "o3")[2]["alignment"]["model"] == "none"


def test_scale_out_of_range(limo: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    ref = limo / "reference_three_letric"
    q = copy_query(limo, tmp_path, lambda df: df.assign(x=df["x"] * 1.3, z=df["z"] * 1.3))
    assert run_cli(ref, q, tmp_path / "o1") == 2
    err = capsys.readouterr().err
    assert "alignment scale 0.76" in err and "outside [0.900, 1.100]" in err
    assert run_cli(ref, q, tmp_path / "o2", "--allow-scale") == 0
    assert np.isclose(result(tmp_path / "o2")[2]["alignment"]["scale"], 0.9969 / 1.3, atol=1e-3)


def test_missing_tag_map(limo: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    q = copy_query(limo, tmp_path, tags=False)
    assert run_cli(limo / "reference_three_letric", q, tmp_path / "o", "--align", "tags") == 2
    assert "no tag map" in capsys.readouterr().err


def test_files_round_trip(limo: Path, tmp_path: Path) -> None:
    from tagtrail.io.reloc_files import read_relocalization_csv, write_summary_json

    ref, qry = limo / "reference_three_letric", limo / "query_quadrad_2"
    out = report_stage.run(
        read_trajectory(qry),
        read_trajectory(ref),
        align_stage.alignment_block("none", None, 0, 2),
        report_stage.Params(mode="trajectory"),
    )
    relocalize(ref, qry, tmp_path, mode="trajectory", align="none")
    back = read_relocalization_csv(tmp_path / "relocalization.csv")
    pd.testing.assert_frame_equal(back, out["relocalization"], check_exact=True)
    write_summary_json(tmp_path / "s.json", {"rms_m": float("nan"), "n": np.int64(3)})
    assert json.loads((tmp_path / "s.json").read_text()) == {"rms_m": None, "n": 3}


# --- bad input files and options: one `error:` line naming the file, row and column, exit 2 ---


def write_run(folder: Path, shift: float = 0.0) -> Path:
    """A small run in the original tool's layout: ``trajetoria_camera.csv`` + ``mapa_tags.csv``."""
    folder.mkdir()
    n = 20
    t = np.arange(n)
    traj = pd.DataFrame(
        {
            "t_ns": 1_700_000_000_000_000_000 + t * 100_000_000,
            "x_m": 0.1 * t + shift,
            "y_m": 0.0,
            "z_m": 1.0 + 0.02 * t,
            "qx": 0.0,
            "qy": 0.0,
            "qz": 0.0,
            "qw": 1.0,
        }
    )
    write_trajectory_csv(folder / "trajetoria_camera.csv", traj)
    (folder / "mapa_tags.csv").write_text(
        "tag,x,y,z,qx,qy,qz,qw,n_obs\n"
        "tag36h11:0,0.0,0.0,0.0,0.0,0.0,0.0,1.0,20\n"
        "tag36h11:1,1.0,0.0,0.0,0.0,0.0,0.0,1.0,20\n"
        "tag36h11:2,1.0,0.0,2.0,0.0,0.0,0.0,1.0,20\n"
    )
    return folder


def edit_cell(f: Path, row: int, col: str, value: str) -> None:
    """Set data row ``row`` (1-based, header not counted), column ``col`` of a CSV to ``value``."""
    lines = f.read_text().splitlines()
    cols = lines[0].split(",")
    cells = lines[row].split(",")
    cells[cols.index(col)] = value
    lines[row] = ",".join(cells)
    f.write_text("\n".join(lines) + "\n")


def cli_error(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """Run ``tagtrail relocalize …`` (the console script's entry); assert exit 2, one line."""
    from tagtrail.cli import main as tagtrail_main

    assert tagtrail_main(["relocalize", *argv]) == 2
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "unexpected" not in err[0], cap.err
    return err[0]


def test_synthetic_runs_relocalize(tmp_path: Path) -> None:  # the files the cases below break
    ref, qry = write_run(tmp_path / "ref"), write_run(tmp_path / "qry", shift=0.03)
    assert main([str(ref), str(qry), "-o", str(tmp_path / "o"), "--mode", "trajectory"]) == 0
    assert result(tmp_path / "o")[0] == pytest.approx(0.03, abs=1e-6)


TRAJ = "trajetoria_camera.csv"
BAD_TRAJECTORIES = {
    "text cell": (
        lambda f: edit_cell(f, 3, "x", "abc"),
        "data row 3, column x: 'abc' is not a number",
    ),
    "empty cell": (lambda f: edit_cell(f, 5, "qw", ""), "data row 5, column qw: empty cell"),
    "nan": (lambda f: edit_cell(f, 2, "y", "nan"), "data row 2, column y: empty cell (or NaN)"),
    "inf": (lambda f: edit_cell(f, 4, "z", "inf"), "data row 4, column z: 'inf' is not finite"),
    "-inf": (lambda f: edit_cell(f, 1, "x", "-inf"), "data row 1, column x: '-inf' is not finite"),
    "text stamp": (
        lambda f: edit_cell(f, 7, "stamp_sec", "soon"),
        "data row 7, column stamp_sec: 'soon' is not a number",
    ),
    "fractional stamp": (
        lambda f: edit_cell(f, 2, "stamp_nanosec", "1.5"),
        "data row 2, column stamp_nanosec: '1.5' is not an integer",
    ),
    "nanosec range": (
        lambda f: edit_cell(f, 2, "stamp_nanosec", "1000000000"),
        "data row 2, column stamp_nanosec: '1000000000' is not an integer in",
    ),
    "zero quaternion": (
        lambda f: [edit_cell(f, 6, c, "0") for c in ("qx", "qy", "qz", "qw")],
        "data row 6: quaternion (qx, qy, qz, qw) = (0.0, 0.0, 0.0, 0.0) has zero length",
    ),
    "stamps go back": (
        lambda f: edit_cell(f, 9, "stamp_sec", "1699999999"),
        "data row 9: stamp 1699999999.800000000 s is earlier than the one before",
    ),
    "missing column": (
        lambda f: f.write_text(f.read_text().replace(",qw", ",w")),
        "not a trajectory CSV, missing columns qw",
    ),
    "empty file": (lambda f: f.write_text(""), "empty file (expected a trajectory CSV"),
    "ragged row": (
        lambda f: f.write_text(f.read_text() + "1,2,3,4,5,6,7,8,9,10\n"),
        "cannot read trajectory CSV: Error tokenizing data",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_TRAJECTORIES))
def test_bad_trajectory_csv_one_line(tmp_path: Path, capsys, case: str) -> None:
    ref, qry = write_run(tmp_path / "ref"), write_run(tmp_path / "qry")
    edit, message = BAD_TRAJECTORIES[case]
    edit(qry / TRAJ)
    line = cli_error(capsys, str(ref), str(qry), "-o", str(tmp_path / "o"))
    assert f"error: {qry / TRAJ}: " in line and message in line, line
    assert not (tmp_path / "o").exists()


def test_equal_stamps_are_accepted(tmp_path: Path) -> None:
    ref, qry = write_run(tmp_path / "ref"), write_run(tmp_path / "qry")
    edit_cell(qry / TRAJ, 4, "stamp_nanosec", "200000000")  # row 4 = row 3's stamp
    assert main([str(ref), str(qry), "-o", str(tmp_path / "o")]) == 0


BAD_TAG_CSV = {
    "text cell": (lambda f: edit_cell(f, 2, "z", "x"), "data row 2, column z: 'x' is not a number"),
    "bad tag name": (
        lambda f: edit_cell(f, 3, "tag", "tagX"),
        "data row 3, column tag: 'tagX' is not a tag name",
    ),
    "zero quaternion": (
        lambda f: [edit_cell(f, 1, c, "0.0") for c in ("qx", "qy", "qz", "qw")],
        "data row 1: quaternion",
    ),
    "duplicate tag": (
        lambda f: edit_cell(f, 3, "tag", "tag36h11:1"),
        "tag tag36h11:1 is listed twice (data row 2 and data row 3)",
    ),
    "missing column": (
        lambda f: f.write_text(f.read_text().replace(",qx,", ",q,")),
        "not a tag map CSV, missing columns qx",
    ),
    "n_obs": (lambda f: edit_cell(f, 1, "n_obs", "many"), "data row 1, column n_obs: 'many'"),
}


@pytest.mark.parametrize("case", sorted(BAD_TAG_CSV))
def test_bad_tag_map_csv_one_line(tmp_path: Path, capsys, case: str) -> None:
    ref, qry = write_run(tmp_path / "ref"), write_run(tmp_path / "qry")
    edit, message = BAD_TAG_CSV[case]
    edit(ref / "mapa_tags.csv")
    line = cli_error(capsys, str(ref), str(qry), "-o", str(tmp_path / "o"))
    assert f"error: {ref / 'mapa_tags.csv'}: " in line and message in line, line


GOOD_TAG = "  position: {x: 1.0, y: 0.0, z: 0.0}\n  orientation: {x: 0.0, y: 0.0, z: 0.0, w: 1.0}\n"
BAD_TAG_YAML = {
    "not YAML": ("tags: {tag36h11:0: [\n", "not valid YAML (tag map): line 2, column 1:"),
    "no tags": ("world_frame: map\n", "not a tag map YAML (needs a 'tags:' mapping"),
    "no orientation": (
        "tags:\n tag36h11:0:\n  position: {x: 1, y: 0, z: 0}\n",
        "tag tag36h11:0: missing 'orientation:' mapping",
    ),
    "missing key": (
        "tags:\n tag36h11:0:\n" + GOOD_TAG.replace(", z: 0.0}", "}", 1),
        "tag tag36h11:0: position.z is missing",
    ),
    "text value": (
        "tags:\n tag36h11:0:\n" + GOOD_TAG.replace("x: 1.0", "x: one"),
        "tag tag36h11:0: position.x is 'one', not a finite number",
    ),
    "nan value": (
        "tags:\n tag36h11:0:\n" + GOOD_TAG.replace("x: 1.0", "x: .nan"),
        "tag tag36h11:0: position.x is nan, not a finite number",
    ),
    "zero quaternion": (
        "tags:\n tag36h11:0:\n" + GOOD_TAG.replace("w: 1.0", "w: 0"),
        "tag tag36h11:0: quaternion (qx, qy, qz, qw) = (0.0, 0.0, 0.0, 0.0)",
    ),
    "bad name": ("tags:\n tagX:\n" + GOOD_TAG, "tags: key 'tagX' is not a tag name"),
    "bad anchor": (
        "anchor_tag: zero\ntags:\n tag36h11:0:\n" + GOOD_TAG,
        "anchor_tag 'zero' is not a tag name",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_TAG_YAML))
def test_bad_tag_map_yaml_one_line(tmp_path: Path, capsys, case: str) -> None:
    ref, qry = write_run(tmp_path / "ref"), write_run(tmp_path / "qry")
    (qry / "mapa_tags.csv").unlink()
    text, message = BAD_TAG_YAML[case]
    (qry / "tag_map.yaml").write_text(text)
    line = cli_error(capsys, str(ref), str(qry), "-o", str(tmp_path / "o"))
    assert f"error: {qry / 'tag_map.yaml'}: " in line and message in line, line


def test_out_is_a_file(tmp_path: Path, capsys) -> None:
    ref, qry = write_run(tmp_path / "ref"), write_run(tmp_path / "qry")
    (tmp_path / "taken").write_text("keep me\n")
    line = cli_error(capsys, str(ref), str(qry), "-o", str(tmp_path / "taken"))
    assert f"-o {tmp_path / 'taken'}: is a file, not a folder" in line
    line = cli_error(capsys, str(ref), str(qry), "-o", str(tmp_path / "taken" / "sub"))
    assert f"lies under {tmp_path / 'taken'}, which is a file" in line
    assert (tmp_path / "taken").read_text() == "keep me\n"


def test_data_errors_name_the_datasets(tmp_path: Path, capsys) -> None:
    ref, qry = write_run(tmp_path / "ref"), write_run(tmp_path / "qry")
    for row in range(1, 21):  # a reference that never moves
        edit_cell(ref / TRAJ, row, "x", "0.5")
        edit_cell(ref / TRAJ, row, "z", "1.0")
    line = cli_error(capsys, str(ref), str(qry), "-o", str(tmp_path / "o"))
    assert line == (
        f"error: reference {ref}, query {qry}: the reference trajectory needs at "
        "least 2 distinct planar positions"
    )
