"""Relocalization cases for the streaming tests: reference, query, alignment file, offline result.

The offline values come from the offline code path (align stage transform + report stage, or
``tagtrail relocalize`` on the real LIMO files), never from the streaming code.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from tagtrail.commands.relocalize import relocalize
from tagtrail.geometry import se3
from tagtrail.geometry.reference_path import reference_plane
from tagtrail.geometry.registration import Alignment, world_transform
from tagtrail.io.layouts import POSE_COLS, read_trajectory, write_trajectory_csv
from tagtrail.io.reloc_files import read_relocalization_csv
from tagtrail.schemas.artifacts import poses
from tagtrail.stages import report as report_stage
from tagtrail.stages.align import transform_trajectory

T0_NS = 1_700_000_000_000_000_000


@dataclass(frozen=True)
class Case:
    reference: Path
    query: Path
    alignment: Path | None
    plane: str
    offline: pd.DataFrame  # report.relocalization columns (t_ns, distance_m, …)


def planar_poses(u: np.ndarray, v: np.ndarray, heading: np.ndarray, y: np.ndarray) -> np.ndarray:
    """world_T_cam ``(N, 4, 4)``: camera at (u, y, v), optical axis along ``heading`` in x–z,
    optical y down (world y up, as with an upright anchor tag)."""
    z_ax = np.stack([np.cos(heading), np.zeros_like(heading), np.sin(heading)], axis=1)
    y_ax = np.tile([0.0, -1.0, 0.0], (len(u), 1))
    x_ax = np.cross(y_ax, z_ax)
    R = np.stack([x_ax, y_ax, z_ax], axis=2)
    return se3.make_T(R, np.stack([u, y, v], axis=1))


def frame(T: np.ndarray, t_ns: np.ndarray) -> pd.DataFrame:
    xyz, q = se3.xyz_quat_from_T(T)
    df = pd.DataFrame(np.hstack([xyz, q]), columns=POSE_COLS)
    df.insert(0, "t_ns", t_ns.astype(np.int64))
    return df


def reference_frame(n: int) -> pd.DataFrame:
    """An ellipse in x–z (3 × 2 m), n samples at 10 Hz, cameras looking along the path."""
    s = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    u, v = 1.5 * np.cos(s), 1.0 * np.sin(s)
    heading = np.arctan2(1.0 * np.cos(s), -1.5 * np.sin(s))
    T = planar_poses(u, v, heading, np.full(n, -0.13))
    return frame(T, T0_NS + np.arange(n, dtype=np.int64) * 100_000_000)


def query_frame(n: int, seed: int = 0, out_of_order: bool = True) -> pd.DataFrame:
    """Poses scattered around the ellipse (±0.3 m, ±40°), 20 Hz, one stamp out of order unless
    ``out_of_order`` is False (trajectory files must be in time order: the reader refuses them)."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0, 2 * np.pi, n)
    u = 1.5 * np.cos(s) + rng.uniform(-0.3, 0.3, n)
    v = 1.0 * np.sin(s) + rng.uniform(-0.3, 0.3, n)
    heading = np.arctan2(np.cos(s), -1.5 * np.sin(s)) + np.radians(rng.uniform(-40, 40, n))
    T = planar_poses(u, v, heading, -0.13 + rng.uniform(-0.02, 0.02, n))
    t_ns = T0_NS + 10**9 + np.arange(n, dtype=np.int64) * 50_000_000
    if out_of_order and n > 11:
        t_ns[[10, 11]] = t_ns[[11, 10]]
    return frame(T, t_ns)


def synthetic_case(tmp: Path, n_ref: int = 300, n_query: int = 120) -> Case:
    """Synthetic files in ``tmp``; the live node gets the alignment block as a JSON file."""
    ref, query = reference_frame(n_ref), query_frame(n_query, out_of_order=False)
    write_trajectory_csv(tmp / "reference" / "trajectory.csv", ref)
    write_trajectory_csv(tmp / "query" / "trajectory.csv", query)
    block = {
        "model": "similarity",
        "scale": 1.02,
        "rotation_deg": 7.5,
        "translation": [0.05, -0.1],
        "inliers": 4,
        "common_tags": 4,
        "rms_m": 0.001,
    }
    (tmp / "alignment.json").write_text(json.dumps({"plane": "xz", "alignment": block}))
    a = np.radians(block["rotation_deg"])
    al = Alignment(
        "similarity",
        block["scale"],
        np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]),
        np.array(block["translation"]),
        np.ones(4, bool),
        0.001,
    )
    # offline, from the files as written (what a user would run)
    ref_f = read_trajectory(tmp / "reference")
    q_f = read_trajectory(tmp / "query")
    A, R = world_transform(al, reference_plane("xz", *poses(ref_f)))
    res = report_stage.run(
        transform_trajectory(q_f, A, R),
        ref_f,
        block,
        report_stage.Params(mode="trajectory", plane="xz"),
    )
    return Case(
        tmp / "reference",
        tmp / "query" / "trajectory.csv",
        tmp / "alignment.json",
        "xz",
        res["relocalization"],
    )


def limo_case(tmp: Path, limo: Path, query: str = "query_metric_8") -> Case:
    """The LIMO reference and a query, aligned on their common tags by ``tagtrail relocalize``."""
    out = tmp / "offline"
    relocalize(
        limo / "reference_three_letric",
        limo / query,
        out,
        mode="trajectory",
        align="tags",
        align_model="similarity",
        plane="xz",
    )
    return Case(
        limo / "reference_three_letric",
        limo / query / "trajetoria_camera.csv",
        out / "summary.json",
        "xz",
        read_relocalization_csv(out / "relocalization.csv"),
    )
