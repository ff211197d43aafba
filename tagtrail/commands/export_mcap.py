"""``tagtrail export-mcap``: one dataset's run as an MCAP file to scrub through in Foxglove and to
play with ``ros2 bag play`` (profile ``ros2``, ``cdr`` messages, ``ros2msg`` schemas holding the
full message definitions), with a Foxglove layout written beside it (``<name>.layout.json``).

Read from the up-to-date artifacts (as ``tagtrail show``/``eval`` do) and from the dataset's
source. Frames per SPEC: ``map`` = the world (the anchor tag; a query's trajectory in the
reference's world, after ``align``), the camera frame = its optical frame, named as the source's
images name it. Channels (those whose data the run has):

- ``/tag_map`` (``visualization_msgs/msg/MarkerArray``, once): each tag's square (the anchor
  orange), its id, and where ``std_pos_m`` is finite a sphere of radius 3·std_pos_m;
- ``/tf_static`` (``tf2_msgs/msg/TFMessage``, once): ``map`` → ``tag36h11:<id>``;
- ``/tf`` (``tf2_msgs/msg/TFMessage``, each pose): ``map`` → the camera;
- ``/reference_path``, ``/query_path`` (``nav_msgs/msg/Path``, once): the reference's smoothed
  trajectory; a query dataset's (aligned) trajectory;
- ``/relocalization/distance_m``, ``/relocalization/heading_error_deg``
  (``std_msgs/msg/Float64``, each row of ``report.relocalization``): D and phi, as the live node
  names them;
- ``/detections/annotations`` (``foxglove_msgs/msg/ImageAnnotations``, each frame with
  detections): the tags' outlines and ids, drawn on the image by Foxglove's Image panel;
- the source's image (or detection) and camera_info topics, copied from a rosbag2 as recorded;
  an image folder's files as ``/camera/image/compressed`` with ``/camera/camera_info``.

Static messages are logged at the run's first stamp with transient-local QoS offers (as a latched
publisher's), so ``ros2 bag play`` hands them to late subscribers too.
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import math
from collections.abc import Iterator, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tagtrail.errors import SpecError

EXAMPLES = """examples:
  tagtrail export-mcap -o reference.mcap
  tagtrail export-mcap --dataset query_1 -o query_1.mcap
  ros2 bag play query_1.mcap          # ROS 2 Iron or newer; Humble: ros2 bag play -s mcap …
"""
LAYOUT = Path(__file__).with_name("foxglove_layout.json")
CAMERA_FRAME = "camera"  # when the source names none
ANNOTATIONS = "/detections/annotations"
TAG_MAP, TF, TF_STATIC = "/tag_map", "/tf", "/tf_static"
REFERENCE_PATH, QUERY_PATH = "/reference_path", "/query_path"
DISTANCE, HEADING = "/relocalization/distance_m", "/relocalization/heading_error_deg"
FOLDER_IMAGE, FOLDER_CAMERA_INFO = "/camera/image/compressed", "/camera/camera_info"
STD_SIGMAS = 3.0  # the uncertainty spheres' radius in standard deviations
_ORANGE, _BLUE, _RED, _GREEN = (
    (1.0, 0.55, 0.0, 1.0),
    (0.2, 0.6, 1.0, 0.9),
    (1.0, 0.2, 0.2, 0.3),
    (0.1, 0.9, 0.3, 1.0),
)

# foxglove_msgs (ROS 2 package ros-$ROS_DISTRO-foxglove-msgs), the fields Foxglove's Image panel
# reads; topics of a type a player's ROS lacks are skipped by ros2 bag play with a warning.
FOXGLOVE_MSGS = {
    "foxglove_msgs/msg/Color": "float64 r\nfloat64 g\nfloat64 b\nfloat64 a\n",
    "foxglove_msgs/msg/Point2": "float64 x\nfloat64 y\n",
    "foxglove_msgs/msg/CircleAnnotation": (
        "builtin_interfaces/Time timestamp\nfoxglove_msgs/Point2 position\nfloat64 diameter\n"
        "float64 thickness\nfoxglove_msgs/Color fill_color\nfoxglove_msgs/Color outline_color\n"
    ),
    "foxglove_msgs/msg/PointsAnnotation": (
        "builtin_interfaces/Time timestamp\nuint8 UNKNOWN=0\nuint8 POINTS=1\nuint8 LINE_LOOP=2\n"
        "uint8 LINE_STRIP=3\nuint8 LINE_LIST=4\nuint8 type\nfoxglove_msgs/Point2[] points\n"
        "foxglove_msgs/Color outline_color\nfoxglove_msgs/Color[] outline_colors\n"
        "foxglove_msgs/Color fill_color\nfloat64 thickness\n"
    ),
    "foxglove_msgs/msg/TextAnnotation": (
        "builtin_interfaces/Time timestamp\nfoxglove_msgs/Point2 position\nstring text\n"
        "float64 font_size\nfoxglove_msgs/Color text_color\n"
        "foxglove_msgs/Color background_color\n"
    ),
    "foxglove_msgs/msg/ImageAnnotations": (
        "foxglove_msgs/CircleAnnotation[] circles\nfoxglove_msgs/PointsAnnotation[] points\n"
        "foxglove_msgs/TextAnnotation[] texts\n"
    ),
}
IMAGE_ANNOTATIONS = "foxglove_msgs/msg/ImageAnnotations"
_INF = "{sec: 2147483647, nsec: 4294967295}"


def qos(latched: bool) -> str:
    """rosbag2's ``offered_qos_profiles`` YAML: reliable, transient local if ``latched``."""
    return (
        f"- history: 3\n  depth: 0\n  reliability: 1\n  durability: {1 if latched else 2}\n"
        f"  deadline: {_INF}\n  lifespan: {_INF}\n  liveliness: 1\n"
        f"  liveliness_lease_duration: {_INF}\n  avoid_ros_namespace_conventions: false\n"
    )


@lru_cache(maxsize=1)
def typestore() -> Any:
    """tagtrail's Humble typestore plus ``foxglove_msgs`` (a private copy: the shared one is not
    changed)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from tagtrail.io import msgs

    store = get_typestore(Stores.ROS2_HUMBLE)  # a new store each call
    types: dict[str, Any] = {}
    for name, text in {**msgs.APRILTAG_MSGS, **FOXGLOVE_MSGS}.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def ros2msg(typename: str) -> bytes:
    """The full ``ros2msg`` definition of ``typename`` (dependencies after ``====`` lines)."""
    text, _ = typestore().generate_msgdef(typename, ros_version=2)
    return str(text).encode()


# --- messages ----------------------------------------------------------------------------------


def _T() -> Any:
    return typestore().types


def _cdr(msg: Any) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def _stamp(t_ns: int) -> Any:
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return _T()["builtin_interfaces/msg/Time"](sec, nsec)


def _header(t_ns: int, frame_id: str) -> Any:
    return _T()["std_msgs/msg/Header"](_stamp(t_ns), frame_id)


def _pose(row: Sequence[float]) -> Any:
    T = _T()
    return T["geometry_msgs/msg/Pose"](
        T["geometry_msgs/msg/Point"](*map(float, row[:3])),
        T["geometry_msgs/msg/Quaternion"](*map(float, row[3:7])),
    )


POSE7 = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]


def path_msg(traj: pd.DataFrame, frame_id: str, t_ns: int) -> bytes:
    """``nav_msgs/msg/Path`` of a trajectory (``t_ns`` + pose columns), each pose its stamp."""
    T = _T()
    PS = T["geometry_msgs/msg/PoseStamped"]
    poses = [
        PS(_header(t, frame_id), _pose(row))
        for t, row in zip(
            traj["t_ns"].tolist(), traj[POSE7].to_numpy(np.float64).tolist(), strict=True
        )
    ]
    return _cdr(T["nav_msgs/msg/Path"](_header(t_ns, frame_id), poses))


def _transform(t_ns: int, parent: str, child: str, row: Sequence[float]) -> Any:
    T = _T()
    return T["geometry_msgs/msg/TransformStamped"](
        _header(t_ns, parent),
        child,
        T["geometry_msgs/msg/Transform"](
            T["geometry_msgs/msg/Vector3"](*map(float, row[:3])),
            T["geometry_msgs/msg/Quaternion"](*map(float, row[3:7])),
        ),
    )


def tf_msgs(traj: pd.DataFrame, camera_frame: str) -> Iterator[tuple[int, bytes]]:
    """``tf2_msgs/msg/TFMessage`` ``map → camera_frame`` (world_T_cam) for each pose."""
    TF_ = _T()["tf2_msgs/msg/TFMessage"]
    for t, row in zip(
        traj["t_ns"].tolist(), traj[POSE7].to_numpy(np.float64).tolist(), strict=True
    ):
        yield int(t), _cdr(TF_([_transform(t, "map", camera_frame, row)]))


def tag_frames_msg(tags: pd.DataFrame, t_ns: int) -> bytes:
    """One ``TFMessage``: ``map → tag36h11:<id>`` (world_T_tag) for every mapped tag."""
    rows = tags[POSE7].to_numpy(np.float64).tolist()
    return _cdr(
        _T()["tf2_msgs/msg/TFMessage"](
            [
                _transform(t_ns, "map", f"tag36h11:{int(i)}", r)
                for i, r in zip(tags["tag_id"].tolist(), rows, strict=True)
            ]
        )
    )


def tag_map_msg(tags: pd.DataFrame, anchor_id: int, t_ns: int) -> tuple[bytes, int]:
    """The map as a ``MarkerArray`` (and its marker count): per tag a square (a thin CUBE in the
    tag's frame, its edge ``size_m``; the anchor orange), its id above it (TEXT_VIEW_FACING), and
    where ``std_pos_m`` is finite a SPHERE of radius 3·std_pos_m."""
    from tagtrail.stream.markers import marker

    M = _T()["visualization_msgs/msg/Marker"]
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    std = (
        tags["std_pos_m"].to_numpy(np.float64)
        if "std_pos_m" in tags
        else np.full(len(tags), np.nan)
    )
    out = []
    for k, (tag_id, row) in enumerate(
        zip(
            tags["tag_id"].astype(int).tolist(),
            tags[POSE7].to_numpy(np.float64).tolist(),
            strict=True,
        )
    ):
        s = float(tags["size_m"].iloc[k]) if "size_m" in tags else 0.16
        anchor = tag_id == anchor_id
        square = marker(
            "tags",
            tag_id,
            M.CUBE,
            "map",
            sec,
            nsec,
            scale=(s, s, 0.004),
            color=_ORANGE if anchor else _BLUE,
        )
        out.append(dataclasses.replace(square, pose=_pose(row)))
        z_tag = _rotate(row[3:7], (0.0, 0.0, 1.0))  # the tag's normal, out of its face
        label = f"tag36h11:{tag_id}" + (" (anchor)" if anchor else "")
        out.append(
            marker(
                "tag_ids",
                tag_id,
                M.TEXT_VIEW_FACING,
                "map",
                sec,
                nsec,
                position=(np.asarray(row[:3]) + 0.6 * s * np.asarray(z_tag)).tolist(),
                scale=(0.0, 0.0, max(0.05, 0.4 * s)),
                text=label,
            )
        )
        if math.isfinite(std[k]) and std[k] > 0:
            d = 2 * STD_SIGMAS * float(std[k])
            out.append(
                marker(
                    "tag_std_3sigma",
                    tag_id,
                    M.SPHERE,
                    "map",
                    sec,
                    nsec,
                    position=row[:3],
                    scale=(d, d, d),
                    color=_RED,
                )
            )
    return _cdr(_T()["visualization_msgs/msg/MarkerArray"](out)), len(out)


def _rotate(q_xyzw: Sequence[float], v: Sequence[float]) -> tuple[float, float, float]:
    from tagtrail.geometry import se3

    R = se3.R_from_quat_xyzw(np.asarray(q_xyzw, dtype=np.float64))
    return tuple(float(c) for c in R @ np.asarray(v, dtype=np.float64))  # type: ignore[return-value]


def float_msg(value: float) -> bytes:
    return _cdr(_T()["std_msgs/msg/Float64"](float(value)))


def annotation_msgs(dets: pd.DataFrame, anchor_id: int | None) -> Iterator[tuple[int, bytes]]:
    """``foxglove_msgs/msg/ImageAnnotations`` per frame of ``extract.detections``: each tag's
    outline (LINE_LOOP through corners 0..3) and its id at its centre. Foxglove puts the origin at
    the top-left pixel's corner, OpenCV (the artifact) at its centre: +0.5 px."""
    T = _T()
    Pt, C = T["foxglove_msgs/msg/Point2"], T["foxglove_msgs/msg/Color"]
    PA, TA = T["foxglove_msgs/msg/PointsAnnotation"], T["foxglove_msgs/msg/TextAnnotation"]
    clear = C(0.0, 0.0, 0.0, 0.0)
    corners = [f"c{i}{a}" for i in range(4) for a in "xy"]
    for _, grp in dets.groupby("t_ns", sort=True):
        t_ns = int(grp["t_ns"].iloc[0])
        stamp = _stamp(t_ns)
        xy = grp[corners].to_numpy(np.float64).reshape(-1, 4, 2) + 0.5
        points, texts = [], []
        for tag_id, quad in zip(grp["tag_id"].astype(int).tolist(), xy, strict=True):
            color = C(*(_ORANGE if tag_id == anchor_id else _GREEN))
            points.append(
                PA(stamp, PA.LINE_LOOP, [Pt(*p) for p in quad.tolist()], color, [], clear, 2.0)
            )
            cx, cy = quad.mean(axis=0).tolist()
            texts.append(TA(stamp, Pt(cx, cy), str(tag_id), 14.0, color, C(0.0, 0.0, 0.0, 0.6)))
        yield t_ns, _cdr(T[IMAGE_ANNOTATIONS]([], points, texts))


def camera_info_msg(camera: Any, t_ns: int, frame_id: str) -> bytes:
    """``sensor_msgs/msg/CameraInfo`` of a :class:`~tagtrail.geometry.camera.CameraModel`."""
    T = _T()
    K = np.asarray(camera.K, dtype=np.float64).reshape(3, 3)
    P = np.hstack([K, np.zeros((3, 1))])
    roi = T["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False)
    return _cdr(
        T["sensor_msgs/msg/CameraInfo"](
            _header(t_ns, frame_id),
            int(camera.height),
            int(camera.width),
            str(camera.distortion_model),
            np.asarray(camera.D, dtype=np.float64),
            K.reshape(-1),
            np.eye(3).reshape(-1),
            P.reshape(-1),
            0,
            0,
            roi,
        )
    )


# --- the source's own messages -----------------------------------------------------------------


def source_messages(source: Any, notes: list[str]) -> tuple[dict[str, str], list[Iterator[Any]]]:
    """The topics to copy from a dataset's source (topic → type) and iterators of
    ``(t_ns, topic, cdr)`` over them, each in recording order: a bag's image (or detection) and
    camera_info topics, an image folder's files as CompressedImage; nothing for observations."""
    from tagtrail.io.sources import BagSource, ImageFolderSource

    if isinstance(source, BagSource):
        if source.path.suffix == ".bag":
            notes.append(
                f"{source.path}: a ROS 1 bag's messages are not copied (ROS 1 "
                "encoding); the detections are drawn from the artifacts"
            )
            return {}, []
        from tagtrail.io.bags import open_bag

        reader = open_bag(source.path)
        try:
            types = {c.topic: c.msgtype for c in reader.connections}
        finally:
            reader.close()
        topics = {t: types[t] for t in (source.topic, source.camera_info_topic) if t}
        unknown = [t for t, m in topics.items() if m not in typestore().types]
        for t in unknown:
            notes.append(f"{t} ({topics.pop(t)}) not copied: no definition of its type")
        return topics, [_bag_messages(source.path, topics)]
    if isinstance(source, ImageFolderSource):
        topics = {FOLDER_IMAGE: "sensor_msgs/msg/CompressedImage"}
        return topics, [_folder_images(source)]
    return {}, []


def _bag_messages(path: Path, topics: dict[str, str]) -> Iterator[Any]:
    """A rosbag2's messages on ``topics``, the CDR bytes as recorded; log time = the header
    stamp (receive time when it is zero), as the artifacts' ``t_ns``."""
    from tagtrail.io.bags import open_bag

    reader = open_bag(path)
    try:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, t_recv, raw in reader.messages(connections=conns):
            msg: Any = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp
            t_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec) or int(t_recv)
            yield t_ns, conn.topic, bytes(raw)
    finally:
        reader.close()


def _folder_images(source: Any) -> Iterator[Any]:
    CI = typestore().types["sensor_msgs/msg/CompressedImage"]
    for f, t_ns in zip(source.files, source.stamps_ns.tolist(), strict=True):
        fmt = "png" if f.suffix.lower() == ".png" else "jpeg"
        data = np.frombuffer(f.read_bytes(), dtype=np.uint8)
        yield int(t_ns), FOLDER_IMAGE, _cdr(CI(_header(t_ns, CAMERA_FRAME), fmt, data))


def camera_frame_of(source: Any) -> str:
    """The frame_id of the source's first image/detection message (else ``camera``)."""
    from tagtrail.io.bags import open_bag
    from tagtrail.io.sources import BagSource

    if not isinstance(source, BagSource):
        return CAMERA_FRAME
    reader = open_bag(source.path)
    try:
        conns = [c for c in reader.connections if c.topic == source.topic]
        for conn, _, raw in reader.messages(connections=conns):
            msg: Any = reader.deserialize(raw, conn.msgtype)
            return str(msg.header.frame_id) or CAMERA_FRAME
    finally:
        reader.close()
    return CAMERA_FRAME


# --- the command -------------------------------------------------------------------------------


class Run:
    """The up-to-date artifacts of one plan (``runner.plan()`` once): :meth:`get` loads one."""

    def __init__(self, runner: Any, ns: argparse.Namespace) -> None:
        self.runner, self.ns = runner, ns
        self.status = {(s.stage, s.dataset): s for s in runner.plan()}

    def get(self, stage: str, output: str, dataset: str, required: bool = True) -> Any:
        """``stage.output`` of ``dataset``; None when that node does not run (or, if not
        ``required``, is absent); a one-line :class:`SpecError` when it is not up to date."""
        st = self.status.get((stage, dataset))
        if st is None:
            if required:
                from tagtrail.runner.dag import Node

                why = self.runner.graph.skipped.get(Node(stage, dataset), "not in the pipeline")
                raise SpecError(f"{stage} [{dataset}] does not run: {why}")
            return None
        if st.status != "cached":
            words = ["tagtrail", "run"]
            if str(self.ns.pipeline) != "pipeline.yaml":
                words += ["-p", str(self.ns.pipeline)]
            for o in self.ns.set or ():
                words += ["-S", o]
            raise SpecError(
                f"{stage} [{dataset}] is not up to date: run `{' '.join(words)}` first, then export"
            )
        return self.runner.store.load(stage, st.key, output)


class Channels:
    """An ``mcap`` writer's schemas and channels, registered on first use; counts messages."""

    def __init__(self, writer: Any) -> None:
        self.w = writer
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.types: dict[str, str] = {}
        self.counts: dict[str, int] = {}

    def add(self, topic: str, typename: str, latched: bool = False) -> None:
        if typename not in self._schemas:
            self._schemas[typename] = self.w.register_schema(
                name=typename, encoding="ros2msg", data=ros2msg(typename)
            )
        self._channels[topic] = self.w.register_channel(
            topic=topic,
            message_encoding="cdr",
            schema_id=self._schemas[typename],
            metadata={"offered_qos_profiles": qos(latched)},
        )
        self.types[topic], self.counts[topic] = typename, 0

    def write(self, t_ns: int, topic: str, data: bytes) -> None:
        seq = self.counts[topic]
        self.w.add_message(
            channel_id=self._channels[topic],
            log_time=int(t_ns),
            publish_time=int(t_ns),
            sequence=seq,
            data=data,
        )
        self.counts[topic] = seq + 1


def export(
    run: Run, dataset: str, out: Path, images: bool = True
) -> tuple[Channels, list[str], dict[str, str]]:
    """Write ``dataset``'s MCAP to ``out`` (atomically); returns its channels, notes for the user
    and the topics the layout names (image, camera_info)."""
    from mcap.writer import CompressionType, Writer

    from tagtrail.io.layouts import atomic_write
    from tagtrail.io.sources import open_source

    pipe = run.runner.pipe
    ref_ds = pipe.reference
    query = dataset != ref_ds and (run.status.get(("align", dataset)) is not None)
    traj = run.get("align" if query else "smooth", "trajectory", dataset)
    ref_traj = run.get("smooth", "trajectory", ref_ds)
    tags = run.get("optimize", "tag_map", ref_ds)
    anchor_id = int(run.get("optimize", "report", ref_ds).anchor_id)
    reloc = run.get("report", "relocalization", dataset, required=False) if query else None
    dets = run.get("extract", "detections", dataset, required=False)
    camera = run.get("extract", "camera", dataset, required=False)
    notes: list[str] = []
    source = open_source(pipe.datasets[dataset])
    try:
        frame = camera_frame_of(source)
        copied, streams = source_messages(source, notes) if images else ({}, [])
    except BaseException:
        source.close()
        raise
    times = [int(traj["t_ns"].iloc[0])] if len(traj) else []
    if dets is not None and len(dets):
        times.append(int(dets["t_ns"].min()))
    t0 = min(times) if times else 0

    made: list[tuple[int, str, bytes]] = []
    map_bytes, _ = tag_map_msg(tags, anchor_id, t0)
    made += [
        (t0, TAG_MAP, map_bytes),
        (t0, TF_STATIC, tag_frames_msg(tags, t0)),
        (t0, REFERENCE_PATH, path_msg(ref_traj, "map", t0)),
    ]
    if query:
        made.append((t0, QUERY_PATH, path_msg(traj, "map", t0)))
    made += [(t, TF, b) for t, b in tf_msgs(traj, frame)]
    if reloc is not None:
        for t, d, phi in zip(
            reloc["t_ns"].tolist(),
            reloc["distance_m"].tolist(),
            reloc["heading_error_deg"].tolist(),
            strict=True,
        ):
            made += [(int(t), DISTANCE, float_msg(d)), (int(t), HEADING, float_msg(phi))]
    if dets is not None and len(dets):
        made += [(t, ANNOTATIONS, b) for t, b in annotation_msgs(dets, anchor_id)]
    layout_topics = {"image": "", "camera_info": ""}
    for topic, typename in copied.items():
        if typename in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"):
            layout_topics["image"] = topic
        elif typename == "sensor_msgs/msg/CameraInfo":
            layout_topics["camera_info"] = topic
    if camera is not None and images and not layout_topics["camera_info"]:
        layout_topics["camera_info"] = FOLDER_CAMERA_INFO
        # at each image of a folder, else at each pose
        stamps = (
            [int(t) for t in getattr(source, "stamps_ns", ())]
            or sorted({t for t, top, _ in made if top == TF})
            or [t0]
        )
        made += [(t, FOLDER_CAMERA_INFO, camera_info_msg(camera, t, frame)) for t in stamps]
        copied[FOLDER_CAMERA_INFO] = "sensor_msgs/msg/CameraInfo"
    made.sort(key=lambda m: m[0])
    types = {
        TAG_MAP: "visualization_msgs/msg/MarkerArray",
        TF_STATIC: "tf2_msgs/msg/TFMessage",
        REFERENCE_PATH: "nav_msgs/msg/Path",
        QUERY_PATH: "nav_msgs/msg/Path",
        TF: "tf2_msgs/msg/TFMessage",
        DISTANCE: "std_msgs/msg/Float64",
        HEADING: "std_msgs/msg/Float64",
        ANNOTATIONS: IMAGE_ANNOTATIONS,
    }
    latched = {TAG_MAP, TF_STATIC, REFERENCE_PATH, QUERY_PATH}
    channels: list[Channels] = []

    def write(tmp: Path) -> None:
        with tmp.open("wb") as fh:
            w: Any = Writer(fh, compression=CompressionType.ZSTD)
            w.start(profile="ros2", library="tagtrail export-mcap")
            ch = Channels(w)
            present = {top for _, top, _ in made}
            for topic, typename in types.items():
                if topic in present:
                    ch.add(topic, typename, latched=topic in latched)
            for topic, typename in copied.items():
                if topic not in ch.types:
                    ch.add(topic, typename)
            merged = heapq.merge(iter(made), *streams, key=lambda m: m[0])
            for t_ns, topic, data in merged:
                ch.write(t_ns, topic, data)
            w.finish()
            channels.append(ch)

    try:
        atomic_write(out, write)
    finally:
        source.close()
    return channels[0], notes, layout_topics


def layout_json(image_topic: str, camera_info_topic: str, present: set[str]) -> str:
    """The shipped Foxglove layout with the run's image and camera_info topics filled in; what it
    names of topics not in ``present`` (the MCAP's) is left out (a reference run has no D/phi)."""
    doc = json.loads(LAYOUT.read_text(encoding="utf-8"))
    fill = {"{image_topic}": image_topic, "{camera_info_topic}": camera_info_topic}
    topic_values = ("imageTopic", "calibrationTopic", "cameraInfoTopic")

    def absent(topic: str) -> bool:
        return not topic or (topic.startswith("/") and topic not in present)

    def walk(v: Any) -> Any:
        if isinstance(v, dict):
            out = {}
            for key, x in v.items():
                k = fill[key] if key in fill else str(key)
                if (key in fill or k.startswith("/")) and absent(k):
                    continue  # a topic's settings
                if isinstance(x, str):
                    x = fill.get(x, x)
                    if k in topic_values and absent(x):
                        continue
                    if k == "value" and absent(x.rsplit(".", 1)[0]):
                        return None  # a plot series of a topic the run lacks
                out[k] = walk(x)
            return out
        if isinstance(v, list):
            return [y for y in map(walk, v) if y is not None]
        return v

    return json.dumps(walk(doc), indent=2) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``export-mcap`` arguments to ``parser`` (returned)."""
    parser.epilog = EXAMPLES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("-p", "--pipeline", default="pipeline.yaml", help="pipeline file")
    parser.add_argument("--dataset", default=None, help="dataset (default: the reference)")
    parser.add_argument(
        "-S",
        "--set",
        action="append",
        metavar="STAGE.PARAM=VALUE",
        help="the parameter overrides the run was made with (repeatable)",
    )
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        metavar="FILE.mcap",
        help="the MCAP file to write (its layout: FILE.layout.json beside it)",
    )
    parser.add_argument(
        "--no-images",
        action="store_true",
        help="leave the source's image/detection/camera_info messages out",
    )
    return parser


def build_parser() -> argparse.ArgumentParser:
    return add_arguments(
        argparse.ArgumentParser(
            prog="tagtrail export-mcap",
            description="One run as an MCAP file for Foxglove and ros2 bag play.",
        )
    )


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """Run from parsed arguments (or an argv list); 0 on success, the error's exit code else."""
    from tagtrail.cli import run_command

    ns = args if isinstance(args, argparse.Namespace) else build_parser().parse_args(args)
    return run_command(lambda: _main(ns))


def layout_path(out: Path) -> Path:
    return out.with_name(out.stem + ".layout.json")


def _main(ns: argparse.Namespace) -> int:
    from tagtrail.io.layouts import atomic_write_text
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import did_you_mean, load_pipeline
    from tagtrail.stages import REGISTRY

    out = Path(ns.output)
    if out.is_dir():
        raise SpecError(f"-o {out}: is a folder; name the .mcap file to write")
    pipe = load_pipeline(Path(ns.pipeline), REGISTRY, ns.set or ())
    dataset = ns.dataset if ns.dataset is not None else pipe.reference
    if dataset not in pipe.datasets:
        raise SpecError(f"unknown dataset {dataset!r}{did_you_mean(dataset, pipe.datasets)}")
    ch, notes, topics = export(Run(Runner(pipe), ns), dataset, out, images=not ns.no_images)
    layout = layout_path(out)
    atomic_write_text(layout, layout_json(topics["image"], topics["camera_info"], set(ch.types)))
    width = max(map(len, ch.types))
    print(
        f"wrote {out} [{dataset}]: {sum(ch.counts.values()):,} messages on {len(ch.types)} topics"
    )
    for topic, typename in ch.types.items():
        print(f"  {topic:<{width}}  {ch.counts[topic]:>7,}  {typename}")
    for note in notes:
        print(f"note: {note}")
    print(f"Foxglove layout: {layout} (Layouts → Import from file)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
