"""Write a simulated scene as a rosbag2 folder (images or detections) or an observations folder.

Topics: images ``/camera/color/image_raw`` (rgb8) or ``/camera/color/image_raw/compressed``
(jpeg) with ``/camera/color/camera_info``; or, as the LIMO workflow records, ``/detections``
(apriltag_msgs) with ``/camera_info``. Always ``/ground_truth/camera_pose`` (PoseStamped,
frame ``map`` = world = the anchor tag's frame, world_T_cam). With odometry (the default):
``/odom`` (nav_msgs/Odometry, 50 Hz, :mod:`tagtrail.sim.odometry`) and ``/tf_static`` (base_link →
the camera frame, transient local), written in stamp order among the frames. Detection corners
follow apriltag_ros: detector order (corner i = SPEC tag corner i) and +0.5 px from OpenCV's
convention.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from tqdm import tqdm

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.se3 import R_from_rotvec, make_T, xyz_quat_from_T
from tagtrail.io import msgs
from tagtrail.io.layouts import atomic_write_text, tag_name
from tagtrail.sim import odometry
from tagtrail.sim.camera import FRAME_ID, Visibility, tag_visibility
from tagtrail.sim.odometry import OdomSample
from tagtrail.sim.render import Renderer
from tagtrail.sim.scenarios import SimOptions
from tagtrail.sim.scene import Scene

IMAGE_TOPIC = "/camera/color/image_raw"
COMPRESSED_TOPIC = "/camera/color/image_raw/compressed"
INFO_TOPIC = "/camera/color/camera_info"
DETECTIONS_TOPIC = "/detections"
DETECTIONS_INFO_TOPIC = "/camera_info"
GT_TOPIC = "/ground_truth/camera_pose"
OBS_HEADER = "stamp_sec,stamp_nanosec,tag,x,y,z,qx,qy,qz,qw"


def _t(name: str) -> Any:
    return msgs.typestore().types[name]


def _header(t_ns: int, frame_id: str) -> Any:
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return _t("std_msgs/msg/Header")(
        stamp=_t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec), frame_id=frame_id
    )


def camera_info_msg(scene: Scene, t_ns: int) -> Any:
    c = scene.camera
    P = np.hstack([c.K, np.zeros((3, 1))])
    roi = _t("sensor_msgs/msg/RegionOfInterest")(0, 0, 0, 0, False)
    return _t(msgs.CAMERA_INFO)(
        header=_header(t_ns, FRAME_ID),
        height=c.height,
        width=c.width,
        distortion_model=c.distortion_model,
        d=c.D,
        k=c.K.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=P.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def pose_msg(world_T_cam: F64, t_ns: int) -> Any:
    xyz, q = xyz_quat_from_T(world_T_cam)
    pose = _t("geometry_msgs/msg/Pose")(
        position=_t("geometry_msgs/msg/Point")(*map(float, xyz)),
        orientation=_t("geometry_msgs/msg/Quaternion")(*map(float, q)),
    )
    return _t(msgs.POSE_STAMPED)(header=_header(t_ns, "map"), pose=pose)


def synth_detections(
    scene: Scene, opts: SimOptions, rng: np.random.Generator
) -> tuple[Visibility, F64, F64]:
    """Detector output per frame and tag: ``(visibility, corners (N, M, 4, 2) px in apriltag's
    convention (+0.5, noisy), decision margins (N, M))``."""
    vis = tag_visibility(
        scene.camera,
        scene.cam_T_tags(),
        scene.tag_sizes,
        max_range_m=opts.max_range_m,
        max_incidence_deg=opts.max_incidence_deg,
    )
    noise = rng.normal(0.0, opts.corner_noise_px, vis.corners_px.shape)
    corners = vis.corners_px + 0.5 + noise
    base = 50.0 + 100.0 * np.clip(vis.edge_px / 100.0, 0.0, 1.0) * np.clip(vis.cos_incidence, 0, 1)
    margins = np.clip(base + rng.normal(0.0, 4.0, base.shape), 20.0, 150.0)
    return vis, corners, margins


def _centre(c: F64) -> F64:
    """Intersection of the quad's diagonals (the homography image of the tag centre)."""
    h = np.concatenate([c, np.ones(c.shape[:-1] + (1,))], -1)
    p = np.cross(np.cross(h[0], h[2]), np.cross(h[1], h[3]))
    centre: F64 = p[:2] / p[2]
    return centre


def detections_msg(t_ns: int, frame_id: str, ids: np.ndarray, corners: F64, margins: F64) -> Any:
    Point = _t("apriltag_msgs/msg/Point")
    dets = [
        _t("apriltag_msgs/msg/AprilTagDetection")(
            family="36h11",
            id=int(i),
            hamming=0,
            goodness=0.0,
            decision_margin=float(m),
            centre=Point(*map(float, _centre(c))),
            corners=[Point(float(x), float(y)) for x, y in c],
            homography=np.zeros(9),
        )
        for i, c, m in zip(ids, corners, margins, strict=True)
    ]
    return _t(msgs.DETECTIONS)(header=_header(t_ns, frame_id), detections=dets)


class _Bag:
    def __init__(self, folder: Path, storage: str) -> None:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self.writer = Writer(folder, version=9, storage_plugin=plugin)
        self.conns: dict[str, Any] = {}

    def __enter__(self) -> _Bag:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    def write(self, topic: str, t_ns: int, msg: Any, qos: list[Any] | None = None) -> None:
        mt = msg.__msgtype__
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(
                topic, mt, typestore=msgs.typestore(), offered_qos_profiles=qos or ()
            )
        self.writer.write(self.conns[topic], int(t_ns), msgs.typestore().serialize_cdr(msg, mt))


class _Odometry:
    """Writes ``/tf_static`` once, then each ``/odom`` sample up to a frame's stamp."""

    def __init__(self, bag: _Bag, scene: Scene, opts: SimOptions, samples: list[OdomSample]):
        self.bag, self.samples, self.k = bag, samples, 0
        if samples:
            t0 = int(scene.t_ns[0])
            tf = odometry.tf_static_msg(odometry.base_T_cam(opts.mount), t0, FRAME_ID)
            bag.write(odometry.TF_STATIC_TOPIC, t0, tf, odometry.tf_static_qos())

    def until(self, t_ns: float) -> None:
        """Write the samples stamped at or before ``t_ns`` (all: ``inf``)."""
        while self.k < len(self.samples) and self.samples[self.k].stamp_ns <= t_ns:
            s = self.samples[self.k]
            self.bag.write(odometry.ODOM_TOPIC, s.stamp_ns, s.msg)
            self.k += 1


def write_bag(
    folder: Path,
    scene: Scene,
    opts: SimOptions,
    rng: np.random.Generator,
    odom: list[OdomSample] | None = None,
) -> None:
    """Render (or synthesise detections for) every frame of ``scene`` into the bag ``folder``;
    ``odom``: the ``/odom`` samples to interleave (and ``/tf_static``), drawn by the caller from
    its own generator so that the frames' draws from ``rng`` stay the same with or without."""
    world_T_cam = scene.world_T_cam()
    fid = FRAME_ID
    frames = tqdm(
        range(len(scene.t_ns)),
        desc=scene.name,
        unit="frame",
        leave=False,
        disable=not opts.progress,
    )
    with _Bag(folder, opts.storage) as bag:
        od = _Odometry(bag, scene, opts, odom or [])
        if opts.detections:
            vis, corners, margins = synth_detections(scene, opts, rng)
            for i in frames:
                t, sel = int(scene.t_ns[i]), vis.visible[i]
                od.until(t)
                msg = detections_msg(t, fid, scene.tag_ids[sel], corners[i, sel], margins[i, sel])
                bag.write(DETECTIONS_TOPIC, t, msg)
                bag.write(DETECTIONS_INFO_TOPIC, t, camera_info_msg(scene, t))
                bag.write(GT_TOPIC, t, pose_msg(world_T_cam[i], t))
            od.until(np.inf)
            return
        renderer = Renderer(scene, opts.realism, seed=int(rng.integers(2**31)))
        gains = renderer.gains(len(scene.t_ns), rng)
        for i in frames:
            t = int(scene.t_ns[i])
            od.until(t)
            rgb = renderer.render(scene.scene_T_cam[i], rng, float(gains[i]))
            if opts.compressed:
                ok, buf = cv2.imencode(
                    ".jpg",
                    cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, opts.jpeg_quality],
                )
                msg = _t(msgs.COMPRESSED_IMAGE)(
                    header=_header(t, fid),
                    format="rgb8; jpeg compressed bgr8",
                    data=buf.reshape(-1),
                )
                bag.write(COMPRESSED_TOPIC, t, msg)
            else:
                h, w = rgb.shape[:2]
                msg = _t(msgs.IMAGE)(
                    header=_header(t, fid),
                    height=h,
                    width=w,
                    encoding="rgb8",
                    is_bigendian=0,
                    step=3 * w,
                    data=rgb.reshape(-1),
                )
                bag.write(IMAGE_TOPIC, t, msg)
            bag.write(INFO_TOPIC, t, camera_info_msg(scene, t))
            bag.write(GT_TOPIC, t, pose_msg(world_T_cam[i], t))
        od.until(np.inf)


def write_observations(
    folder: Path, scene: Scene, opts: SimOptions, rng: np.random.Generator
) -> int:
    """Write ``observations.csv`` (cam_T_tag of every tag in view, §4.1 of the paper): exact
    rigid transforms plus zero-mean Gaussian noise, per axis, of std ``noise_t_m`` on the
    translation and ``noise_r_deg`` on the rotation (left-multiplied axis-angle). Returns the
    number of rows."""
    vis = tag_visibility(
        scene.camera,
        scene.cam_T_tags(),
        scene.tag_sizes,
        max_range_m=opts.max_range_m,
        max_incidence_deg=opts.max_incidence_deg,
    )
    fr, tg = np.nonzero(vis.visible)
    cam_T_tag = scene.cam_T_tags()[fr, tg]
    dR = R_from_rotvec(rng.normal(0.0, np.radians(opts.noise_r_deg), (len(fr), 3)))
    dt = rng.normal(0.0, opts.noise_t_m, (len(fr), 3))
    noisy = make_T(dR @ cam_T_tag[:, :3, :3], cam_T_tag[:, :3, 3] + dt)
    xyz, q = xyz_quat_from_T(noisy)
    sec, nsec = np.divmod(scene.t_ns[fr], 1_000_000_000)
    lines = [OBS_HEADER] + [
        f"{s},{n},{tag_name(i)}," + ",".join(repr(float(v)) for v in (*p, *qq))
        for s, n, i, p, qq in zip(sec, nsec, scene.tag_ids[tg], xyz, q, strict=True)
    ]
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "observations.csv", "\n".join(lines) + "\n")
    return len(fr)
