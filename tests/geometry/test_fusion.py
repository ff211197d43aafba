"""Per-frame camera pose fusion (Eq. 3.8) and multi-tag PnP."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import (
    camera_estimates,
    frame_poses,
    fuse_mean,
    fuse_robust,
    multi_tag_pnp,
    tag_corners,
)
from tagtrail.geometry.ippe import best_pose
from tagtrail.geometry.se3 import (
    R_from_rotvec,
    T_from_xyz_quat,
    inv,
    make_T,
    pose_error,
    transform_points,
    xyz_quat_from_T,
)
from tagtrail.schemas.artifacts import CORNER_COLS, POSE_COLS, ippe_solutions
from tagtrail.sim.simulate import simulate


def test_camera_estimates_cancel_frames() -> None:
    rng = np.random.default_rng(0)
    world_T_cam = make_T(R_from_rotvec(rng.normal(size=3)), rng.normal(size=3))
    world_T_tag = make_T(R_from_rotvec(rng.normal(size=(4, 3))), rng.normal(size=(4, 3)))
    est = camera_estimates(world_T_tag, inv(world_T_cam) @ world_T_tag)
    assert np.allclose(est, world_T_cam, atol=1e-12)


def test_fusion_exact_and_robust_to_one_bad_tag() -> None:
    rng = np.random.default_rng(1)
    truth = make_T(R_from_rotvec(rng.normal(size=(3, 3))), rng.normal(size=(3, 3)))
    group = np.repeat(np.arange(3), 5)
    est = np.repeat(truth, 5, axis=0)
    for fuse in (fuse_mean, fuse_robust):
        assert np.allclose(fuse(est, group, 3), truth, atol=1e-12)
    noisy = est @ make_T(R_from_rotvec(rng.normal(scale=0.005, size=(15, 3))),
                         rng.normal(scale=0.01, size=(15, 3)))
    flip = make_T(Rotation.from_euler("x", 40, degrees=True).as_matrix(), [0.5, 0, 0])
    noisy[0] = noisy[0] @ flip
    dt_mean, _ = pose_error(fuse_mean(noisy, group, 3)[0], truth[0])
    dt_rob, dr_rob = pose_error(fuse_robust(noisy, group, 3, f_scale=0.05)[0], truth[0])
    assert dt_rob < 0.03 < 0.08 < dt_mean
    assert np.rad2deg(dr_rob) < 1.0


def _wall_view(seed: int, n_tags: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coplanar tags on a wall seen by a camera 2 m away: world corners, normalised px, pose."""
    rng = np.random.default_rng(seed)
    world_T_tag = make_T(np.eye(3), np.c_[rng.uniform(-0.8, 0.8, (n_tags, 2)), np.zeros(n_tags)])
    corners = tag_corners(np.full(n_tags, 0.16))
    pts_w = transform_points(world_T_tag[:, None], corners).reshape(-1, 3)
    R = Rotation.from_euler("x", 180, degrees=True).as_matrix() @ R_from_rotvec([0.1, 0.2, 0.0])
    world_T_cam = make_T(R, [0.2, -0.1, 2.0])
    p = transform_points(inv(world_T_cam), pts_w)
    return pts_w, p[:, :2] / p[:, 2:], world_T_cam


def test_multi_tag_pnp_on_coplanar_tags() -> None:
    pts_w, norm, truth = _wall_view(2)
    pose, n_inl = multi_tag_pnp(pts_w, norm, ransac_thresh=3 / 500)
    assert pose is not None and n_inl == len(pts_w)
    dt, dr = pose_error(pose, truth)
    assert dt < 1e-9 and dr < 1e-9


def test_multi_tag_pnp_rejects_a_wrong_tag() -> None:
    pts_w, norm, truth = _wall_view(3, n_tags=4)
    rng = np.random.default_rng(4)
    norm = norm + rng.normal(scale=0.3 / 500, size=norm.shape)
    norm[:4] += 0.04  # one tag's corners 20 px off (e.g. a wrong map entry)
    pose, n_inl = multi_tag_pnp(pts_w, norm, ransac_thresh=3 / 500)
    assert pose is not None and n_inl == 12
    # Same answer as an oracle fit on the good tags only (noise-limited, not outlier-limited).
    oracle, _ = multi_tag_pnp(pts_w[4:], norm[4:], ransac_thresh=1.0)
    assert oracle is not None
    dt, dr = pose_error(pose, oracle)
    assert dt < 1e-6 and dr < 1e-6
    assert pose_error(pose, truth)[0] < 0.05
    assert multi_tag_pnp(pts_w[:4], norm[:4], ransac_thresh=3 / 500) == (None, 0)


# --- frame_poses: the trajectory stage's numbers, exactly ------------------------------------


def _stage_glue(observations, detections, camera, tag_map, params):  # noqa: ANN001, ANN202
    """The trajectory stage's table handling around :func:`frame_poses` (the call that replaces
    its per-frame code): ``trajectory.trajectory`` columns, and what frame_poses returned."""
    if isinstance(camera, dict):  # the extract.camera artifact as JSON
        camera = CameraModel.from_dict(camera) if camera else None
    ids = tag_map["tag_id"].to_numpy(np.int64)
    order = np.argsort(ids)
    ids = ids[order]
    mv = tag_map[POSE_COLS].to_numpy(np.float64)[order]
    W_map = T_from_xyz_quat(mv[:, :3], mv[:, 3:])
    obs = observations[observations["tag_id"].isin(ids)]
    obs = obs[~obs.duplicated(["frame_idx", "tag_id"], keep=False)]
    obs = obs.sort_values(["frame_idx", "tag_id"], kind="stable")
    uframe, group = np.unique(obs["frame_idx"].to_numpy(np.int64), return_inverse=True)
    t_ns = obs.groupby("frame_idx")["t_ns"].first().reindex(uframe).to_numpy(np.int64)
    k = np.searchsorted(ids, obs["tag_id"].to_numpy(np.int64))
    px = None
    if len(detections) > 0 and camera is not None and params.method in ("auto", "pnp"):
        det = detections.drop_duplicates(["frame_idx", "tag_id"], keep=False)
        det = det.set_index(["frame_idx", "tag_id"])[CORNER_COLS]
        key = pd.MultiIndex.from_arrays([obs["frame_idx"].to_numpy(), obs["tag_id"].to_numpy()])
        px = det.reindex(key).to_numpy(np.float64).reshape(-1, 4, 2)
    size = np.full(len(obs), np.nan)
    if "size_m" in tag_map.columns:
        size = tag_map["size_m"].to_numpy(np.float64)[order][k]
    if "size_m" in obs.columns:
        size = np.where(np.isfinite(size), size, obs["size_m"].to_numpy(np.float64))
    res = frame_poses(
        W_map[k], best_pose(*ippe_solutions(obs)), group, len(uframe),
        corners_px=px, size_m=size, camera=camera, method=params.method, loss=params.loss,
        f_scale=params.f_scale, rot_weight_m=params.rot_weight_m, ransac_px=params.ransac_px,
    )
    xyz, q = xyz_quat_from_T(res.world_T_cam)
    out = pd.DataFrame({"t_ns": t_ns})
    out[POSE_COLS] = np.concatenate([xyz, q], axis=1)
    out["n_tags"] = res.n_tags.astype(np.int32)
    return out.sort_values("t_ns", kind="stable").reset_index(drop=True), res


@pytest.fixture(scope="module")
def corridor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A pipeline on a simulated corridor (1-3 tags a frame, noisy corners)."""
    root = tmp_path_factory.mktemp("fp")
    rec = simulate("corridor", root, frames=90, detections=True, corner_noise_px=0.8,
                   seed=5)["corridor"]  # fmt: skip
    (root / "pipeline.yaml").write_text(f"reference: corridor\ndatasets:\n  corridor:\n"
                                        f"    source: {rec}\n")  # fmt: skip
    return root / "pipeline.yaml"


def _offline(pipeline: Path, *overrides: str) -> tuple[Any, ...]:
    """The real stages run by the runner: their inputs and output of ``trajectory``."""
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import load_pipeline
    from tagtrail.stages import REGISTRY

    pipe = load_pipeline(pipeline, REGISTRY, overrides)
    runner = Runner(pipe)
    runner.run(["trajectory"])

    def get(stage: str, output: str) -> Any:
        key = runner.key_of(stage, "corridor")
        assert key is not None
        return runner.store.load(stage, key, output)

    return (get("pnp", "observations"), get("extract", "detections"), get("extract", "camera"),
            get("optimize", "tag_map"), get("trajectory", "trajectory"),
            pipe.params_for("trajectory", "corridor"))  # fmt: skip


@pytest.mark.parametrize("method", ["auto", "avg", "lsq", "pnp"])
def test_frame_poses_equals_the_trajectory_stage(corridor: Path, method: str) -> None:
    obs, det, camera, tags, want, params = _offline(corridor, f"trajectory.method={method}",
                                                    "trajectory.f_scale=0.05")  # fmt: skip
    assert params.method == method
    got, res = _stage_glue(obs, det, camera, tags, params)
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    if method in ("auto", "pnp"):  # both branches taken: PnP frames and single-tag frames
        assert 0 < res.by_pnp.sum() < len(res.by_pnp)
        assert res.method == "pnp"
    else:
        assert not res.by_pnp.any() and res.method == method


def test_frame_poses_without_corners_is_lsq(corridor: Path) -> None:
    obs, det, camera, tags, want, params = _offline(corridor, "trajectory.method=lsq")
    got, res = _stage_glue(obs, det.iloc[:0], camera, tags, params.model_copy(
        update={"method": "pnp"}))  # fmt: skip
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    assert res.method == "lsq" and not res.by_pnp.any()


def test_frame_poses_frame_without_observations_is_nan() -> None:
    T = make_T(np.eye(3), [[1.0, 2.0, 3.0]])
    res = frame_poses(T, np.eye(4)[None], np.array([1]), 2, method="lsq", loss="soft_l1",
                      f_scale=0.1, rot_weight_m=1.0, ransac_px=3.0)  # fmt: skip
    assert res.n_tags.tolist() == [0, 1]
    assert np.isnan(res.world_T_cam[0]).all()
    assert np.allclose(res.world_T_cam[1], T[0], atol=1e-12)
