"""Stage trajectory (Eq. 3.8): avg / lsq / pnp fusion against known camera poses."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.errors import DataError
from tagtrail.geometry.se3 import T_from_xyz_quat, make_T, pose_error
from tagtrail.runner.stage import stage_spec
from tagtrail.stages import trajectory
from tests.stages.mapping_scene import (
    CAMERA,
    POSE,
    Scene,
    detections,
    observations,
    ring_scene,
    tag_map_frame,
)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return ring_scene(n_tags=16, r_cam=1.0, half_fov_deg=50.0, n_frames=120)


def run(scene: Scene, obs: pd.DataFrame, method: str, det: pd.DataFrame | None = None,
        tag_map: pd.DataFrame | None = None) -> pd.DataFrame:
    det = detections(scene) if det is None else det
    tm = tag_map_frame(scene.world_T_tag) if tag_map is None else tag_map
    params = trajectory.Params(method=method)  # type: ignore[arg-type]
    return trajectory.run(obs, det, CAMERA, tm, params)["trajectory"]


def frame_errors(scene: Scene, traj: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    idx = np.searchsorted(scene.t_ns, traj["t_ns"].to_numpy())
    T = T_from_xyz_quat(traj[POSE[:3]].to_numpy(), traj[POSE[3:]].to_numpy())
    dt, dr = pose_error(T, scene.world_T_cam[idx])
    return dt, np.rad2deg(dr)


def flipped(scene: Scene, frac: float = 0.08, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """cam_T_tag with a fraction of observations flipped 40 deg about the tag's x axis."""
    T = scene.cam_T_tag()
    bad = np.random.default_rng(seed).random(len(T)) < frac
    flip = make_T(Rotation.from_euler("x", 40, degrees=True).as_matrix(), np.zeros(3))
    T[bad] = T[bad] @ flip
    return T, bad


def test_stage_contract() -> None:
    spec = stage_spec("trajectory", trajectory)
    assert spec.outputs == ("trajectory",)
    assert str(spec.inputs["tag_map"]) == "optimize.tag_map"
    assert str(spec.inputs["camera"]) == "extract.camera"


EXTRA = ["std_pos_m", "std_rot_deg", "motion_prior"]


@pytest.mark.parametrize("method", ["avg", "lsq", "pnp", "joint-none"])
def test_exact_observations_give_exact_poses(scene: Scene, method: str) -> None:
    if method == "joint-none":  # the joint method without the motion prior: exact too
        params = trajectory.Params(method="joint", motion="none")
        traj = trajectory.run(observations(scene), detections(scene), CAMERA,
                              tag_map_frame(scene.world_T_tag), params)["trajectory"]
        assert np.isfinite(traj["std_pos_m"]).all() and not traj["motion_prior"].any()
    else:
        traj = run(scene, observations(scene), method)
        assert traj["std_pos_m"].isna().all()
    assert list(traj.columns) == ["t_ns", *POSE, "n_tags", *EXTRA]
    assert traj["t_ns"].is_monotonic_increasing and len(traj) == len(scene.t_ns)
    assert traj["n_tags"].tolist() == np.bincount(scene.frame).tolist()
    dt, dr = frame_errors(scene, traj)
    assert dt.max() < 1e-9 and dr.max() < 1e-7


def test_pnp_is_immune_to_ippe_flips(scene: Scene) -> None:
    T, bad = flipped(scene)
    obs = observations(scene, T)
    hit = np.isin(np.arange(len(scene.t_ns)), scene.frame[bad])
    err = {m: frame_errors(scene, run(scene, obs, m))[0][hit] for m in ("avg", "lsq", "pnp")}
    assert err["pnp"].max() < 1e-9  # corners are unaffected by the pose solver's flip
    assert err["avg"].mean() > 0.05
    assert err["lsq"].mean() < err["avg"].mean()


def test_single_tag_frames_use_the_lower_reprojection_solution(scene: Scene) -> None:
    T_bad, _ = flipped(scene, frac=1.0)
    amb = np.full(len(T_bad), 0.8)
    obs = observations(scene, T_bad, ambiguity=amb, alt_cam_T_tag=scene.cam_T_tag())
    obs["reproj_px"], obs["alt_reproj_px"] = 2.0, 0.5  # the "alt" solution fits better
    dt, _ = frame_errors(scene, run(scene, obs, "lsq"))
    assert dt.max() < 1e-9


def test_frames_without_mapped_tags_get_no_pose(scene: Scene) -> None:
    keep = np.arange(16) % 4 != 0
    tm = tag_map_frame(scene.world_T_tag[keep], np.flatnonzero(keep))
    traj = run(scene, observations(scene), "pnp", tag_map=tm)
    mapped = keep[scene.tag]
    assert len(traj) == len(np.unique(scene.frame[mapped]))
    assert traj["n_tags"].sum() == mapped.sum()
    assert frame_errors(scene, traj)[0].max() < 1e-9


def test_pnp_without_detections_falls_back_to_lsq(
    scene: Scene, caplog: pytest.LogCaptureFixture
) -> None:
    obs = observations(scene)
    with caplog.at_level(logging.WARNING, logger="tagtrail.stages.trajectory"):
        traj = trajectory.run(obs, pd.DataFrame(), {}, tag_map_frame(scene.world_T_tag),
                              trajectory.Params(method="pnp"))["trajectory"]
    assert "using lsq" in caplog.text
    assert frame_errors(scene, traj)[0].max() < 1e-9


def test_empty_map_is_a_data_error(scene: Scene) -> None:
    with pytest.raises(DataError, match="tag map is empty"):
        run(scene, observations(scene), "lsq", tag_map=tag_map_frame(scene.world_T_tag[:0]))
    none_seen = tag_map_frame(scene.world_T_tag[:1], np.array([99]))
    assert run(scene, observations(scene), "lsq", tag_map=none_seen).empty
