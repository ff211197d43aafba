"""Stage align: recovers a known query→reference transform from the common tags."""

from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd
import pydantic
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.errors import DataError
from tagtrail.runner.stage import stage_spec
from tagtrail.stages import align

POSE = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]
KEYS = ["model", "scale", "rotation_deg", "translation", "inliers", "common_tags", "rms_m"]


def tag_map(ids: np.ndarray, pos: np.ndarray) -> pd.DataFrame:
    df = pd.DataFrame(pos, columns=["x_m", "y_m", "z_m"])
    df.insert(0, "tag_id", ids.astype(np.int64))
    df[["qx", "qy", "qz", "qw"]] = [0.0, 0.0, 0.0, 1.0]
    df["n_obs"], df["size_m"] = 10, 0.2
    return df


def trajectory(P: np.ndarray, R: np.ndarray) -> pd.DataFrame:
    df = pd.DataFrame(P, columns=["x_m", "y_m", "z_m"])
    df.insert(0, "t_ns", 1_700_000_000_000_000_000 + np.arange(len(P), dtype=np.int64) * 10**8)
    df[["qx", "qy", "qz", "qw"]] = Rotation.from_matrix(R).as_quat()
    df["n_tags"] = 3
    return df


def upright_circle(n: int = 60, r: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Camera on a circle in the floor (xz, world y up) looking along the path."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    P = np.stack([r * np.cos(a), np.full(n, 0.03), r * np.sin(a)], axis=1)
    f = np.stack([-np.sin(a), np.zeros(n), np.cos(a)], axis=1)
    y = np.tile([0.0, -1.0, 0.0], (n, 1))
    return P, np.stack([np.cross(y, f), y, f], axis=2)


def headings_xz(R: np.ndarray) -> np.ndarray:
    return np.arctan2(R[:, 2, 2], R[:, 0, 2])


@pytest.fixture
def scene() -> dict[str, object]:
    """Reference world + a query world related by a planar similarity (xz) and 30 % bad tags."""
    rng = np.random.default_rng(11)
    ids = np.arange(20)
    ref_tags = np.column_stack(
        [rng.uniform(-3, 3, 20), rng.uniform(-0.05, 0.3, 20), rng.uniform(-3, 3, 20)]
    )
    s, deg, t = 1.03, -54.9, np.array([-2.04, -0.11])  # query → reference, in (x, z)
    a = math.radians(deg)
    R2 = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    to_query = lambda p: np.column_stack(  # noqa: E731  (inverse of the planar map)
        [((p[:, [0, 2]] - t) @ R2 / s)[:, 0], p[:, 1], ((p[:, [0, 2]] - t) @ R2 / s)[:, 1]]
    )
    q_tags = to_query(ref_tags) + rng.normal(0, 1e-4, (20, 3)) * [1, 0, 1]
    bad = rng.choice(20, 6, replace=False)
    q_tags[bad] += np.column_stack([rng.uniform(0.3, 1, 6), np.zeros(6), rng.uniform(-1, -0.3, 6)])
    P, R = upright_circle()
    Pq_ref, Rq_ref = P[::3] * 0.8 + [0.3, 0.0, -0.2], R[::3]  # query poses, reference world
    R_about_n = Rotation.from_rotvec(a * np.array([0.0, -1.0, 0.0])).as_matrix()  # n = −y
    return {
        "ref_tags": tag_map(ids, ref_tags),
        "q_tags": tag_map(ids, q_tags),
        "ref_traj": trajectory(P, R),
        "q_traj": trajectory(to_query(Pq_ref), R_about_n.T @ Rq_ref),
        "truth": (Pq_ref, Rq_ref),
        "s": s,
        "deg": deg,
        "t": t,
        "bad": bad,
    }


def run(scene: dict, **params: object) -> dict:
    return align.run(
        scene["q_tags"],
        scene["ref_tags"],
        scene["q_traj"],
        scene["ref_traj"],
        align.Params(**params),
    )


@pytest.mark.parametrize("plane", ["xz", "auto"])
def test_recovers_planar_similarity_with_outliers(scene: dict, plane: str) -> None:
    out = run(scene, plane=plane)
    al, traj = out["alignment"], out["trajectory"]
    assert list(al.model_dump()) == KEYS
    assert al["model"] == "similarity" and al["common_tags"] == 20 and al["inliers"] == 14
    assert al["scale"] == pytest.approx(scene["s"], abs=1e-4)
    assert al["rotation_deg"] == pytest.approx(scene["deg"], abs=0.01)
    np.testing.assert_allclose(al["translation"], scene["t"], atol=1e-3)
    P_true, R_true = scene["truth"]
    np.testing.assert_allclose(traj[["x_m", "y_m", "z_m"]].to_numpy(), P_true, atol=1e-3)
    R = Rotation.from_quat(traj[["qx", "qy", "qz", "qw"]].to_numpy()).as_matrix()
    dh = np.degrees(np.angle(np.exp(1j * (headings_xz(R) - headings_xz(R_true)))))
    assert np.abs(dh).max() < 0.01
    assert list(traj.columns) == list(scene["q_traj"].columns)
    np.testing.assert_array_equal(traj["t_ns"], scene["q_traj"]["t_ns"])


def test_rigid_keeps_scale_one(scene: dict) -> None:
    scene["q_tags"][["x_m", "z_m"]] *= 1.03  # undo the query's scale: a rigid problem
    al = run(scene, plane="xz", model="rigid")["alignment"]
    assert al["scale"] == 1.0 and al["rotation_deg"] == pytest.approx(-54.9, abs=0.01)


def test_se3_recovers_a_3d_transform() -> None:
    rng = np.random.default_rng(1)
    ref_tags = rng.uniform(-3, 3, (8, 3))
    Rt = Rotation.from_rotvec([0.2, -0.8, 0.3]).as_matrix()
    tt = np.array([0.5, 0.1, -1.0])
    q_tags = (ref_tags - tt) @ Rt  # query = inv(T) · reference
    P, R = upright_circle(12)
    q_traj = trajectory((P - tt) @ Rt, Rt.T @ R)
    out = align.run(
        tag_map(np.arange(8), q_tags),
        tag_map(np.arange(8), ref_tags),
        q_traj,
        trajectory(P, R),
        align.Params(model="se3"),
    )
    assert out["alignment"]["inliers"] == 8 and len(out["alignment"]["translation"]) == 3
    np.testing.assert_allclose(out["trajectory"][["x_m", "y_m", "z_m"]].to_numpy(), P, atol=1e-9)
    Rq = Rotation.from_quat(out["trajectory"][["qx", "qy", "qz", "qw"]].to_numpy()).as_matrix()
    np.testing.assert_allclose(Rq, R, atol=1e-9)


def test_align_none_keeps_the_query_frame(scene: dict) -> None:
    out = run(scene, align="none")
    pd.testing.assert_frame_equal(out["trajectory"], scene["q_traj"])
    assert out["alignment"].model_dump() == {
        "model": "none",
        "scale": 1.0,
        "rotation_deg": 0.0,
        "translation": [0.0, 0.0],
        "inliers": 0,
        "common_tags": 20,
        "rms_m": None,
    }


def test_auto_without_enough_common_tags_warns(scene: dict, caplog: pytest.LogCaptureFixture):
    scene["q_tags"] = scene["q_tags"].iloc[:1]
    with caplog.at_level(logging.WARNING, logger="tagtrail.stages.align"):
        out = run(scene)
    assert "only 1 common tag" in caplog.text and "align=none" in caplog.text
    assert out["alignment"]["model"] == "none"
    pd.testing.assert_frame_equal(out["trajectory"], scene["q_traj"])


def test_tags_without_common_tags_is_an_error(scene: dict) -> None:
    scene["q_tags"]["tag_id"] += 100
    with pytest.raises(DataError, match="only 0 common tag.*same tags"):
        run(scene, align="tags")


def test_scale_out_of_range_is_an_error_unless_allowed(scene: dict) -> None:
    scene["q_tags"][["x_m", "z_m"]] /= 1.2  # scale 1.03 · 1.2 ≈ 1.24
    with pytest.raises(DataError, match=r"alignment scale 1\.23.* different tag sizes"):
        run(scene, plane="xz")
    assert run(scene, plane="xz", allow_scale=True)["alignment"]["scale"] == pytest.approx(
        1.236, abs=1e-3
    )


def test_stage_contract() -> None:
    spec = stage_spec("align", align)
    assert spec.scope == "query" and spec.outputs == ("alignment", "trajectory")
    assert str(spec.inputs["ref_tag_map"]) == "reference:optimize.tag_map"
    with pytest.raises(pydantic.ValidationError):
        align.Params(plane="zx")
    with pytest.raises(pydantic.ValidationError):
        align.Params(ransac_threshold=0.1)
