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

from tagtrail.geometry.plane import resolve_plane
from tagtrail.io.layouts import read_tag_map, read_trajectory, write_tag_map, write_trajectory_csv
from tagtrail.relocalize import main, relocalize
from tagtrail.stages import align as align_stage
from tagtrail.stages import report as report_stage
from tagtrail.stages.align import poses

TABLE_4_3 = {  # query folder: (case, D [m], phi [deg]) as published
    "query_pontobranco": (1, 0.2998, -31.38),
    "query_metric_8": (2, 0.4284, -10.34),
    "query_quadrad_2": (3, 0.3567, -1.63),
}
COMMON_TAGS = {"query_pontobranco": 4, "query_metric_8": 3, "query_quadrad_2": 4}
HEADER = ("stamp_sec,stamp_nanosec,t_rel_s,nearest_ref_idx,distance_m,heading_error_deg,"
          "query_heading_deg,ref_heading_deg,query_u,query_v,ref_u,ref_v")  # fmt: skip
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
    summary = relocalize(limo / "reference_three_letric", limo / query, tmp_path, mode="point",
                         align="tags", align_model="similarity", plane="xz")  # fmt: skip
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
    args = [str(limo / "reference_three_letric"), str(limo / "query_metric_8"), "--mode", "point",
            "--plane", "xz", "--align", "tags", "--align-model", "similarity"]  # fmt: skip
    assert main([*args, "-o", str(tmp_path / "a")]) == 0
    printed = capsys.readouterr().out
    assert "D   = 0.428" in printed and "phi = -10.3" in printed and "similarity on 3/3" in printed
    for name in FILES:
        assert str(tmp_path / "a" / name) in printed
    assert (tmp_path / "a" / "relocalization.csv").read_text().splitlines()[0] == HEADER
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert list(summary) == ["mode", "plane", "n", "distance_m", "abs_heading_error_deg",
                             "alignment"]  # fmt: skip
    assert list(summary["distance_m"]) == ["mean", "median", "p90", "p95", "max", "rmse"]
    assert list(summary["alignment"]) == ["model", "scale", "rotation_deg", "translation",
                                          "inliers", "common_tags", "rms_m"]  # fmt: skip
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

    def spy(mod):  # noqa: ANN001, ANN202
        real = mod.run

        def run(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
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
    by_file = relocalize(ref / "trajetoria_camera.csv", qry / "trajetoria_camera.csv",
                         tmp_path / "files", plane="xz")  # fmt: skip
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
    out = report_stage.run(read_trajectory(qry), read_trajectory(ref), {},
                           report_stage.Params(mode="trajectory"))  # fmt: skip
    relocalize(ref, qry, tmp_path, mode="trajectory", align="none")
    back = read_relocalization_csv(tmp_path / "relocalization.csv")
    pd.testing.assert_frame_equal(back, out["relocalization"], check_exact=True)
    write_summary_json(tmp_path / "s.json", {"rms_m": float("nan"), "n": np.int64(3)})
    assert json.loads((tmp_path / "s.json").read_text()) == {"rms_m": None, "n": 3}
