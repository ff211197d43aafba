"""Per-frame camera pose fusion (Eq. 3.8) and multi-tag PnP."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.geometry.fusion import (
    camera_estimates,
    frame_poses,
    fuse_mean,
    fuse_robust,
    multi_tag_pnp,
    tag_corners,
)
from tagtrail.geometry.se3 import (
    R_from_rotvec,
    inv,
    make_T,
    pose_error,
    transform_points,
)
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
    noisy = est @ make_T(
        R_from_rotvec(rng.normal(scale=0.005, size=(15, 3))), rng.normal(scale=0.01, size=(15, 3))
    )
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


# --- frame_poses ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def corridor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A pipeline on a simulated corridor (1-3 tags a frame, noisy corners)."""
    root = tmp_path_factory.mktemp("fp")
    rec = simulate("corridor", root, frames=90, detections=True, corner_noise_px=0.8, seed=5)[
        "corridor"
    ]
    (root / "pipeline.yaml").write_text(
        f"reference: corridor\ndatasets:\n  corridor:\n    source: {rec}\n"
    )
    return root / "pipeline.yaml"


def test_trajectory_stage_poses_single_tag_frames_by_fusion_and_the_rest_by_pnp(
    corridor: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import load_pipeline
    from tagtrail.stages import REGISTRY

    runner = Runner(load_pipeline(corridor, REGISTRY, ["trajectory.method=pnp"]))
    with caplog.at_level("INFO", logger="tagtrail.stages.trajectory"):
        runner.run(["trajectory"])
    key = runner.key_of("trajectory", "corridor")
    assert key is not None
    traj = runner.store.load("trajectory", key, "trajectory")
    n_pnp = int(caplog.text.split("multi-tag PnP for ")[1].split(" of ")[0])
    assert 0 < n_pnp < len(traj) and (traj["n_tags"] >= 2).sum() >= n_pnp


def test_frame_poses_frame_without_observations_is_nan() -> None:
    T = make_T(np.eye(3), [[1.0, 2.0, 3.0]])
    res = frame_poses(
        T,
        np.eye(4)[None],
        np.array([1]),
        2,
        method="lsq",
        loss="soft_l1",
        f_scale=0.1,
        rot_weight_m=1.0,
        ransac_px=3.0,
    )
    assert res.n_tags.tolist() == [0, 1]
    assert np.isnan(res.world_T_cam[0]).all()
    assert np.allclose(res.world_T_cam[1], T[0], atol=1e-12)
