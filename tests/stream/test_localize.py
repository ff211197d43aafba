"""Live localization from simulated ``/detections`` + ``/camera_info`` (tagtrail.sim), checked
against the simulator's ground truth (which the code under test did not produce)."""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tagtrail.io.layouts import read_tag_map, read_trajectory
from tagtrail.sim.simulate import simulate
from tagtrail.stream import codec
from tagtrail.stream.localize import Localizer
from tagtrail.stream.replay import bag_messages
from tagtrail.stream.stats import Deferred, DropError
from tests.stream.helpers import Collector, free_port, localize_replayed, loopback, running

N_FRAMES = 45


def _sim(tmp: Path, noise_px: float) -> Path:
    return simulate(
        "circle", tmp, frames=N_FRAMES, detections=True, corner_noise_px=noise_px, seed=3
    )["circle"]


@pytest.fixture(scope="module")
def exact(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _sim(tmp_path_factory.mktemp("loc_exact"), 0.0)


@pytest.fixture(scope="module")
def noisy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _sim(tmp_path_factory.mktemp("loc_noisy"), 0.1)


def _errors_m(poses: list[bytes], gt: pd.DataFrame) -> np.ndarray:
    g = gt.set_index("t_ns")
    err = []
    for raw in poses:
        p = codec.decode_pose(raw)
        row = g.loc[p.sec * 1_000_000_000 + p.nanosec]
        err.append(np.linalg.norm([p.x - row.x_m, p.y - row.y_m, p.z - row.z_m]))
    return np.asarray(err)


def test_exact_detections_give_the_exact_pose(exact: Path) -> None:
    """Noise-free corners: the chain (CDR, −0.5 px, undistortion, PnP, map) is exact."""
    loc = Localizer(read_tag_map(exact / "ground_truth" / "tag_map.yaml")[0])
    msgs = bag_messages(exact, ["/camera_info", "/detections"])
    first_det = msgs.keys.index("detections")
    with pytest.raises(Deferred):  # before any CameraInfo: kept until it comes
        loc.on_detections(msgs.payloads[first_det])
    kept = loc.on_camera_info(msgs.payloads[msgs.keys.index("camera_info")])
    assert [k for k, _ in kept] == ["tag_only_pose"]
    out = [p for _, p in kept]
    for i, (key, payload) in enumerate(zip(msgs.keys, msgs.payloads, strict=True)):
        if key == "camera_info":
            assert loc.on_camera_info(payload) == []
        elif i != first_det:
            out += [p for _, p in loc.on_detections(payload)]
    assert len(out) == N_FRAMES
    err = _errors_m(out, read_trajectory(exact / "ground_truth" / "trajectory.csv"))
    assert err.max() < 1e-6, err.max()
    with pytest.raises(DropError) as info:
        loc.on_detections(b"\x00\x01\x00\x00garbage")
    assert info.value.reason == "malformed"


def test_a_repeated_camera_info_is_not_parsed_again(
    exact: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """CameraInfo that differs from the last one taken only in its stamp is not parsed again
    (it precedes each frame: ~0.3 ms of latency); one that differs in anything else is, and
    a garbled one is refused as before."""
    loc = Localizer(read_tag_map(exact / "ground_truth" / "tag_map.yaml")[0])
    raw = bag_messages(exact, ["/camera_info"]).payloads[0]
    msg = codec.deserialize(raw, "sensor_msgs/msg/CameraInfo")
    parsed: list[bytes] = []
    deserialize = codec.deserialize
    monkeypatch.setattr(codec, "deserialize", lambda d, t: parsed.append(d) or deserialize(d, t))
    loc.on_camera_info(raw)
    first = loc.camera
    msg.header.stamp.sec += 7
    loc.on_camera_info(codec.serialize(msg))
    assert loc.camera is first and len(parsed) == 1  # only its stamp differs: not parsed
    msg.k = msg.k.copy()
    msg.k[0] *= 1.01  # a new focal length
    loc.on_camera_info(codec.serialize(msg))
    assert len(parsed) == 2 and loc.camera.K[0, 0] == pytest.approx(first.K[0, 0] * 1.01)
    second = loc.camera
    msg.header.stamp.sec += 1
    loc.on_camera_info(codec.serialize(msg))
    assert loc.camera is second and len(parsed) == 2
    with pytest.raises(DropError):
        loc.on_camera_info(raw[:12] + b"\xff" * 8)  # its stamp, then garbage
    assert len(parsed) == 3


def test_localize_over_zenoh_within_1cm(noisy: Path) -> None:
    """Bag topics replayed over zenoh → ``stream localize`` (separate processes) → poses."""
    port = free_port()
    gt = read_trajectory(noisy / "ground_truth" / "trajectory.csv")
    node_args = [
        "localize",
        "--map",
        noisy / "ground_truth" / "tag_map.yaml",
        "--listen",
        loopback(port),
        "--duration",
        "45",
        "--stats-period",
        "0",
    ]
    # a detection that precedes the first CameraInfo is kept until it comes
    poses, node = localize_replayed(
        node_args, noisy, port, N_FRAMES, sig=signal.SIGINT
    )  # Ctrl-C: a clean exit too
    stats = node.stats()
    assert stats["processed"] == 2 * N_FRAMES and not stats["dropped"], stats
    err = _errors_m(poses, gt)
    assert err.max() < 0.01, f"max {err.max():.4f} m, median {np.median(err):.4f} m"


def test_localize_from_compressed_images_over_zenoh(tmp_path: Path) -> None:
    """Rendered JPEG frames → pupil-apriltags in the node (its detector lives only there)."""
    rec = simulate("circle", tmp_path, frames=16, compressed=True, seed=4)["circle"]
    gt = read_trajectory(rec / "ground_truth" / "trajectory.csv")
    port = free_port()
    node_args = [
        "localize",
        "--map",
        rec / "ground_truth" / "tag_map.yaml",
        "--listen",
        loopback(port),
        "--image-key",
        "camera/color/image_raw/compressed",
        "--camera-info-key",
        "camera/color/camera_info",
        "--duration",
        "45",
        "--stats-period",
        "0",
    ]
    with running(node_args) as (node,):
        node.wait_for("localize: ready")
        sub = Collector(port, ["tag_only_pose"])
        try:
            with running(
                [
                    "replay",
                    rec,
                    "--topics",
                    "/camera/color/camera_info",
                    "/camera/color/image_raw/compressed",
                    "--connect",
                    loopback(port),
                    "--rate",
                    "0.5",
                ]
            ) as (rep,):
                assert rep.p.wait(30) == 0, rep.output
            # frames arriving while the detector is busy are skipped (latest only)
            poses = sub.wait_until("tag_only_pose", lambda v: len(v) >= 8)
        finally:
            sub.close()
        assert node.stop() == 0, node.output
    assert set(node.stats()["dropped"]) <= {"skipped"}, node.stats()
    err = _errors_m(poses, gt)
    assert err.max() < 0.01, f"max {err.max():.4f} m, median {np.median(err):.4f} m"


def _first_frame(rec: Path) -> tuple[Localizer, np.ndarray, np.ndarray]:
    """A localizer of ``rec``'s map, its camera given, and the first detection message's tag
    ids ``(n,)`` and corners ``(n, 4, 2)``."""
    from tagtrail.io.sources import detections_from_msg

    loc = Localizer(read_tag_map(rec / "ground_truth" / "tag_map.yaml")[0])
    msgs = bag_messages(rec, ["/camera_info", "/detections"])
    loc.on_camera_info(msgs.payloads[msgs.keys.index("camera_info")])
    raw = next(p for k, p in zip(msgs.keys, msgs.payloads, strict=True) if k == "detections")
    dets = detections_from_msg(codec.deserialize(raw, "apriltag_msgs/msg/AprilTagDetectionArray"))
    ids = np.array([d.tag_id for d in dets])
    px = np.array([d.corners for d in dets], np.float64).reshape(-1, 4, 2)
    return loc, ids, px


def test_frame_pose_falls_back_to_the_fusion_as_the_trajectory_stage(exact: Path) -> None:
    """Multi-tag PnP needs no per-tag IPPE pose, so the node solves IPPE's poses only when
    PnP does not pose the frame; then (one tag, or PnP fails: the tags' corners shifted 40 px,
    each their own way, leave too few inliers) the pose is the trajectory stage's fusion of
    them, each tag's solution the one the map agrees with (the shifted tags: not all the
    lower-reprojection ones)."""
    from tagtrail.geometry.fusion import frame_poses
    from tagtrail.geometry.ippe import map_branches, solve_ippe

    loc, ids, px = _first_frame(exact)
    assert len(ids) >= 3 and set(ids) <= set(loc.ids.tolist())
    order = np.argsort(ids)
    ids, px = ids[order], px[order]
    shifted = px.copy()  # each tag its own way: no 6 corners agree on a pose, PnP fails
    shifts = np.array([[40.0, 0.0], [0.0, 40.0], [-40.0, 0.0], [0.0, -40.0]])
    shifted += np.resize(shifts, (len(ids), 2))[:, None, :]
    p = loc.params.trajectory
    picks = []
    for sel_px, sel_ids, by_pnp in (
        (px, ids, True),
        (shifted, ids, False),
        (px[:1], ids[:1], False),
    ):
        T, n = loc.frame_pose(sel_px, sel_ids)
        k = np.searchsorted(loc.ids, sel_ids)
        both = solve_ippe(sel_px, loc.size_m[k], loc.camera)[0]
        pick = map_branches(
            np.zeros(len(k), np.int64), loc.world_T_tag[k, :3, :3], both[..., :3, :3]
        )
        picks.append(pick)
        want = frame_poses(
            loc.world_T_tag[k],
            both[np.arange(len(k)), pick],
            np.zeros(len(k), np.int64),
            1,
            corners_px=sel_px,
            size_m=loc.size_m[k],
            camera=loc.camera,
            method="auto",
            loss=p.loss,
            f_scale=p.f_scale,
            rot_weight_m=p.rot_weight_m,
            ransac_px=p.ransac_px,
        )
        assert bool(want.by_pnp[0]) == by_pnp and n == len(sel_ids)
        assert T is not None and np.abs(T - want.world_T_cam[0]).max() < 1e-12
    assert picks[1].any()  # the map took a mirror, which the node used to leave


def test_unmapped_and_repeated_tags_are_left_out_of_a_frame(exact: Path) -> None:
    """A tag the map does not hold changes nothing; a tag detected twice in one frame is
    nobody's to trust (the offline detections table has no corners for it either): it leaves
    the smoother's corners and the PnP."""
    from tagtrail.stream.localize import _duplicated

    np.testing.assert_array_equal(_duplicated(np.array([4, 2, 4, 9])), [True, False, True, False])
    assert not _duplicated(np.array([4, 2, 9])).any() and len(_duplicated(np.zeros(0, int))) == 0
    loc, ids, px = _first_frame(exact)
    assert len(ids) >= 3
    T, n = loc.frame_pose(px, ids)
    unmapped = max(loc.ids.tolist()) + 1
    T2, n2 = loc.frame_pose(np.concatenate([px, px[:1] + 50.0]), np.r_[ids, unmapped])
    assert n2 == n and T is not None and T2 is not None and np.abs(T2 - T).max() < 1e-12
    loc.frame_pose(np.concatenate([px, px[:1] + 50.0]), np.r_[ids, ids[0]], pose=False)
    assert loc._last_obs is not None
    tags = loc._last_obs[0]
    assert len(tags) == len(ids) - 1 and int(np.searchsorted(loc.ids, ids[0])) not in tags
