"""Outputs a controller can use (issue 28), through ``tagtrail relocalize`` (the CLI, on CSV
folders) and through the live ``stream relocalize`` node (real zenoh on 127.0.0.1): the same
numbers, and the figure-eight crossing handled by ``progress`` association.

The reference is a lemniscate of Bernoulli built here from its analytic formula, in a z-up world
(plane xy); the query drives 4 cm to its left with the path's heading.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from tagtrail.cli import main as tagtrail_main
from tagtrail.commands.relocalize import relocalize
from tagtrail.io.layouts import write_trajectory_csv
from tagtrail.io.reloc_files import RELOC_HEADER, TRACK_HEADER, read_relocalization_csv
from tests.stream.helpers import Collector, free_port, loopback, running

A_M = 1.5  # the lemniscate's half-width
T0_NS = 1_760_000_000_000_000_000
HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
PREFIX = "ctl_test"
FLOAT_KEYS = ("distance_m", "heading_error_deg", "cross_track_m", "progress_m", "curvature_1pm")
TABLE_4_3 = {
    "query_pontobranco": (0.2998, -31.38),
    "query_metric_8": (0.4284, -10.34),
    "query_quadrad_2": (0.3567, -1.63),
}


def lemniscate_frame(t: np.ndarray, left_m: float = 0.0, dt_ns: int = 50_000_000) -> pd.DataFrame:
    """world_T_cam rows ``left_m`` to the left of the lemniscate (z up: seen from above), the
    camera looking along the path (optical y down), at parameters ``t``."""
    s, c = np.sin(t), np.cos(t)
    den = 1 + s * s
    dx = -A_M * s * (1 + s * s + 2 * c * c) / den**2
    dy = A_M * ((c * c - s * s) * den - 2 * s * s * c * c) / den**2
    sp = np.hypot(dx, dy)
    x, y = A_M * c / den - left_m * dy / sp, A_M * s * c / den + left_m * dx / sp
    f = np.column_stack([dx / sp, dy / sp, np.zeros_like(t)])
    down = np.tile([0.0, 0.0, -1.0], (len(t), 1))
    R = np.stack([np.cross(down, f), down, f], axis=2)
    df = pd.DataFrame({"t_ns": T0_NS + dt_ns * np.arange(len(t), dtype=np.int64)})
    df[["x_m", "y_m", "z_m"]] = np.column_stack([x, y, np.full(len(t), 0.15)])
    df[["qx", "qy", "qz", "qw"]] = Rotation.from_matrix(R).as_quat()
    return df


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("figure_eight")
    write_trajectory_csv(
        root / "reference" / "trajectory.csv", lemniscate_frame(np.linspace(0.0, 2 * np.pi, 2000))
    )
    write_trajectory_csv(
        root / "query" / "trajectory.csv",
        lemniscate_frame(np.linspace(0.01, 2 * np.pi - 0.01, 600), 0.04),
    )
    return root


def cli(folders: Path, out: Path, *extra: str) -> pd.DataFrame:
    assert (
        tagtrail_main(
            [
                "relocalize",
                str(folders / "reference"),
                str(folders / "query"),
                "-o",
                str(out),
                "--mode",
                "trajectory",
                "--plane",
                "xy",
                *extra,
            ]
        )
        == 0
    )
    return read_relocalization_csv(out / "relocalization.csv")


def test_cli_progress_on_the_figure_eight(
    folders: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rel = cli(folders, tmp_path / "p")  # progress: the default
    printed = capsys.readouterr().out
    assert "progress association" in printed and "centred difference" in printed
    header = (tmp_path / "p" / "relocalization.csv").read_text().splitlines()[0]
    assert header == ",".join(RELOC_HEADER + TRACK_HEADER)
    assert rel["heading_error_deg"].abs().max() <= 1.0
    np.testing.assert_allclose(rel["cross_track_m"], 0.04, atol=1e-3, rtol=0)
    assert (rel["nearest_ref_idx"].diff().dropna() >= 0).all() and not rel["lost"].any()
    summary = json.loads((tmp_path / "p" / "summary.json").read_text())
    assert summary["association"] == "progress" and summary["ref_heading"] == "sample"
    assert summary["cross_track_m"]["mean"] == pytest.approx(0.04, abs=1e-3)
    assert summary["abs_cross_track_m"]["max"] == pytest.approx(0.04, abs=1e-3)
    assert summary["lost"] == 0


def test_cli_nearest_reproduces_the_crossing_failure(folders: Path, tmp_path: Path) -> None:
    rel = cli(folders, tmp_path / "n", "--association", "nearest")
    phi = rel["heading_error_deg"].abs()
    assert ((phi - 90.0).abs() < 5.0).sum() >= 2  # the other branch, at right angles
    assert (rel["nearest_ref_idx"].diff().dropna() < 0).any()
    assert json.loads((tmp_path / "n" / "summary.json").read_text())["association"] == "nearest"


@pytest.mark.parametrize("association", ["progress", "nearest"])
def test_live_node_gives_the_cli_numbers(folders: Path, tmp_path: Path, association: str) -> None:
    """``stream replay`` (the query) → ``stream relocalize`` → this subscriber: state, the
    Float64 topics and the lookahead pose equal ``tagtrail relocalize``'s rows."""
    offline = cli(folders, tmp_path / "off", "--association", association).set_index("t_ns")
    n = len(offline)
    port = free_port()
    keys = [*FLOAT_KEYS, "state", "lookahead_pose"]
    node_args = [
        "relocalize",
        "--reference",
        folders / "reference",
        "--plane",
        "xy",
        "--association",
        association,
        "--prefix",
        PREFIX,
        "--listen",
        loopback(port),
        "--path-period",
        "0.5",
        "--duration",
        "60",
        "--stats-period",
        "0",
    ]
    with running([str(a) for a in node_args]) as (node,):
        node.wait_for("relocalize: ready")
        sub = Collector(port, [f"{PREFIX}/{k}" for k in (*keys, "reference_path")])
        try:
            sub.wait(f"{PREFIX}/reference_path", 1, timeout=15)  # our subscriptions are known
            with running(
                [
                    "replay",
                    folders / "query" / "trajectory.csv",
                    "--rate",
                    "0",
                    "--connect",
                    loopback(port),
                    "--wait",
                    "10",
                ]
            ) as (rep,):
                assert rep.p.wait(30) == 0, rep.output
            got = {k: sub.wait(f"{PREFIX}/{k}", n) for k in keys}
        finally:
            sub.close()
        assert node.stop() == 0, node.output
    states = [json.loads(b) for b in got["state"]]
    t_ns = [s["stamp_sec"] * 10**9 + s["stamp_nanosec"] for s in states]
    assert t_ns == offline.index.tolist()  # in order: progress follows the stream
    row = offline.loc[t_ns]
    for k in FLOAT_KEYS:
        live = [HUMBLE.deserialize_cdr(b, "std_msgs/msg/Float64").data for b in got[k]]
        np.testing.assert_allclose(live, row[k], rtol=0, atol=1e-9, err_msg=k)
        np.testing.assert_allclose([s[k] for s in states], row[k], rtol=0, atol=1e-9, err_msg=k)
    for k in ("lookahead_u", "lookahead_v"):
        np.testing.assert_allclose([s[k] for s in states], row[k], rtol=0, atol=1e-9)
    assert [s["lost"] for s in states] == row["lost"].tolist()
    assert [s["nearest_ref_idx"] for s in states] == row["nearest_ref_idx"].tolist()
    la = [HUMBLE.deserialize_cdr(b, "geometry_msgs/msg/PoseStamped") for b in got["lookahead_pose"]]
    assert [(m.header.stamp.sec, m.header.stamp.nanosec) for m in la] == [
        (s["stamp_sec"], s["stamp_nanosec"]) for s in states
    ]
    # plane xy: (u, v) = (x, y); the pose lies on the reference at the lookahead point
    np.testing.assert_allclose(
        [[m.pose.position.x, m.pose.position.y] for m in la],
        row[["lookahead_u", "lookahead_v"]],
        atol=1e-9,
    )
    np.testing.assert_allclose([m.pose.position.z for m in la], 0.15, atol=1e-12)
    if association == "progress":
        assert max(abs(s["heading_error_deg"]) for s in states) <= 1.0
        np.testing.assert_allclose([s["cross_track_m"] for s in states], 0.04, atol=1e-3)


@pytest.mark.parametrize("query", sorted(TABLE_4_3))
def test_table_4_3_with_either_association(realdata: Path, tmp_path: Path, query: str) -> None:
    """The paper's LIMO Table 4.3 (point mode) with ``association=nearest`` explicitly; point
    mode has one parked pose and no previous match, so the association does not enter it."""
    limo = realdata / "limo_seed_runs"
    D_pub, phi_pub = TABLE_4_3[query]
    rows = []
    for association in ("nearest", "progress"):
        out = tmp_path / association
        summary = relocalize(
            limo / "reference_three_letric",
            limo / query,
            out,
            mode="point",
            align="tags",
            plane="xz",
            association=association,
        )
        assert summary["association"] == "polyline" and summary["ref_heading"] == "segment"
        rows.append((out / "relocalization.csv").read_text())
        rel = read_relocalization_csv(out / "relocalization.csv")
        assert abs(rel["distance_m"].iloc[0] - D_pub) <= 0.002
        assert abs(rel["heading_error_deg"].iloc[0] - phi_pub) <= 0.2
        # in point mode |cross-track| is D (the nearest point of the polyline)
        assert abs(rel["cross_track_m"].iloc[0]) == pytest.approx(
            rel["distance_m"].iloc[0], abs=1e-12
        )
    assert rows[0] == rows[1]


def test_trajectory_mode_nearest_is_eq_3_12(realdata: Path, tmp_path: Path) -> None:
    """``nearest`` on a real LIMO query in trajectory mode: every k* is the globally nearest
    reference sample (Eq. 3.12), as the seed computed it."""
    from tagtrail.io.layouts import read_trajectory

    limo = realdata / "limo_seed_runs"
    relocalize(
        limo / "reference_three_letric",
        limo / "query_metric_8",
        tmp_path,
        mode="trajectory",
        align="tags",
        plane="xz",
        association="nearest",
    )
    rel = read_relocalization_csv(tmp_path / "relocalization.csv")
    ref = read_trajectory(limo / "reference_three_letric")[["x_m", "z_m"]].to_numpy()
    q = rel[["query_u", "query_v"]].to_numpy()
    d = np.linalg.norm(q[:, None, :] - ref[None], axis=2)
    np.testing.assert_allclose(rel["distance_m"], d.min(axis=1), atol=1e-6)
