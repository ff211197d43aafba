"""Stage eval: errors against a SPEC ground-truth folder, including a different anchor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.errors import DataError
from tagtrail.geometry.se3 import inv, make_T, quat_xyzw_from_R
from tagtrail.io.layouts import read_tag_map, read_trajectory, write_tag_map, write_trajectory_csv
from tagtrail.runner.stage import stage_spec
from tagtrail.schemas.inputs import GroundTruth
from tagtrail.stages import evaluate as eval_stage
from tests.stages.mapping_scene import POSE, ring_scene, tag_map_frame

STATS = {"mean", "median", "rmse", "p95", "max", "min"}


def traj_frame(t_ns: np.ndarray, T: np.ndarray) -> pd.DataFrame:
    df = pd.DataFrame({"t_ns": t_ns})
    df[POSE] = np.concatenate([T[:, :3, 3], quat_xyzw_from_R(T[:, :3, :3])], axis=1)
    df["n_tags"] = np.int32(1)
    return df


@pytest.fixture()
def world(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray, np.ndarray]:
    """GT folder with world = tag 0's frame; returns (folder, t_ns, world_T_cam, world_T_tag)."""
    scene = ring_scene(n_frames=40)
    tags, cams = scene.anchor_frame(0)
    gt = tmp_path / "ground_truth"
    write_trajectory_csv(gt / "trajectory.csv", traj_frame(scene.t_ns, cams))
    write_tag_map(gt, tag_map_frame(tags), anchor_id=0)
    return gt, scene.t_ns, cams, tags


def evaluate(gt: Path, traj: pd.DataFrame, tags: pd.DataFrame, raw: pd.DataFrame | None = None):
    raw = traj if raw is None else raw
    gt_tags, gt_anchor = read_tag_map(gt)
    truth = GroundTruth(gt, read_trajectory(gt), gt_tags, gt_anchor)
    return eval_stage.run(traj, raw, tags, truth, eval_stage.Params())["evaluation"]


def test_stage_contract() -> None:
    spec = stage_spec("eval", eval_stage)
    assert str(spec.inputs["ground_truth"]) == "ground_truth"
    assert str(spec.inputs["trajectory"]) == "smooth.trajectory"


def test_exact_estimate_in_gt_frame(world) -> None:
    gt, t_ns, cams, tags = world
    ev = evaluate(gt, traj_frame(t_ns, cams), tag_map_frame(tags))
    assert ev["anchor_id"] == 0 and ev["gt_anchor_id"] == 0
    for key in ("trajectory", "trajectory_raw", "tags"):
        block = ev[key]
        assert set(block["position_m"].model_dump()) == STATS
        assert set(block["angle_deg"].model_dump()) == STATS
        assert block["position_m"]["max"] < 1e-9 and block["angle_deg"]["max"] < 1e-6
    assert ev["trajectory"]["n"] == 40 and ev["trajectory"]["coverage"] == 1.0
    assert ev["tags"]["n"] == 11  # the anchor is left out


def test_estimate_anchored_on_another_tag(world) -> None:
    """The map's gauge is tag 5: GT is re-expressed in tag 5's frame before comparing."""
    gt, t_ns, cams, tags = world
    a_T_w = inv(tags[5])
    ev = evaluate(gt, traj_frame(t_ns, a_T_w @ cams), tag_map_frame(a_T_w @ tags))
    assert ev["anchor_id"] == 5 and ev["gt_anchor_id"] == 0
    assert ev["trajectory"]["position_m"]["max"] < 1e-9 and ev["tags"]["position_m"]["max"] < 1e-9


def test_known_errors(world) -> None:
    gt, t_ns, cams, tags = world
    off = make_T(Rotation.from_euler("z", 2.0, degrees=True).as_matrix(), [0.1, 0.0, 0.0])
    est = traj_frame(t_ns[::2], cams[::2] @ off)  # every other frame: coverage 0.5
    shifted = tags.copy()
    shifted[1:, 0, 3] += 0.01 * np.arange(1, 12)  # tag k moved k cm along world x
    ev = evaluate(gt, est, tag_map_frame(shifted), raw=traj_frame(t_ns, cams))
    tr = ev["trajectory"]
    assert tr["n"] == 20 and tr["coverage"] == 0.5
    assert tr["position_m"]["mean"] == pytest.approx(0.1)
    assert tr["angle_deg"]["min"] == pytest.approx(2.0)
    assert ev["trajectory_raw"]["position_m"]["max"] < 1e-9
    pos = ev["tags"]["position_m"]
    assert pos["min"] == pytest.approx(0.01) and pos["max"] == pytest.approx(0.11)
    assert pos["mean"] == pytest.approx(0.06) and pos["median"] == pytest.approx(0.06)
    assert pos["rmse"] == pytest.approx(np.sqrt(np.mean((0.01 * np.arange(1, 12)) ** 2)))


def test_no_matching_stamps_and_unknown_anchor(world) -> None:
    gt, t_ns, cams, tags = world
    ev = evaluate(gt, traj_frame(t_ns + 1, cams), tag_map_frame(tags))
    assert ev["trajectory"]["n"] == 0 and ev["trajectory"]["position_m"]["mean"] is None
    foreign = tag_map_frame(np.eye(4)[None], np.array([42]))
    with pytest.raises(DataError, match="anchor tag 42 is not in the ground-truth"):
        evaluate(gt, traj_frame(t_ns, cams), foreign)


def test_gauge_free_errors_remove_the_anchor_pose_error(world) -> None:
    """A map and trajectory that are exact but for a 0.5 deg turn and 1 cm shift of the whole
    (the anchor's own pose error): large anchored errors, zero once rigidly aligned; a real
    distortion (one tag 2 cm off) survives the alignment."""
    gt, t_ns, cams, tags = world
    turn = make_T(Rotation.from_euler("y", 0.5, degrees=True).as_matrix(), [0.01, 0.0, 0.0])
    ev = evaluate(gt, traj_frame(t_ns, turn @ cams), tag_map_frame(turn @ tags))
    assert ev["tags"]["position_m"]["mean"] > 0.02
    gf = ev["gauge_free"]
    assert gf["rotation_deg"] == pytest.approx(0.5) and gf["translation_m"] > 0.005
    for key in ("trajectory", "tags"):
        assert gf[key]["position_m"]["max"] < 1e-9 and gf[key]["angle_deg"]["max"] < 1e-6
    assert gf["tags"]["n"] == 11 and gf["trajectory"]["n"] == 40
    bent = tags.copy()
    bent[4, 0, 3] += 0.02
    gf = evaluate(gt, traj_frame(t_ns, cams), tag_map_frame(bent))["gauge_free"]
    assert 0.01 < gf["tags"]["position_m"]["max"] < 0.02
    few = evaluate(gt, traj_frame(t_ns, cams), tag_map_frame(tags[:2]))
    assert few["gauge_free"] is None
