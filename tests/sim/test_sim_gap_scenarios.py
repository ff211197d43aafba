"""The odometry scenarios ``corridor_gap`` and ``room_blank_turn``: their stretches without a tag
in view hold no detection — in the synthetic detections (fast) and in the rendered images after
``tagtrail run``'s extract (slow) — while the frames around them see tags, and the robot moves
(the corridor) or turns (the room) through them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from tagtrail.cli import main
from tagtrail.io.layouts import POSE_COLS, read_trajectory
from tagtrail.sim import simulate
from tagtrail.sim.scenarios import BLANK_STRETCH_S, SimOptions, build
from tests.sim.helpers import read_topic

MIN_BLANK_S = {"corridor_gap": 5.0, "room_blank_turn": 2.0}


def _stretch(t_ns: np.ndarray, scenario: str) -> np.ndarray:
    """Frames inside the scenario's blank stretch."""
    lo, hi = BLANK_STRETCH_S[scenario]
    t_s = (t_ns - t_ns[0]) / 1e9
    inside: np.ndarray = (t_s >= lo) & (t_s <= hi)
    return inside


@pytest.mark.parametrize("scenario", ["corridor_gap", "room_blank_turn"])
def test_blank_stretch_in_synthetic_detections(scenario: str, tmp_path: Path) -> None:
    bag = simulate(scenario, tmp_path, detections=True)[scenario]
    dets = read_topic(bag, "/detections")
    t_ns = np.array([t for t, _ in dets])
    n = np.array([len(m.detections) for _, m in dets])
    inside = _stretch(t_ns, scenario)
    lo, hi = BLANK_STRETCH_S[scenario]
    assert hi - lo >= MIN_BLANK_S[scenario] and inside.sum() >= MIN_BLANK_S[scenario] * 30
    assert (n[inside] == 0).all()
    # tags before and after the stretch: the map is one piece on both sides
    t_s = (t_ns - t_ns[0]) / 1e9
    assert (n[(t_s > lo - 2) & (t_s < lo)] > 0).any() and (n[t_s > hi] > 0).mean() > 0.9
    scene = yaml.safe_load((bag / "ground_truth" / "scene.yaml").read_text())
    assert scene["scenario"] == scenario and (bag / "ground_truth/odometry_truth.csv").is_file()


def test_the_corridor_moves_and_the_room_turns_in_the_stretch() -> None:
    gap, turn = (build(s, SimOptions())[0] for s in ("corridor_gap", "room_blank_turn"))
    inside = _stretch(gap.t_ns, "corridor_gap")
    p = gap.scene_T_cam[inside, :2, 3]
    assert np.linalg.norm(p[-1] - p[0]) > 1.4  # 0.3 m/s for > 5 s
    inside = _stretch(turn.t_ns, "room_blank_turn")
    z = turn.scene_T_cam[inside, :2, 2]  # the optical axis, horizontal
    heading = np.unwrap(np.arctan2(z[:, 1], z[:, 0]))
    assert abs(heading[-1] - heading[0]) > np.radians(40)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["corridor_gap", "room_blank_turn"])
def test_blank_stretch_in_rendered_images(
    scenario: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Rendered, then ``tagtrail run extract`` (the demo's detector settings): zero detections
    in every frame of the stretch (the renderer's detector sees farther than the synthetic
    model)."""
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", scenario, "--out", "data"]) == 0
    bag = tmp_path / "data" / scenario
    (tmp_path / "pipeline.yaml").write_text(
        yaml.safe_dump(
            {
                "reference": scenario,
                "datasets": {scenario: {"source": f"data/{scenario}"}},
                "stages": {"extract": {"quad_decimate": 2.0, "min_decision_margin": 20}},
            }
        )
    )
    assert main(["run", "extract"]) == 0
    (frames_file,) = (tmp_path / "artifacts").rglob("*frames*.parquet")
    frames = pd.read_parquet(frames_file)
    inside = _stretch(frames["t_ns"].to_numpy(), scenario)
    assert inside.sum() >= MIN_BLANK_S[scenario] * 30
    assert (frames["n_det"].to_numpy()[inside] == 0).all()
    traj = read_trajectory(bag / "ground_truth" / "trajectory.csv")
    assert len(traj) == len(frames) and set(POSE_COLS) <= set(traj.columns)
