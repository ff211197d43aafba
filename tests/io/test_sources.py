"""Sources: bags written in tmp_path from real photos, image folders, observations, bad input."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tagtrail.errors import SourceError
from tagtrail.geometry.camera import CameraModel
from tagtrail.io import msgs
from tagtrail.io.camera_files import read_camera_file
from tagtrail.io.sources import open_source
from tagtrail.schemas.pipeline import DatasetConfig, Topics
from tagtrail.vision.images import RawImage
from tests.io import bags

T0 = bags.T0_NS
DT = 33_333_333


@pytest.fixture(scope="module")
def upenn(realdata: Path) -> tuple[list[Path], CameraModel]:
    folder = realdata / "upenn_ar_tag36h11_id12_seq/frames"
    return sorted(folder.glob("frame*.jpg"))[:4], read_camera_file(folder / "camera.yaml")


def cfg(source: Path, **topics: str) -> DatasetConfig:
    return DatasetConfig(source=source, topics=Topics(**topics))


def image_bag(
    path: Path,
    files: list[Path],
    cam: CameraModel,
    storage: str = "mcap",
    compressed: bool = False,
    extra: list | None = None,
) -> Path:
    out: list = [("/camera/camera_info", T0, bags.camera_info_msg(cam))]
    for k, f in enumerate(files):
        t = T0 + k * DT
        if compressed:  # the original JPEG bytes, as image_transport would ship them
            msg = bags.compressed_msg(f.read_bytes(), "jpeg", t)
            out.append(("/camera/image_raw/compressed", t + 1000, msg))
        else:
            rgb = np.ascontiguousarray(cv2.imread(str(f))[..., ::-1])
            out.append(("/camera/image_raw", t + 1000, bags.image_msg(rgb, "rgb8", t)))
    return bags.write_bag(path, out + (extra or []), storage)


@pytest.mark.parametrize(("storage", "compressed"), [("mcap", False), ("sqlite3", True)])
def test_image_bag_frames_stamps_camera(tmp_path: Path, upenn, storage, compressed) -> None:
    files, cam = upenn
    bag = image_bag(tmp_path / "bag", files, cam, storage, compressed)
    src = open_source(cfg(bag))
    assert src.kind == "images" and len(src) == len(files)
    assert src.camera() is not None and src.camera().same_as(cam)
    frames = list(src)
    assert [f[0] for f in frames] == list(range(len(files)))
    assert [f[1] for f in frames] == [T0 + k * DT for k in range(len(files))]  # header stamps
    for (_, _, img), f in zip(frames, files, strict=True):
        want = (
            cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if compressed
            else cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2GRAY)
        )
        np.testing.assert_array_equal(img, want)
    raw = next(src.iter_raw())[2]  # undecoded for workers
    assert isinstance(raw, RawImage) and raw.kind == ("compressed" if compressed else "raw")
    assert [len(c) for c in src.chunks(3)] == [3, 1]


def test_ros1_bag(tmp_path: Path, upenn) -> None:
    files, cam = upenn
    grays = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files[:2]]
    src = open_source(cfg(bags.write_ros1_bag(tmp_path / "rec.bag", grays, cam)))
    assert src.kind == "images" and len(src) == 2 and src.camera().same_as(cam)
    out = list(src)
    assert out[1][1] == T0 + 50_000_000
    np.testing.assert_array_equal(out[1][2], grays[1])


def test_humble_sqlite3_detection_bag_without_definitions(tmp_path: Path, upenn) -> None:
    _, cam = upenn
    corners = np.array([[10.0, 20.0], [30.0, 20.0], [30.0, 40.0], [10.0, 40.0]])
    msgs_ = [("/camera_info", T0, bags.camera_info_msg(cam))] + [
        ("/detections", T0 + k, bags.detections_msg(T0 + k * DT, [(12, 0, 55.5, corners + k)]))
        for k in range(3)
    ]
    bag = bags.make_humble(bags.write_bag(tmp_path / "bag", msgs_, "sqlite3"))
    assert "message_definitions" not in (bag / "metadata.yaml").read_text()
    src = open_source(cfg(bag))
    assert src.kind == "detections" and len(src) == 3 and src.camera().same_as(cam)
    frames = list(src)
    assert [f[1] for f in frames] == [T0 + k * DT for k in range(3)]
    det = frames[2][2][0]
    assert (det.tag_id, det.hamming, det.decision_margin) == (12, 0, 55.5)
    np.testing.assert_array_equal(det.corners, corners + 2 - 0.5)  # C library → OpenCV pixels


def test_zero_header_stamp_falls_back_to_receive_time(tmp_path: Path, upenn) -> None:
    files, cam = upenn
    gray = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE)
    bag = bags.write_bag(
        tmp_path / "bag",
        [
            ("/cam/camera_info", T0, bags.camera_info_msg(cam)),
            ("/cam/image", T0 + 7, bags.image_msg(gray, "mono8", 0)),
        ],
    )
    assert [t for _, t, _ in open_source(cfg(bag)).iter_raw()] == [T0 + 7]


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial", "equidistant"])
def test_camera_info_distortion_models(tmp_path: Path, upenn, model: str) -> None:
    files, _ = upenn
    D = {
        "plumb_bob": [0.1, -0.2, 1e-3, 2e-3, 0.05],
        "equidistant": [0.05, -0.01, 2e-3, -1e-3],
        "rational_polynomial": [0.1, -0.2, 1e-3, 2e-3, 0.05, 0.01, -0.02, 0.01],
    }[model]
    cam = CameraModel(640, 480, [820.0, 0, 320, 0, 821.0, 240, 0, 0, 1], D, model)
    src = open_source(cfg(image_bag(tmp_path / "bag", files[:1], cam)))
    assert src.camera().distortion_model == model and src.camera().same_as(cam)


def test_camera_info_change_warns(tmp_path: Path, upenn, caplog) -> None:
    files, cam = upenn
    other = CameraModel(640, 480, cam.K * [[1.1], [1.1], [1]], cam.D, cam.distortion_model)
    extra = [("/camera/camera_info", T0 + 3 * DT, bags.camera_info_msg(other))]
    src = open_source(cfg(image_bag(tmp_path / "bag", files, cam, extra=extra)))
    with caplog.at_level(logging.WARNING, logger="tagtrail.sources"):
        assert len(list(src.iter_raw())) == len(files)
    assert "/camera/camera_info changes during the recording" in caplog.text
    assert src.camera().same_as(cam)  # the first message wins


def test_topic_choice(tmp_path: Path, upenn) -> None:
    files, cam = upenn
    gray = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE)
    det = bags.detections_msg(T0, [(3, 0, 80.0, np.ones((4, 2)))])
    bag = bags.write_bag(
        tmp_path / "bag",
        [
            ("/left/camera_info", T0, bags.camera_info_msg(cam)),
            ("/right/camera_info", T0, bags.camera_info_msg(cam)),
            ("/left/image_raw", T0, bags.image_msg(gray, "mono8", T0)),
            ("/right/image_raw", T0, bags.image_msg(gray, "mono8", T0)),
            ("/detections", T0, det),
        ],
    )
    with pytest.raises(SourceError) as err:
        open_source(cfg(bag))
    msg = str(err.value)
    assert "several" in msg and "/left/image_raw (sensor_msgs/msg/Image, 1 msgs)" in msg
    assert "/right/image_raw" in msg and "`topics: {image: /left/image_raw}`" in msg
    src = open_source(cfg(bag, image="/right/image_raw"))  # camera_info from the same namespace
    assert (src.kind, src.topic, src.camera_info_topic) == (
        "images",
        "/right/image_raw",
        "/right/camera_info",
    )
    with pytest.raises(SourceError, match=r"several CameraInfo .* `topics: {camera_info: /left"):
        open_source(cfg(bag, detections="/detections"))  # no namespace to match
    src = open_source(cfg(bag, detections="/detections", camera_info="/left/camera_info"))
    assert (src.kind, src.topic) == ("detections", "/detections")
    with pytest.raises(SourceError, match=r"topic /nope \(topics.image in pipeline.yaml\) is not"):
        open_source(cfg(bag, image="/nope"))
    with pytest.raises(SourceError, match="has type sensor_msgs/msg/Image, not apriltag_msgs"):
        open_source(cfg(bag, detections="/left/image_raw"))


def test_images_preferred_over_detections(tmp_path: Path, upenn) -> None:
    files, cam = upenn
    extra = [("/detections", T0, bags.detections_msg(T0, []))]
    src = open_source(cfg(image_bag(tmp_path / "bag", files[:1], cam, extra=extra)))
    assert (src.kind, src.topic) == ("images", "/camera/image_raw")


def test_image_folder_order_stamps_camera(tmp_path: Path, upenn) -> None:
    files, cam = upenn
    folder = tmp_path / "imgs"
    folder.mkdir()
    names = ["f2.jpg", "f10.JPG", "f1.png"]
    for name, f in zip(names, files, strict=False):
        shutil.copy(f, folder / name)
    (folder / "notes.txt").write_text("ignored")
    assert open_source(cfg(folder)).camera() is None  # extract reports it (no intrinsics)
    shutil.copy(files[0].parent / "camera.yaml", folder / "camera.yaml")
    src = open_source(cfg(folder))
    assert src.kind == "images" and len(src) == 3 and src.camera().same_as(cam)
    frames = list(src.iter_raw())
    assert [Path(p.data).name for _, _, p in frames] == ["f1.png", "f2.jpg", "f10.JPG"]
    assert [t for _, t, _ in frames] == [0, 100_000_000, 200_000_000]  # 10 Hz from 0
    (folder / "stamps.csv").write_text(
        "file,stamp_sec,stamp_nanosec\nf10.JPG,5,3\nf1.png,5,1\nf2.jpg,5,2\n"
    )
    assert [t for _, t, _ in open_source(cfg(folder)).iter_raw()] == [
        5 * 10**9 + k for k in (1, 2, 3)
    ]
    other = tmp_path / "other.yaml"
    other.write_text((folder / "camera.yaml").read_text().replace("823.8", "900.0"))
    src = open_source(DatasetConfig(source=folder, camera=other))  # `camera:` overrides
    assert src.camera().K[0, 0] == 900.0
    (folder / "stamps.csv").write_text("file,stamp_sec,stamp_nanosec\nf1.png,5,1\n")
    with pytest.raises(SourceError, match=r"stamps.csv: no stamp for 2 image\(s\), e.g. f2.jpg"):
        open_source(cfg(folder))


def test_observations_folder(tmp_path: Path) -> None:
    (tmp_path / "observations.csv").write_text(
        "stamp_sec,stamp_nanosec,tag,x,y,z,qx,qy,qz,qw\n"
        "2,0,tag36h11:5,0.1,0.2,1.0,0,0,0,1\n"
        "1,500,tag36h11:7,0.0,0.0,2.0,1,0,0,0\n"
        "1,500,tag36h11:3,0.0,0.1,2.0,1,0,0,0\n"
    )
    src = open_source(cfg(tmp_path))
    assert src.kind == "observations" and src.camera() is None and len(src) == 2
    obs = src.observations()
    assert list(obs.columns) == [
        "t_ns",
        "frame_idx",
        "tag_id",
        "x_m",
        "y_m",
        "z_m",
        "qx",
        "qy",
        "qz",
        "qw",
    ]
    assert obs["tag_id"].tolist() == [3, 7, 5] and obs["frame_idx"].tolist() == [0, 0, 1]
    assert obs["t_ns"].tolist() == [10**9 + 500, 10**9 + 500, 2 * 10**9]
    assert [len(p) for _, _, p in src] == [2, 1]


def test_bad_sources(tmp_path: Path, upenn) -> None:
    files, cam = upenn
    with pytest.raises(SourceError, match=r"nowhere: no such file or folder \(dataset source\)"):
        open_source(cfg(tmp_path / "nowhere"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="empty or unrecognised source folder"):
        open_source(cfg(tmp_path / "empty"))
    bag = bags.write_bag(tmp_path / "emptybag", [], topics={"/camera/image_raw": msgs.IMAGE})
    with pytest.raises(SourceError, match="topic /camera/image_raw has no messages"):
        open_source(cfg(bag))
    bag = bags.write_bag(tmp_path / "nothing", [])
    with pytest.raises(SourceError, match="no image .* or detection .* topic; topics there: none"):
        open_source(cfg(bag))
    pose = msgs.typestore().types[msgs.POSE_STAMPED]
    p = pose(
        header=bags.header(T0),
        pose=msgs.typestore().types["geometry_msgs/msg/Pose"](
            position=msgs.typestore().types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            orientation=msgs.typestore().types["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=0.0, w=1.0
            ),
        ),
    )
    bag = bags.write_bag(tmp_path / "poses", [("/pose", T0, p)])
    with pytest.raises(SourceError, match=r"topics there: /pose \(geometry_msgs/msg/PoseStamped"):
        open_source(cfg(bag))
    bad = tmp_path / "badbag"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 5}\n")
    with pytest.raises(SourceError, match="badbag: cannot read bag"):
        open_source(cfg(bad))
    bag = image_bag(tmp_path / "ok", files[:1], cam)
    mcap = next(bag.glob("*.mcap"))
    lonely = tmp_path / "lonely"
    lonely.mkdir()
    shutil.copy(mcap, lonely / mcap.name)
    with pytest.raises(SourceError, match="no metadata.yaml next to it.*ros2 bag reindex"):
        open_source(cfg(lonely / mcap.name))
    with pytest.raises(SourceError, match="bag files without metadata.yaml"):
        open_source(cfg(lonely))
    with pytest.raises(SourceError, match=r"cam.yaml: camera file not found"):
        open_source(DatasetConfig(source=bag, camera=tmp_path / "cam.yaml"))


def test_tagslam_ros1_detections_are_read_directly(realdata: Path, tmp_path: Path) -> None:
    """TagSLAM test 16's ``apriltag_msgs/ApriltagArrayStamped`` bag (ROS 1, MIT detector, no
    decision margin, family ``mit``) with its Kalibr ``cameras.yaml``: every detection comes
    out, tag36h11, corners as recorded (the MIT detector's are OpenCV's), margin NaN."""
    import bz2

    import numpy as np

    from tagtrail.io.sources import open_source
    from tagtrail.schemas.pipeline import DatasetConfig

    root = realdata / "tagslam_test_16"
    bag = tmp_path / "tag_detections.bag"
    bag.write_bytes(bz2.decompress((root / "tag_detections.bag.bz2").read_bytes()))
    src = open_source(DatasetConfig(source=bag, camera=root / "cameras.yaml"))
    assert src.kind == "detections" and src.camera() is not None
    frames = list(src.iter_raw())
    dets = [d for _, _, data in frames for d in data]
    assert len(frames) == 297 and len(dets) == 1471
    first = frames[0][2][0]
    assert first.tag_id == 1 and first.family == "" and np.isnan(first.decision_margin)
    assert np.allclose(first.corners[0], [526.064208984375, 392.17669677734375])


def test_image_folder_without_stamps_is_not_timed(realdata: Path, tmp_path: Path) -> None:
    """Without stamps.csv an image folder's stamps are its files' order (10 Hz): not capture
    times, so nothing downstream links its frames in time."""
    import shutil

    from tagtrail.io.sources import open_source
    from tagtrail.schemas.pipeline import DatasetConfig

    frames = realdata / "upenn_ar_tag36h11_id12_seq" / "frames"
    folder = tmp_path / "imgs"
    folder.mkdir()
    shutil.copy(frames / "camera.yaml", folder)
    names = [f.name for f in sorted(frames.glob("frame*.jpg"))[:3]]
    for name in names:
        shutil.copy(frames / name, folder)
    assert not open_source(DatasetConfig(source=folder)).timed
    (folder / "stamps.csv").write_text(
        "file,stamp_sec,stamp_nanosec\n"
        + "".join(f"{name},{100 + k},0\n" for k, name in enumerate(names))
    )
    assert open_source(DatasetConfig(source=folder)).timed


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_isaac_ros_detections(tmp_path: Path, storage: str, caplog) -> None:
    """isaac_ros_apriltag's detections (its .msg registered in the typestore: a Humble bag
    carries no definitions): corners -0.5 px to OpenCV's, no hamming (-1) or margin (NaN), the
    family as the message names it; the declared convention is logged."""
    cam = CameraModel.from_dict(
        {
            "width": 640,
            "height": 480,
            "distortion_model": "plumb_bob",
            "K": [500, 0, 320, 0, 500, 240, 0, 0, 1],
            "D": [0] * 5,
        }
    )
    bag, truth = bags.isaac_bag(tmp_path, cam, storage)
    if storage == "sqlite3":
        bags.make_humble(bag)
    with caplog.at_level(logging.INFO, logger="tagtrail.sources"):
        src = open_source(DatasetConfig(source=bag))
    assert "isaac_ros_apriltag (NVIDIA Isaac ROS)" in caplog.text
    assert "+0.5 px from OpenCV's" in caplog.text and "rectified image" in caplog.text
    assert src.kind == "detections" and src.camera() is not None and len(src) == 5
    dets = [d for _, _, ds in src.iter_raw() for d in ds]
    assert [d.tag_id for d in dets] == [3, 7] * 5
    assert all(d.hamming == -1 and np.isnan(d.decision_margin) for d in dets)
    assert {d.family for d in dets} == {"tag36h11"}
    assert np.abs(np.array([d.corners for d in dets]) - np.array(truth)).max() < 1e-9


def test_isaac_ros_detections_warn_of_a_distorted_camera(tmp_path: Path, caplog) -> None:
    cam = CameraModel.from_dict(
        {
            "width": 640,
            "height": 480,
            "distortion_model": "plumb_bob",
            "K": [500, 0, 320, 0, 500, 240, 0, 0, 1],
            "D": [0.05, -0.02, 0, 0, 0],
        }
    )
    bag, _ = bags.isaac_bag(tmp_path, cam)
    with caplog.at_level(logging.WARNING, logger="tagtrail.sources"):
        open_source(DatasetConfig(source=bag))
    assert (
        "detects in the rectified image, but the camera (CameraInfo of /camera_info_rect) "
        "has lens distortion [0.05, -0.02, 0.0, 0.0, 0.0]" in caplog.text
    )


def test_detection_types_declare_convention_and_quality_fields() -> None:
    kinds = msgs.DETECTION_SOURCES
    assert set(kinds) == {msgs.DETECTIONS, msgs.TAGSLAM_DETECTIONS, msgs.ISAAC_DETECTIONS}
    assert kinds[msgs.DETECTIONS].missing() == []
    assert kinds[msgs.TAGSLAM_DETECTIONS].missing() == ["decision_margin"]
    assert kinds[msgs.ISAAC_DETECTIONS].missing() == ["hamming", "decision_margin"]
    tagslam = kinds[msgs.TAGSLAM_DETECTIONS]
    assert (
        tagslam.pixel_offset("mit"),
        tagslam.pixel_offset(""),
        tagslam.pixel_offset("umich"),
    ) == (0.0, 0.0, 0.5)
    assert kinds[msgs.DETECTIONS].pixel_offset("tag36h11") == 0.5
