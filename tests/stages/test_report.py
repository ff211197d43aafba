"""Stage report: D and phi per pose (trajectory mode) or for a parked robot (point mode)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.errors import DataError
from tagtrail.runner.stage import stage_spec
from tagtrail.stages import report

T0 = 1_770_992_000_000_000_000
ALIGNMENT = {
    "model": "similarity",
    "scale": 0.99,
    "rotation_deg": 12.0,
    "translation": [0.1, 0.2],
    "inliers": 4,
    "common_tags": 4,
    "rms_m": 0.002,
}
STAT_KEYS = ["mean", "median", "p90", "p95", "max", "rmse"]


def traj(uv: np.ndarray, heading_deg: np.ndarray, dt_ns: int = 100_000_000) -> pd.DataFrame:
    """Upright cameras at (u, 0.03, v) in the xz floor with the given headings."""
    h = np.radians(heading_deg)
    f = np.stack([np.cos(h), np.zeros_like(h), np.sin(h)], axis=1)
    y = np.tile([0.0, -1.0, 0.0], (len(h), 1))
    R = np.stack([np.cross(y, f), y, f], axis=2)
    df = pd.DataFrame({"t_ns": T0 + dt_ns * np.arange(len(h), dtype=np.int64)})
    df[["x_m", "y_m", "z_m"]] = np.column_stack([uv[:, 0], np.full(len(h), 0.03), uv[:, 1]])
    df[["qx", "qy", "qz", "qw"]] = Rotation.from_matrix(R).as_quat()
    return df


REF = traj(np.column_stack([0.1 * np.arange(51), np.zeros(51)]), np.zeros(51))


def test_trajectory_mode_against_hand_values() -> None:
    k = np.array([3, 10, 11, 40, 50])
    heading = np.array([-20.0, 10.0, 30.0, 179.0, -90.0])
    q = traj(np.column_stack([0.1 * k + 0.02, np.full(5, 0.2)]), heading)
    out = report.run(q, REF, ALIGNMENT, report.Params(mode="trajectory", plane="xz"))
    rel, summary = out["relocalization"], out["summary"]
    assert list(rel.columns) == report.RELOC_COLS
    assert rel["t_ns"].dtype == np.int64 and rel["nearest_ref_idx"].dtype == np.int64
    np.testing.assert_array_equal(rel["nearest_ref_idx"], k)
    np.testing.assert_allclose(rel["distance_m"], math.hypot(0.02, 0.2), atol=1e-9)
    np.testing.assert_allclose(rel["heading_error_deg"], heading, atol=1e-9)
    np.testing.assert_allclose(rel["t_rel_s"], [0.0, 0.1, 0.2, 0.3, 0.4], atol=1e-12)
    np.testing.assert_allclose(
        rel[["ref_u", "ref_v"]], np.column_stack([0.1 * k, np.zeros(5)]), atol=1e-12
    )
    assert list(summary.model_dump())[:6] == [
        "mode",
        "plane",
        "n",
        "distance_m",
        "abs_heading_error_deg",
        "alignment",
    ]  # seed's first
    assert summary["mode"] == "trajectory" and summary["plane"] == "xz" and summary["n"] == 5
    assert summary["alignment"].model_dump() == ALIGNMENT
    a = np.abs(heading)  # 20, 10, 30, 179, 90
    expected = {
        "mean": 65.8,
        "median": 30.0,
        "p90": 143.4,
        "p95": 161.2,
        "max": 179.0,
        "rmse": math.sqrt(np.mean(a**2)),
    }
    assert list(summary["abs_heading_error_deg"].model_dump()) == STAT_KEYS
    for key, value in expected.items():
        assert summary["abs_heading_error_deg"][key] == pytest.approx(value, abs=1e-9)
    assert summary["distance_m"]["rmse"] == pytest.approx(math.hypot(0.02, 0.2), abs=1e-12)


def test_point_mode_parked_robot_across_180() -> None:
    rng = np.random.default_rng(0)
    uv = np.array([1.43, 0.3]) + rng.normal(0, 0.005, (9, 2))
    heading = np.array([176.0, -176.0, 178.0, -178.0, 180.0, -180.0, 179.0, -179.0, 180.0])
    out = report.run(traj(uv, heading), REF, ALIGNMENT, report.Params(mode="point", plane="xz"))
    rel, summary = out["relocalization"], out["summary"]
    assert len(rel) == 1 and summary["n"] == 1 and summary["mode"] == "point"
    med = np.median(uv, axis=0)
    row = rel.iloc[0]
    assert row["distance_m"] == pytest.approx(abs(med[1]), abs=1e-9)  # to the polyline
    assert (row["query_u"], row["query_v"]) == pytest.approx(tuple(med), abs=1e-12)
    assert (row["ref_u"], row["ref_v"]) == pytest.approx((med[0], 0.0), abs=1e-12)
    assert row["nearest_ref_idx"] == int(med[0] // 0.1)  # segment [k, k+1]
    assert abs(row["heading_error_deg"]) == pytest.approx(180.0, abs=1e-9)
    i = int(np.argmin(np.linalg.norm(uv - med, axis=1)))
    assert row["t_ns"] == T0 + i * 100_000_000
    assert row["t_rel_s"] == pytest.approx(i * 0.1)


def test_auto_mode_uses_the_capture_radius() -> None:
    parked = traj(
        np.array([2.0, 0.5]) + np.random.default_rng(1).normal(0, 0.05, (30, 2)), np.full(30, 5.0)
    )
    moving = traj(np.column_stack([np.linspace(0, 3, 30), np.full(30, 0.5)]), np.zeros(30))
    for q, mode in ((parked, "point"), (moving, "trajectory")):
        out = report.run(q, REF, ALIGNMENT, report.Params(plane="xz"))
        assert out["summary"]["mode"] == mode
    tight = report.Params(plane="xz", static_threshold_m=0.01)
    assert report.run(parked, REF, ALIGNMENT, tight)["summary"]["mode"] == "trajectory"


def test_bad_input() -> None:
    with pytest.raises(DataError, match="query trajectory is empty"):
        report.run(REF.iloc[:0], REF, ALIGNMENT, report.Params())
    with pytest.raises(DataError, match="at least 2"):
        report.run(REF, REF.iloc[:1], ALIGNMENT, report.Params(plane="xz"))


def test_stage_contract() -> None:
    spec = stage_spec("report", report)
    assert spec.scope == "query" and spec.outputs == ("relocalization", "summary")
    assert str(spec.inputs["alignment"]) == "align.alignment"
