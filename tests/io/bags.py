"""Test helpers: write small bags (rosbag2 MCAP/sqlite3, Humble-style sqlite3, ROS 1) in tmp_path.

Messages are built with tagtrail's shared typestore, so what the tests write is what ROS 2 writes.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from tagtrail.geometry.camera import CameraModel
from tagtrail.io import msgs

T0_NS = 1_700_000_000_000_000_000
STORAGE = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


def _ts() -> Any:
    return msgs.typestore()


def header(t_ns: int, frame_id: str = "camera", ts: Any = None) -> Any:
    ts = ts or _ts()
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    seq = {"seq": 0} if "seq" in [f[0] for f in ts.fielddefs["std_msgs/msg/Header"][1]] else {}
    return ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id, **seq)


def image_msg(img: np.ndarray, encoding: str, t_ns: int, step: int | None = None) -> Any:
    """``sensor_msgs/Image`` of an (H, W[, C]) uint8/uint16 array (rows padded to ``step``)."""
    h, w = img.shape[:2]
    row = img.reshape(h, -1).view(np.uint8)
    step = step or row.shape[1]
    data = np.zeros((h, step), np.uint8)
    data[:, : row.shape[1]] = row
    big = int(img.dtype.byteorder == ">")
    return _ts().types[msgs.IMAGE](
        header=header(t_ns),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=big,
        step=step,
        data=data.reshape(-1),
    )


def compressed_msg(data: bytes, fmt: str, t_ns: int) -> Any:
    return _ts().types[msgs.COMPRESSED_IMAGE](
        header=header(t_ns), format=fmt, data=np.frombuffer(data, np.uint8)
    )


def camera_info_msg(cam: CameraModel, t_ns: int = T0_NS, ts: Any = None) -> Any:
    ts = ts or _ts()
    P = np.zeros((3, 4))
    P[:, :3] = cam.K
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    fields = {
        "d": np.asarray(cam.D, np.float64),
        "k": cam.K.reshape(-1).copy(),
        "r": np.eye(3).reshape(-1),
        "p": P.reshape(-1),
    }
    if "D" in [f[0] for f in ts.fielddefs[msgs.CAMERA_INFO][1]]:  # ROS 1 spelling
        fields = {k.upper(): v for k, v in fields.items()}
    return ts.types[msgs.CAMERA_INFO](
        header=header(t_ns, ts=ts),
        height=cam.height,
        width=cam.width,
        distortion_model=cam.distortion_model,
        binning_x=0,
        binning_y=0,
        roi=roi,
        **fields,
    )


def detections_msg(
    t_ns: int, dets: Sequence[tuple[int, int, float, np.ndarray]], family: str = "tag36h11"
) -> Any:
    """``AprilTagDetectionArray``; ``dets`` = (id, hamming, decision_margin, corners (4, 2))."""
    ts = _ts()
    Point = ts.types["apriltag_msgs/msg/Point"]
    items = []
    for tag_id, ham, margin, corners in dets:
        c = np.asarray(corners, np.float64)
        items.append(
            ts.types["apriltag_msgs/msg/AprilTagDetection"](
                family=family,
                id=tag_id,
                hamming=ham,
                goodness=0.0,
                decision_margin=margin,
                centre=Point(x=float(c[:, 0].mean()), y=float(c[:, 1].mean())),
                corners=[Point(x=float(x), y=float(y)) for x, y in c],
                homography=np.zeros(9),
            )
        )
    return ts.types[msgs.DETECTIONS](header=header(t_ns), detections=items)


def isaac_msg(
    t_ns: int, dets: Sequence[tuple[int, np.ndarray, np.ndarray]], family: str = "tag36h11"
) -> Any:
    """``isaac_ros_apriltag_interfaces/AprilTagDetectionArray`` as the Isaac ROS node fills it:
    ``dets`` = (id, corners (4, 2) px, cam_T_tag (4, 4)); centre = the diagonals' crossing
    (here their mean), pose in a PoseWithCovarianceStamped with the image's header."""
    from tagtrail.geometry.se3 import quat_xyzw_from_R

    ts = _ts()
    T = ts.types
    items = []
    for tag_id, corners, cam_T_tag in dets:
        c = np.asarray(corners, np.float64)
        q = quat_xyzw_from_R(cam_T_tag[:3, :3])
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](
                x=cam_T_tag[0, 3], y=cam_T_tag[1, 3], z=cam_T_tag[2, 3]
            ),
            orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        items.append(
            T["isaac_ros_apriltag_interfaces/msg/AprilTagDetection"](
                family=family,
                id=tag_id,
                center=T["geometry_msgs/msg/Point"](x=c[:, 0].mean(), y=c[:, 1].mean(), z=0.0),
                corners=[T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0) for x, y in c],
                pose=T["geometry_msgs/msg/PoseWithCovarianceStamped"](
                    header=header(t_ns),
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](
                        pose=pose, covariance=np.zeros(36)
                    ),
                ),
            )
        )
    return T[msgs.ISAAC_DETECTIONS](header=header(t_ns), detections=items)


def write_bag(
    path: Path,
    messages: Iterable[tuple[str, int, Any]],
    storage: str = "mcap",
    topics: dict[str, str] | None = None,
) -> Path:
    """A rosbag2 (version 9) folder from ``(topic, receive t_ns, msg)``; ``topics`` declares
    topics (name → msgtype) up front, e.g. ones left without messages."""
    ts = _ts()
    with Writer(path, version=9, storage_plugin=STORAGE[storage]) as w:
        conns: dict[str, Any] = {}
        for name, msgtype in (topics or {}).items():
            conns[name] = w.add_connection(name, msgtype, typestore=ts)
        for topic, t_ns, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msg.__msgtype__, typestore=ts)
            w.write(conns[topic], t_ns, ts.serialize_cdr(msg, msg.__msgtype__))
    return path


def make_humble(bag: Path) -> Path:
    """Turn a rosbags-written sqlite3 bag into what ROS 2 Humble writes: schema 3, no
    ``message_definitions`` table, metadata version 5 without type hashes."""
    db = next(bag.glob("*.db3"))
    con = sqlite3.connect(db)
    con.executescript(
        "DROP TABLE message_definitions; UPDATE schema SET schema_version = 3, "
        "ros_distro = 'humble'; ALTER TABLE topics DROP COLUMN type_description_hash;"
    )
    con.commit()
    con.close()
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    info["version"] = 5
    for t in info["topics_with_message_count"]:
        t["topic_metadata"].pop("type_description_hash", None)
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return bag


def write_ros1_bag(path: Path, frames: Sequence[np.ndarray], cam: CameraModel) -> Path:
    """A ROS 1 bag with mono8 ``/camera/image_raw`` and ``/camera/camera_info``."""
    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer1(path) as w:
        ci = w.add_connection("/camera/camera_info", msgs.CAMERA_INFO, typestore=ts)
        im = w.add_connection("/camera/image_raw", msgs.IMAGE, typestore=ts)
        for k, img in enumerate(frames):
            t = T0_NS + k * 50_000_000
            msg = ts.types[msgs.IMAGE](
                header=header(t, ts=ts),
                height=img.shape[0],
                width=img.shape[1],
                encoding="mono8",
                is_bigendian=0,
                step=img.shape[1],
                data=img.reshape(-1),
            )
            w.write(ci, t, ts.serialize_ros1(camera_info_msg(cam, t, ts), msgs.CAMERA_INFO))
            w.write(im, t, ts.serialize_ros1(msg, msgs.IMAGE))
    return path


def isaac_bag(tmp_path: Path, cam: CameraModel, storage: str = "mcap") -> tuple[Path, list]:
    """An Isaac ROS recording: ``/tag_detections`` (isaac_ros_apriltag_interfaces) of two tags
    seen from a moving camera, corners in the C library's convention (+0.5 px), with the
    rectified image's ``/camera_info_rect``."""
    from tagtrail.geometry.rotations import R_from_rotvec
    from tagtrail.geometry.se3 import make_T
    from tests.vision.exact_tag import true_corners

    out, truth = [("/camera_info_rect", T0_NS, camera_info_msg(cam))], []
    for k in range(5):
        t = T0_NS + k * 33_333_333
        dets = []
        for tag_id, x in ((3, -0.15), (7, 0.2)):
            cam_T_tag = make_T(
                R_from_rotvec([np.pi + 0.1 * k, 0.2, 0.0]), np.array([x + 0.02 * k, 0.05, 1.2])
            )
            px = true_corners(cam, cam_T_tag, 0.16)
            truth.append(px)
            dets.append((tag_id, px + 0.5, cam_T_tag))
        out.append(("/tag_detections", t, isaac_msg(t, dets)))
    return write_bag(tmp_path / f"isaac_{storage}", out, storage), truth
