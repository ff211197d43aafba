"""SPEC file layouts: write → read round trips, original tool's files, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

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
