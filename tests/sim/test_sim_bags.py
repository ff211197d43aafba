"""Simulated recordings: layout, ground truth files, readability with rosbags and mcap, options."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from tagtrail.errors import SpecError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.se3 import T_from_xyz_quat
from tagtrail.io.layouts import POSE_COLS, read_tag_map, read_trajectory
from tagtrail.sim import cli, simulate
from tagtrail.sim.camera import FRAME_ID, limo_camera
from tagtrail.sim.render import Renderer
from tests.sim.helpers import SMALL, image_of, read_topic

IMAGE, INFO = "/camera/color/image_raw", "/camera/color/camera_info"
GT = "/ground_truth/camera_pose"


def test_room_layout_and_ground_truth(room_mcap: dict[str, Path]) -> None:
    assert list(room_mcap) == ["reference", "query_1", "query_2", "query_3"]
    for name, folder in room_mcap.items():
        gt = folder / "ground_truth"
        assert (folder / "metadata.yaml").is_file() and folder.name == name
        traj = read_trajectory(gt / "trajectory.csv")
        n = SMALL["frames"] if name == "reference" else SMALL["query_frames"]
        assert len(traj) == n
        tags, anchor = read_tag_map(gt / "tag_map.yaml")
        assert anchor == 0 and len(tags) == 18 and (tags["size_m"] == 0.16).all()
        row = tags.set_index("tag_id").loc[0, POSE_COLS].to_numpy(float)
        np.testing.assert_allclose(row, [0, 0, 0, 0, 0, 0, 1], atol=1e-12)
        scene = yaml.safe_load((gt / "scene.yaml").read_text())
        assert CameraModel.from_dict(scene["camera"]).same_as(limo_camera(), rtol=0)
        assert scene["camera"]["frame_id"] == FRAME_ID
        assert scene["anchor_id"] == 0 and scene["seed"] == SMALL["seed"]
        assert len(scene["tags"]) == 18
        assert (gt / "test_poses.csv").is_file() == name.startswith("query")
        if name.startswith("query"):
            test_pose = read_trajectory(gt / "test_poses.csv")
            assert len(test_pose) == 1
            np.testing.assert_allclose(
                traj[POSE_COLS].to_numpy(),
                np.repeat(test_pose[POSE_COLS].to_numpy(), n, axis=0),
                atol=1e-12,
            )
    assert not list(room_mcap["reference"].parent.glob(".simulate-*"))


def test_rosbags_reads_images_info_and_ground_truth(room_mcap: dict[str, Path]) -> None:
    bag = room_mcap["reference"]
    images, infos, poses = read_topic(bag, IMAGE), read_topic(bag, INFO), read_topic(bag, GT)
    assert len(images) == len(infos) == len(poses) == SMALL["frames"]
    t0, msg = images[0]
    assert t0 == 1_700_000_000 * 10**9 and msg.encoding == "rgb8" and msg.step == 640 * 3
    assert image_of(msg).shape == (480, 640, 3)
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in images])
    np.testing.assert_array_equal(stamps, [t for t, _ in images])
    assert np.allclose(np.diff(stamps), 1e9 / 30, atol=1)
    info = infos[0][1]
    assert info.distortion_model == "plumb_bob" and len(info.d) == 5
    assert info.k[0] == pytest.approx(442.17) and info.k[5] == pytest.approx(246.51)
    traj = read_trajectory(bag / "ground_truth" / "trajectory.csv")
    np.testing.assert_array_equal(traj["t_ns"].to_numpy(), [t for t, _ in poses])
    p = poses[5][1]
    assert p.header.frame_id == "map"
    got = [
        p.pose.position.x,
        p.pose.position.y,
        p.pose.position.z,
        p.pose.orientation.x,
        p.pose.orientation.y,
        p.pose.orientation.z,
        p.pose.orientation.w,
    ]
    np.testing.assert_allclose(got, traj.loc[5, POSE_COLS].to_numpy(float), atol=1e-9)


def _mcap_messages(bag: Path) -> dict[str, list[object]]:
    out: dict[str, list[object]] = {}
    (f,) = bag.glob("*.mcap")
    with f.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, msg in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append(msg)
    return out


ODOM_TOPICS = ("/odom", "/tf_static")  # tests/sim/test_sim_odometry.py checks them


def test_mcap_reads_images_and_detections(room_mcap: dict[str, Path], tmp_path: Path) -> None:
    msgs = _mcap_messages(room_mcap["query_2"])
    assert set(ODOM_TOPICS) <= set(msgs) and len(msgs["/tf_static"]) == 1
    msgs = {k: v for k, v in msgs.items() if k not in ODOM_TOPICS}
    assert {len(v) for v in msgs.values()} == {SMALL["query_frames"]}
    img = msgs[IMAGE][0]
    assert (img.width, img.height, img.encoding) == (640, 480, "rgb8")  # type: ignore[attr-defined]
    assert len(img.data) == 640 * 480 * 3  # type: ignore[attr-defined]
    assert msgs[GT][0].header.frame_id == "map"  # type: ignore[attr-defined]
    det = simulate("circle", tmp_path, frames=8, detections=True)["circle"]
    msgs = _mcap_messages(det)
    assert set(msgs) == {"/detections", "/camera_info", GT, *ODOM_TOPICS}
    d = msgs["/detections"][0].detections[0]  # type: ignore[attr-defined]
    assert d.family == "36h11" and len(d.corners) == 4 and d.hamming == 0


def test_sqlite3_detections_read_with_rosbags(room_detections: dict[str, Path]) -> None:
    bag = room_detections["reference"]
    assert list(bag.glob("*.db3"))
    dets, infos = read_topic(bag, "/detections"), read_topic(bag, "/camera_info")
    assert len(dets) == len(infos) == 300
    assert not read_topic(bag, IMAGE)
    all_d = [d for _, m in dets for d in m.detections]
    assert len(all_d) > 300
    assert {d.family for d in all_d} == {"36h11"} and {d.hamming for d in all_d} == {0}
    margins = np.array([d.decision_margin for d in all_d])
    assert margins.min() >= 20 and margins.max() <= 150 and np.median(margins) > 50
    assert all(not np.any(d.homography) for d in all_d)


def test_compressed_images(tmp_path: Path) -> None:
    out = simulate("corridor", tmp_path, frames=5, compressed=True, jpeg_quality=80)["corridor"]
    msgs = read_topic(out, "/camera/color/image_raw/compressed")
    assert len(msgs) == 5 and "jpeg" in msgs[0][1].format
    img = cv2.imdecode(np.asarray(msgs[0][1].data, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (480, 640, 3)
    assert len(read_topic(out, INFO)) == 5 and not read_topic(out, IMAGE)


def test_same_seed_same_images(tmp_path: Path) -> None:
    a = simulate("circle", tmp_path / "a", frames=3, seed=1)["circle"]
    b = simulate("circle", tmp_path / "b", frames=3, seed=1)["circle"]
    c = simulate("circle", tmp_path / "c", frames=3, seed=2)["circle"]
    ia, ib, ic = (image_of(read_topic(x, IMAGE)[2][1]) for x in (a, b, c))
    assert np.array_equal(ia, ib) and not np.array_equal(ia, ic)


def test_refuses_overwrite_unless_force(tmp_path: Path) -> None:
    simulate("corridor", tmp_path, frames=3, detections=True)
    with pytest.raises(SpecError, match="--force"):
        simulate("corridor", tmp_path, frames=3, detections=True)
    simulate("corridor", tmp_path, frames=4, detections=True, force=True)
    assert len(read_trajectory(tmp_path / "corridor" / "ground_truth")) == 4


def test_interrupted_run_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = {"n": 0}
    original = Renderer.render

    def flaky(self: Renderer, *args: object, **kw: object) -> np.ndarray:
        calls["n"] += 1
        if calls["n"] > 3:
            raise KeyboardInterrupt
        return original(self, *args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(Renderer, "render", flaky)
    with pytest.raises(KeyboardInterrupt):
        simulate("room", tmp_path, frames=10, query_frames=2)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("scenario", "options", "match"),
    [
        ("nope", {}, "unknown scenario"),
        ("room", {"frame": 3}, "did you mean 'frames'"),
        ("room", {"frames": 1}, "--frames"),
        ("room", {"speed_mps": 0.0}, "--speed"),
        ("circle", {"tag_ids": (1, 2)}, "24 tags"),
        ("circle", {"anchor_id": 99}, "--anchor"),
        ("circle", {"tag_ids": tuple(range(600, 624))}, "not in tag36h11"),
        ("room", {"compressed": True, "detections": True}, "exclude"),
        ("room", {"storage": "bag"}, "--storage"),
    ],
)
def test_bad_options(tmp_path: Path, scenario: str, options: dict[str, object], match: str) -> None:
    with pytest.raises(SpecError, match=match):
        simulate(scenario, tmp_path, **options)  # type: ignore[arg-type]
    assert not any(tmp_path.iterdir())


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="tagtrail simulate")
    cli.add_arguments(parser)
    return parser.parse_args(argv)


def test_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = [
        "observations",
        "--out",
        str(tmp_path),
        "--frames",
        "20",
        "--noise-t",
        "0.1",
        "--tag-ids",
        "10-33",
        "--tag-sizes",
        "10=0.2",
        "--anchor",
        "12",
    ]
    assert cli.main(_parse(argv)) == 0
    assert "observations:" in capsys.readouterr().out
    obs = pd.read_csv(tmp_path / "observations" / "observations.csv")
    assert list(obs.columns) == "stamp_sec,stamp_nanosec,tag,x,y,z,qx,qy,qz,qw".split(",")
    assert obs["tag"].str.startswith("tag36h11:").all()
    tags, anchor = read_tag_map(tmp_path / "observations" / "ground_truth" / "tag_map.yaml")
    assert anchor == 12 and sorted(tags["tag_id"]) == list(range(10, 34))
    assert tags.set_index("tag_id").loc[10, "size_m"] == pytest.approx(0.2)
    assert cli.main(_parse(argv)) == 2
    assert "--force" in capsys.readouterr().err
    assert cli.main(_parse(["room", "--out", str(tmp_path), "--size", "big"])) == 2
    assert "error: --size" in capsys.readouterr().err
    assert cli.main(_parse(["room", "--out", str(tmp_path), "--size", "8x8"])) == 2
    assert "error: --size: 8x8 is too small" in capsys.readouterr().err
    help_text = argparse.ArgumentParser()
    cli.add_arguments(help_text)
    assert "examples:" in help_text.format_help()


def test_observations_follow_rigid_transforms(tmp_path: Path) -> None:
    exact = simulate("observations", tmp_path / "a", frames=30)["observations"]
    noisy = simulate("observations", tmp_path / "b", frames=200, noise_t_m=0.1, noise_r_deg=3.0)[
        "observations"
    ]
    for folder, tol in ((exact, 1e-9), (noisy, None)):
        obs = pd.read_csv(folder / "observations.csv")
        traj = read_trajectory(folder / "ground_truth").set_index("t_ns")
        tags = read_tag_map(folder / "ground_truth")[0].set_index("tag_id")
        t_ns = obs["stamp_sec"].to_numpy() * 10**9 + obs["stamp_nanosec"].to_numpy()
        ids = obs["tag"].str.split(":").str[1].astype(int).to_numpy()
        world_T_cam = T_from_xyz_quat(
            traj.loc[t_ns, POSE_COLS[:3]].to_numpy(float),
            traj.loc[t_ns, POSE_COLS[3:]].to_numpy(float),
        )
        cam_T_tag = T_from_xyz_quat(
            obs[["x", "y", "z"]].to_numpy(float), obs[["qx", "qy", "qz", "qw"]].to_numpy(float)
        )
        world_T_tag = T_from_xyz_quat(
            tags.loc[ids, POSE_COLS[:3]].to_numpy(float),
            tags.loc[ids, POSE_COLS[3:]].to_numpy(float),
        )
        # translation noise of cam_T_tag, in the camera frame
        expect = np.linalg.inv(world_T_cam) @ world_T_tag
        dt = cam_T_tag[:, :3, 3] - expect[:, :3, 3]
        if tol is not None:
            assert len(obs) >= 30 and np.abs(dt).max() < tol
            np.testing.assert_allclose(cam_T_tag, expect, atol=1e-9)
        else:
            assert len(obs) > 500
            assert np.abs(dt.mean(axis=0)).max() < 0.015
            np.testing.assert_allclose(dt.std(axis=0), 0.1, rtol=0.12)
            dR = np.swapaxes(expect[:, :3, :3], 1, 2) @ cam_T_tag[:, :3, :3]
            ang = np.degrees(np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1)))
            # |rotvec| of an isotropic 3-axis Gaussian: rms = sqrt(3) * sigma
            assert np.sqrt(np.mean(ang**2)) == pytest.approx(np.sqrt(3) * 3.0, rel=0.12)
