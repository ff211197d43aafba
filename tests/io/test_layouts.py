"""SPEC file layouts: write → read round trips, original tool's files, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from tagtrail.errors import SourceError
from tagtrail.io import layouts


def traj() -> pd.DataFrame:
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    df = pd.DataFrame(rng.normal(size=(5, 3)), columns=["x_m", "y_m", "z_m"])
    df[["qx", "qy", "qz", "qw"]] = q
    df.insert(0, "t_ns", np.arange(5, dtype=np.int64) * 33_333_333 + 1_700_000_000_000_000_001)
    return df


def test_trajectory_csv_round_trip_is_exact(tmp_path: Path) -> None:
    t = traj()
    layouts.write_trajectory_csv(tmp_path / "trajectory.csv", t)
    head = (tmp_path / "trajectory.csv").read_text().splitlines()[0]
    assert head == "stamp_sec,stamp_nanosec,x,y,z,qx,qy,qz,qw"
    back = layouts.read_trajectory(tmp_path)
    pd.testing.assert_frame_equal(back, t)


def test_tum_round_trip(tmp_path: Path) -> None:
    t = traj()
    layouts.write_trajectory_tum(tmp_path / "trajectory.tum", t)
    back = layouts.read_trajectory(tmp_path / "trajectory.tum")
    assert np.allclose(back[layouts.POSE_COLS], t[layouts.POSE_COLS])
    assert np.all(np.abs(back["t_ns"] - t["t_ns"]) < 1000)


def test_tag_map_yaml_and_csv_round_trip(tmp_path: Path) -> None:
    t = traj().drop(columns="t_ns")
    t.insert(0, "tag_id", [0, 3, 7, 12, 40])
    t["n_obs"] = [5, 4, 3, 2, 1]
    t["size_m"] = 0.16
    layouts.write_tag_map(tmp_path, t, anchor_id=0)
    ymap, anchor = layouts.read_tag_map(tmp_path / "tag_map.yaml")
    assert anchor == 0
    pd.testing.assert_frame_equal(ymap, t, check_dtype=False)
    cmap, _ = layouts.read_tag_map(tmp_path / "tag_map.csv")
    pd.testing.assert_frame_equal(cmap, t.drop(columns="size_m"), check_dtype=False)
    assert (tmp_path / "tag_map.csv").read_text().splitlines()[1].startswith("tag36h11:0,")


def test_tag_map_with_standard_deviations(tmp_path: Path) -> None:
    """SPEC's columns first, then the std columns (empty when unknown); the YAML's ``std`` block;
    both still read back as SPEC tag maps."""
    t = traj().drop(columns="t_ns")
    t.insert(0, "tag_id", [0, 3, 7, 12, 40])
    t["n_obs"] = [5, 4, 3, 2, 1]
    t["std_pos_m"] = [0.0, 0.002, 0.004, np.nan, 0.01]
    t["std_rot_deg"] = [0.0, 0.1, 0.2, np.nan, 0.5]
    layouts.write_tag_map(tmp_path, t, anchor_id=0)
    lines = (tmp_path / "tag_map.csv").read_text().splitlines()
    assert lines[0] == "tag,x,y,z,qx,qy,qz,qw,n_obs,std_pos_m,std_rot_deg"
    assert lines[2].endswith(",4,0.002,0.1") and lines[4].endswith(",2,,")
    doc = yaml.safe_load((tmp_path / "tag_map.yaml").read_text())
    assert doc["tags"]["tag36h11:7"]["std"] == {"position_m": 0.004, "orientation_deg": 0.2}
    assert "std" not in doc["tags"]["tag36h11:12"]
    for name in ("tag_map.csv", "tag_map.yaml"):
        back, _ = layouts.read_tag_map(tmp_path / name)
        assert back["tag_id"].tolist() == [0, 3, 7, 12, 40]
        assert np.allclose(back[layouts.POSE_COLS], t[layouts.POSE_COLS])


def test_trajectory_std_csv() -> None:
    t = traj()
    t["n_tags"] = [1, 2, 3, 1, 0]
    t["std_pos_m"] = [0.001, 0.002, np.nan, 0.004, 0.005]
    t["std_rot_deg"] = [0.1, 0.2, np.nan, 0.4, 0.5]
    lines = layouts.trajectory_std_csv_text(t).splitlines()
    assert lines[0] == "stamp_sec,stamp_nanosec,std_pos_m,std_rot_deg,n_tags"
    assert lines[1] == "1700000000,1,0.001,0.1,1" and lines[3].endswith(",,,3")


def test_reads_original_tool_folders(realdata: Path) -> None:
    ref = realdata / "limo_seed_runs" / "reference_three_letric"
    t = layouts.read_trajectory(ref)
    assert len(t) == 106 and t["t_ns"].is_monotonic_increasing
    tags, _ = layouts.read_tag_map(ref)
    assert len(tags) == 21
    _, anchor = layouts.read_tag_map(realdata / "limo_seed_runs" / "query_metric_8")
    assert anchor == 10


def test_bad_files_raise_source_errors(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no trajectory file"):
        layouts.read_trajectory(tmp_path)
    (tmp_path / "trajectory.csv").write_text("a,b\n1,2\n")
    with pytest.raises(SourceError, match="missing columns"):
        layouts.read_trajectory(tmp_path)
    with pytest.raises(SourceError, match="no such file"):
        layouts.read_tag_map(tmp_path / "nope.yaml")


def test_tum_bad_lines_name_the_line(tmp_path: Path) -> None:
    f = tmp_path / "run.tum"
    good = "# stamp x y z qx qy qz qw\n\n1.0 0 0 0 0 0 0 1\n1.5 1 0 0 0 0 0 1  # comment\n"
    f.write_text(good)
    assert layouts.read_trajectory(f)["t_ns"].tolist() == [1_000_000_000, 1_500_000_000]
    cases = {
        good + "2.0 1 abc 0 0 0 0 1\n": "run.tum: line 5, field y: 'abc' is not a finite number",
        good + "2.0 1 0 0 0 0 1\n": "run.tum: line 5: 7 fields, a TUM trajectory line has 8",
        good + "2.0 inf 0 0 0 0 0 1\n": "line 5, field x: 'inf' is not a finite number",
        good + "2.0 1 0 0 0 0 0 0\n": "line 5: quaternion (qx, qy, qz, qw) = (0.0, 0.0, 0.0, 0.0)",
        good + "1.2 1 0 0 0 0 0 1\n": "line 5: stamp 1.200000000 s is earlier than the one before",
    }
    for text, message in cases.items():
        f.write_text(text)
        with pytest.raises(SourceError) as info:
            layouts.read_trajectory(f)
        assert message in str(info.value) and "\n" not in str(info.value), (text, info.value)
    f.write_text("# nothing yet\n")
    empty = layouts.read_trajectory(f)
    assert len(empty) == 0 and list(empty.columns) == layouts.TRAJ_COLS


def test_header_only_csv_is_an_empty_trajectory(tmp_path: Path) -> None:
    (tmp_path / "trajectory.csv").write_text("stamp_sec,stamp_nanosec,x,y,z,qx,qy,qz,qw\n")
    assert len(layouts.read_trajectory(tmp_path)) == 0


def test_observations_csv_bad_tag_cell_names_the_row(tmp_path: Path) -> None:
    f = tmp_path / "observations.csv"
    f.write_text(
        "stamp_sec,stamp_nanosec,tag,x,y,z,qx,qy,qz,qw\n"
        "2,0,tag36h11:5,0.1,0.2,1.0,0,0,0,1\n"
        "1,500,,0.0,0.0,2.0,1,0,0,0\n"
    )
    from tagtrail.io.sources import ObservationsSource

    with pytest.raises(
        SourceError,
        match=r"observations.csv: data row 2, column tag: empty cell "
        r"is not a tag name",
    ):
        ObservationsSource(tmp_path)
