"""Stage trajectory (Eq. 3.8): avg / lsq / pnp fusion against known camera poses."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.errors import DataError
from tagtrail.geometry.joint import SHIFT_SIGMA_BOUND
from tagtrail.geometry.se3 import T_from_xyz_quat, make_T, pose_error
from tagtrail.runner.stage import stage_spec
from tagtrail.schemas.artifacts import ALONE_POSE_COLS, EVIDENCE_COLS
from tagtrail.stages import trajectory
from tests.stages.mapping_scene import (
    CAMERA,
    POSE,
    Scene,
    detections,
    map_report,
    observations,
    ring_scene,
    tag_map_frame,
)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return ring_scene(n_tags=16, r_cam=1.0, half_fov_deg=50.0, n_frames=120)


def run(
    scene: Scene,
    obs: pd.DataFrame,
    method: str,
    det: pd.DataFrame | None = None,
    tag_map: pd.DataFrame | None = None,
) -> pd.DataFrame:
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


EXTRA = ["std_pos_m", "std_rot_deg", "motion_prior", *EVIDENCE_COLS, *ALONE_POSE_COLS]


@pytest.mark.parametrize("method", ["avg", "lsq", "pnp", "joint-none"])
def test_exact_observations_give_exact_poses(scene: Scene, method: str) -> None:
    if method == "joint-none":  # the joint method without the motion prior: exact too
        traj = trajectory.run(
            observations(scene),
            detections(scene),
            CAMERA,
            tag_map_frame(scene.world_T_tag),
            trajectory.Params(method="joint"),
            map_report=map_report(motion="none"),
        )["trajectory"]
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


def test_frames_of_several_tags_take_the_solution_the_map_agrees_with(scene: Scene) -> None:
    """A mirrored solution first (lower reprojection, ambiguity 0.3), the true one second: the
    frame-by-frame fusion takes, per observation, the one the map agrees with in its frame."""
    T_bad, bad = flipped(scene, frac=0.15, seed=1)
    obs = observations(
        scene,
        T_bad,
        ambiguity=np.full(len(T_bad), 0.3),
        alt_cam_T_tag=np.where(bad[:, None, None], scene.cam_T_tag(), T_bad),
    )
    assert bad.sum() > 30 and (np.bincount(scene.frame) > 1).all()
    dt, dr = frame_errors(scene, run(scene, obs, "lsq"))
    assert dt.max() < 1e-9 and dr.max() < 1e-7


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
        traj = trajectory.run(
            obs,
            pd.DataFrame(),
            {},
            tag_map_frame(scene.world_T_tag),
            trajectory.Params(method="pnp"),
        )["trajectory"]
    assert "using lsq" in caplog.text
    assert frame_errors(scene, traj)[0].max() < 1e-9


def test_empty_map_is_a_data_error(scene: Scene) -> None:
    with pytest.raises(DataError, match="tag map is empty"):
        run(scene, observations(scene), "lsq", tag_map=tag_map_frame(scene.world_T_tag[:0]))
    none_seen = tag_map_frame(scene.world_T_tag[:1], np.array([99]))
    assert run(scene, observations(scene), "lsq", tag_map=none_seen).empty


def _noisy_detections(scene: Scene, sigma_px: float, seed: int = 0) -> pd.DataFrame:
    det = detections(scene)
    cols = [f"c{k}{a}" for k in range(4) for a in "xy"]
    rng = np.random.default_rng(seed)
    det[cols] = det[cols].to_numpy() + rng.normal(0.0, sigma_px, (len(det), 8))
    return det


def test_joint_frames_report_how_far_the_motion_prior_moved_them(scene: Scene) -> None:
    """Each frame's evidence: its corner RMS beside that of the frame on its own corners, and the
    prior's change, which is what solving the frames without the prior gives (the map fixed)."""
    det = _noisy_detections(scene, 0.3)
    tm = tag_map_frame(scene.world_T_tag)
    obs = observations(scene)
    traj = trajectory.run(
        obs, det, CAMERA, tm, trajectory.Params(), map_report=map_report(corner_sigma_px=0.3)
    )
    alone = trajectory.run(
        obs,
        det,
        CAMERA,
        tm,
        trajectory.Params(),
        map_report=map_report(corner_sigma_px=0.3, motion="none"),
    )["trajectory"]
    traj = traj["trajectory"]
    assert (traj["shift_m"] > 0).all() and (alone["shift_m"] == 0).all()
    np.testing.assert_allclose(alone["reproj_px"], alone["alone_reproj_px"])
    moved = np.linalg.norm(traj[POSE[:3]].to_numpy() - alone[POSE[:3]].to_numpy(), axis=1)
    np.testing.assert_allclose(traj["shift_m"], moved, atol=1e-6)
    np.testing.assert_allclose(traj["alone_reproj_px"], alone["reproj_px"], atol=1e-6)
    np.testing.assert_allclose(traj[ALONE_POSE_COLS[:3]], alone[POSE[:3]], atol=1e-6)
    np.testing.assert_allclose(alone[ALONE_POSE_COLS], alone[POSE])
    # the prior holds the frames nearer the truth, and within what their corners allow
    assert np.median(frame_errors(scene, traj)[0]) < np.median(frame_errors(scene, alone)[0])
    assert np.median(traj["reproj_px"]) <= 1.2 * np.median(traj["alone_reproj_px"])
    assert (traj["shift_sigma"] > SHIFT_SIGMA_BOUND).mean() <= 0.02


def test_a_prior_far_too_stiff_still_leaves_the_frames_with_their_evidence(scene: Scene) -> None:
    """A motion prior 100x stiffer than the defaults (the ring turns at 0.5 m/s, 0.27 m/s^2):
    its robust (Cauchy) loss lets go where the motion disagrees, so the frames stay within their
    own corners' uncertainty (measured: 1 % beyond the 99.9 % bound, corner RMS 1.10x)."""
    det = _noisy_detections(scene, 0.3)
    traj = trajectory.run(
        observations(scene),
        det,
        CAMERA,
        tag_map_frame(scene.world_T_tag),
        trajectory.Params(),
        map_report=map_report(corner_sigma_px=0.3, motion=0.001),
    )["trajectory"]
    assert (traj["shift_sigma"] > SHIFT_SIGMA_BOUND).mean() <= 0.02
    assert np.median(traj["reproj_px"]) <= 1.2 * np.median(traj["alone_reproj_px"])


@pytest.mark.parametrize("method", ["joint", "lsq"])
def test_a_map_at_another_scale_than_pnp_sizes_gives_the_maps_scale(
    scene: Scene, method: str
) -> None:
    """pnp solved with 0.16 m tags, the map says 0.2 m (a surveyed similarity rescaled it, or a
    query uses the reference's map): the same image is a world 1.25x as large, and the
    trajectory comes out in it."""
    W = scene.world_T_tag.copy()
    W[:, :3, 3] *= 1.25
    tm = tag_map_frame(W)
    tm["size_m"] = 0.2
    traj = trajectory.run(
        observations(scene),
        detections(scene),
        CAMERA,
        tm,
        trajectory.Params(method=method),  # type: ignore[arg-type]
        map_report=map_report(motion="none"),
    )["trajectory"]
    idx = np.searchsorted(scene.t_ns, traj["t_ns"].to_numpy())
    np.testing.assert_allclose(
        traj[POSE[:3]].to_numpy(), 1.25 * scene.world_T_cam[idx, :3, 3], atol=1e-6
    )
