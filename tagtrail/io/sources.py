"""Dataset sources: rosbag2 folders (MCAP/sqlite3), ROS 1 bags, image folders, observations.

:func:`open_source` inspects a :class:`~tagtrail.schemas.pipeline.DatasetConfig` and returns a
source of one of three kinds:

- ``"images"`` — frames are :class:`~tagtrail.vision.images.RawImage` (undecoded; ``decode()`` them,
  preferably in worker processes — iterating the source itself decodes in-process);
- ``"detections"`` — frames are lists of :class:`TagDetection` (apriltag_ros ROS 2, TagSLAM's
  ROS 1 ``ApriltagArrayStamped``, isaac_ros_apriltag; :data:`tagtrail.io.msgs.DETECTION_SOURCES`
  declares each type's corner convention and quality fields);
- ``"observations"`` — camera→tag poses given directly (``observations.csv``).

Every source yields ``(frame_idx, t_ns, payload)`` in recording order; ``frame_idx`` counts from 0.

Topic choice in bags: ``topics.detections`` set → a detection source; otherwise an image source
when the bag has an image topic (``sensor_msgs/Image`` or ``CompressedImage``), else a detection
source. Each choice must be unambiguous or named in ``pipeline.yaml`` (``topics: {image: ...}``).
Stamps come from message headers (receive time when a header stamp is zero); the camera model
from ``DatasetConfig.camera`` if given, else the first ``CameraInfo`` message (a warning if it
changes later). Corners of detection messages are converted to the OpenCV pixel convention by
their type's declared offset; a field the type lacks is "not carried" (hamming -1, margin NaN).
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, SupportsInt, cast

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from tagtrail.errors import SourceError
from tagtrail.geometry.camera import CameraModel
from tagtrail.io import msgs
from tagtrail.io.bags import BAG_FILE_SUFFIXES, open_bag
from tagtrail.io.camera_files import read_camera_file, split_camera_path
from tagtrail.io.layouts import integer_column, read_csv_table, read_stamped_poses, tag_ids
from tagtrail.schemas.artifacts import columns
from tagtrail.schemas.inputs import Odometry, StaticFrames, StaticTransform
from tagtrail.schemas.pipeline import DatasetConfig
from tagtrail.vision.detector import TagDetection
from tagtrail.vision.images import RawImage

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger("tagtrail.sources")

Kind = Literal["images", "detections", "observations"]
IMAGE_EXTS = (".jpg", ".jpeg", ".png")
IMAGE_TYPES = (msgs.IMAGE, msgs.COMPRESSED_IMAGE)
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"
ODOM_TOPIC = "/odom"  # preferred when a bag has several Odometry topics
ODOMETRY_COLS = columns("extract.odometry")
UNKNOWN_VARIANCE = 1e3  # a variance this large (m², rad²) is ROS' "unknown" marker, not a value
FOLDER_PERIOD_NS = 100_000_000  # image folders without stamps.csv: 10 Hz from t = 0
MAX_CORNER_PX = 1e6  # a detection corner farther out is a corrupt message
STAMPS_HEADER = ["file", "stamp_sec", "stamp_nanosec"]
# Compressed files tagtrail does not read, and the command that unpacks each (keeping the file).
UNPACK = {".bz2": "bunzip2 -k", ".gz": "gunzip -k", ".zst": "unzstd", ".xz": "unxz -k"}
OBS_CSV_HEADER = ["stamp_sec", "stamp_nanosec", "tag", "x", "y", "z", "qx", "qy", "qz", "qw"]


Frame = tuple[int, int, Any]


class Source:
    """Base of every source: ``kind``, ``camera()``, ``len()``, iteration, ``chunks()``."""

    kind: Kind
    path: Path
    camera_origin: str = "the camera model"  # where camera() comes from, for messages
    timed: bool = True  # stamps are capture times (not an image folder's file order)

    def camera(self) -> CameraModel | None:
        """The camera model (None for observations sources)."""
        raise NotImplementedError

    def __len__(self) -> int:
        raise NotImplementedError

    def iter_raw(self) -> Iterator[Frame]:
        """``(frame_idx, t_ns, payload)`` with images left undecoded (:class:`RawImage`)."""
        raise NotImplementedError

    def __iter__(self) -> Iterator[Frame]:
        """``(frame_idx, t_ns, payload)``; images decoded to gray uint8 ``(H, W)``."""
        for idx, t_ns, payload in self.iter_raw():
            yield idx, t_ns, payload.decode() if isinstance(payload, RawImage) else payload

    def chunks(self, size: int) -> Iterator[list[Frame]]:
        """Lists of up to ``size`` consecutive raw frames (to ship to worker processes)."""
        chunk: list[Frame] = []
        for frame in self.iter_raw():
            chunk.append(frame)
            if len(chunk) >= size:
                yield chunk
                chunk = []
        if chunk:
            yield chunk

    def observations(self) -> pd.DataFrame:
        """Observations sources: ``t_ns, frame_idx, tag_id`` + pose columns (cam_T_tag)."""
        raise SourceError(f"{self.path}: a {self.kind} source carries no observations")

    def describe(self) -> str:
        return f"{self.kind} source {self.path}"

    def odometry(self) -> Odometry | None:
        """The recording's wheel odometry (None: it has none; only bags can)."""
        return None

    def static_frames(self) -> StaticFrames:
        """The camera's frame and the ``/tf_static`` transforms (none outside bags)."""
        return StaticFrames()

    def frame_name(self, frame_idx: int, t_ns: int) -> str:
        """How messages name a frame (a file name for image folders)."""
        return f"frame {frame_idx} at {t_ns // 1_000_000_000}.{t_ns % 1_000_000_000:09d} s"

    def close(self) -> None:
        """Release open files (sources reopen them when iterated again)."""

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def source_kind(path: Path) -> str:
    """What ``path`` is as a dataset source, from its shape alone (a few ``stat`` calls and one
    folder listing, nothing read): ``bag1``, ``bag2``, ``observations`` or ``images``; anything
    else (``/usr``, an empty folder) raises :class:`SourceError` with one clear message."""
    path = Path(path)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder (dataset source)")
    if path.is_file() and path.suffix in UNPACK:
        raise SourceError(
            f"{path}: a compressed file; unpack it first (`{UNPACK[path.suffix]} "
            f"{path}`) and name {path.with_suffix('').name} as the source"
        )
    if path.is_file():
        if path.suffix == ".bag":
            return "bag1"
        if path.suffix in BAG_FILE_SUFFIXES:
            if (path.parent / "metadata.yaml").is_file():
                return "bag2"
            raise SourceError(
                f"{path}: no metadata.yaml next to it; a rosbag2 recording is a folder "
                f"(`ros2 bag reindex {path.parent}` or `tagtrail stream record --recover "
                f"{path.parent}` recreates a lost metadata.yaml)"
            )
        if path.name == "observations.csv":
            return "observations"
        raise SourceError(
            f"{path}: not a source (expected a rosbag2 folder, a ROS 1 .bag, an image folder or "
            "an observations folder)"
        )
    if (path / "metadata.yaml").is_file():
        return "bag2"
    if (path / "observations.csv").is_file():
        return "observations"
    if _image_files(path):
        return "images"
    if any(path.glob("*.mcap")) or any(path.glob("*.db3")):
        raise SourceError(
            f"{path}: bag files without metadata.yaml (`ros2 bag reindex {path}` or "
            f"`tagtrail stream record --recover {path}` recreates it)"
        )
    bags = sorted(path.glob("*.bag"))
    if bags:
        raise SourceError(f"{path}: holds ROS 1 bags; name one as the source, e.g. {bags[0]}")
    packed = sorted(p for p in path.iterdir() if p.suffix in UNPACK)
    if packed:
        raise SourceError(
            f"{path}: holds compressed files only; unpack one first, e.g. "
            f"`{UNPACK[packed[0].suffix]} {packed[0]}`"
        )
    raise SourceError(
        f"{path}: empty or unrecognised source folder (expected metadata.yaml of a rosbag2 "
        f"recording, jpg/png images, or observations.csv)"
    )


def open_source(cfg: DatasetConfig) -> Source:
    """The source a dataset names; raises :class:`SourceError` with one clear message."""
    path = Path(cfg.source)
    kind = source_kind(path)
    camera = _camera_override(cfg.camera)
    if kind == "bag1":
        return BagSource(path, cfg, camera)
    if kind == "bag2":
        return BagSource(path if path.is_dir() else path.parent, cfg, camera)
    if kind == "observations":
        return ObservationsSource(path if path.is_dir() else path.parent)
    return ImageFolderSource(path, camera, cfg.camera)


def _camera_override(path: Path | None) -> CameraModel | None:
    if path is None:
        return None
    if not split_camera_path(path)[0].is_file():
        raise SourceError(f"{path}: camera file not found (`camera:` of the dataset)")
    return read_camera_file(path)


# --- bags ------------------------------------------------------------------------------------


def _stamp_ns(stamp: Any) -> int:
    sec = stamp.sec if hasattr(stamp, "sec") else stamp.secs
    nsec = stamp.nanosec if hasattr(stamp, "nanosec") else stamp.nsecs
    return int(sec) * 1_000_000_000 + int(nsec)


def detections_from_msg(msg: Any, msgtype: str = msgs.DETECTIONS) -> list[TagDetection]:
    """A detection message of type ``msgtype`` (one of :data:`msgs.DETECTION_SOURCES`) as
    :class:`TagDetection` s, corners moved to OpenCV's convention by the type's declared offset.
    Fields the type lacks come out as "not carried": hamming -1, decision margin NaN, family ""
    (tagtrail's tag36h11 assumed)."""
    kind = msgs.DETECTION_SOURCES[msgtype]
    items = msg.apriltags if msgtype == msgs.TAGSLAM_DETECTIONS else msg.detections
    out = []
    for d in items:
        family = str(d.family)
        corners = np.array([[c.x, c.y] for c in d.corners], dtype=np.float64)
        out.append(
            TagDetection(
                tag_id=int(d.id),
                hamming=int(d.hamming) if kind.hamming else -1,
                decision_margin=float(d.decision_margin) if kind.decision_margin else float("nan"),
                corners=corners - kind.pixel_offset(family),
                family=family if kind.family else "",
            )
        )
    return out


def detection_problem(dets: list[TagDetection]) -> str | None:
    """What is wrong with a message's detections (None: nothing): a negative tag id, a corner
    that is not a finite pixel position within :data:`MAX_CORNER_PX`. Bag sources refuse such a
    message in one line; the live localize node drops and counts it (``bad_detection``)."""
    for d in dets:
        if d.tag_id < 0:
            return f"a detection of tag id {d.tag_id} (ids are >= 0)"
        c = np.asarray(d.corners, dtype=np.float64)
        bad = ~(np.abs(c) <= MAX_CORNER_PX).all(axis=-1)
        if bad.any():
            k = int(np.argmax(bad))
            return (
                f"tag {d.tag_id}: corner {k} is {tuple(c[k].tolist())}, not a pixel "
                "position (finite, within 1e6 px)"
            )
    return None


def raw_image_from_msg(msg: Any, msgtype: str) -> RawImage:
    """A ``sensor_msgs/Image`` or ``CompressedImage`` (``msgtype``) as an undecoded
    :class:`RawImage` (its bytes copied out of the message)."""
    if msgtype == msgs.COMPRESSED_IMAGE:
        return RawImage("compressed", bytes(msg.data), encoding=str(msg.format))
    return RawImage(
        "raw",
        bytes(msg.data),
        encoding=str(msg.encoding),
        width=int(msg.width),
        height=int(msg.height),
        step=int(msg.step),
        bigendian=bool(msg.is_bigendian),
    )


def odometry_record(msg: Any, t_recv: int) -> tuple[Any, ...]:
    """One ``nav_msgs/Odometry`` as ``(t_ns, x, y, z, qx, qy, qz, qw, vx, vy, wz, var_x,
    var_y, var_yaw, covariance set)``: the header stamp (``t_recv`` when zero), raw values."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    cov = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(-1)
    t_ns = _stamp_ns(msg.header.stamp) or t_recv
    var = (cov[0], cov[7], cov[35]) if cov.size == 36 else (np.nan,) * 3
    filled = bool(cov.size == 36 and np.any(cov != 0) and np.isfinite(cov).all())
    return (t_ns, p.x, p.y, p.z, q.x, q.y, q.z, q.w, lin.x, lin.y, ang.z, *var, filled)


def odometry_rows(recs: list[tuple[Any, ...]]) -> pd.DataFrame:
    """``extract.odometry`` rows of :func:`odometry_record` tuples. A variance is NaN when the
    message's pose covariance is not filled (all zero, or a value not finite) or the variance
    itself is not positive or at least :data:`UNKNOWN_VARIANCE` (ROS' "unknown" marker): a
    weight from it would be meaningless. Everything else is kept as recorded (NaN poses,
    stamps going back): what to do with them is the consumer's decision."""
    arr = np.array([r[:-1] for r in recs], dtype=np.float64).reshape(-1, 14)
    filled = np.array([r[-1] for r in recs], dtype=bool)
    var = arr[:, 11:14]
    ok = filled[:, None] & (var > 0) & (var < UNKNOWN_VARIANCE)
    arr[:, 11:14] = np.where(ok, var, np.nan)
    df = pd.DataFrame(arr[:, 1:], columns=ODOMETRY_COLS[1:])
    df.insert(0, "t_ns", np.array([int(r[0]) for r in recs], dtype=np.int64))
    return df


class BagSource(Source):
    """A rosbag2 folder (MCAP or sqlite3) or a ROS 1 ``.bag``, read with rosbags' AnyReader."""

    def __init__(self, path: Path, cfg: DatasetConfig, camera: CameraModel | None) -> None:
        self.path = Path(path)
        self._spare: AnyReader | None = None
        with self._reader(keep=True) as reader:
            by_topic: dict[str, list[Any]] = {}
            for c in reader.connections:
                by_topic.setdefault(c.topic, []).append(c)
            self._types: dict[str, str] = {t: cs[0].msgtype for t, cs in by_topic.items()}
            self._counts: dict[str, int] = {
                t: sum(c.msgcount for c in cs) for t, cs in by_topic.items()
            }
            self.kind, self.topic = self._choose_topic(cfg)
            self.detection_type = msgs.DETECTION_SOURCES.get(self._types[self.topic])
            if self.detection_type is not None:
                kind = self.detection_type
                log.info(
                    "%s: %s is %s: %s%s",
                    self.path,
                    self.topic,
                    kind.writer,
                    kind.convention(),
                    "; in the rectified image" * kind.rectified,
                )
            self.odometry_topic = self._choose_odometry(cfg)
            self._camera_frame: str | None = None
            self.camera_info_topic: str | None = None
            self._camera = camera
            if camera is not None:
                self.camera_origin = str(cfg.camera)
            else:
                self.camera_info_topic = self._choose_camera_info(cfg)
                if self.camera_info_topic is not None:
                    self._camera = self._first_camera_info(reader)
                    self.camera_origin = f"CameraInfo of {self.camera_info_topic}"
        if self._counts[self.topic] == 0:
            raise SourceError(f"{self.path}: topic {self.topic} has no messages (empty bag?)")
        if (
            self.detection_type is not None
            and self.detection_type.rectified
            and self._camera is not None
            and np.any(np.asarray(self._camera.D) != 0)
        ):
            log.warning(
                "%s: %s detects in the rectified image, but the camera (%s) has lens "
                "distortion %s: give the rectified camera (its K, no distortion) with "
                "`camera:` or topics.camera_info",
                self.path,
                self.detection_type.writer,
                self.camera_origin,
                np.round(self._camera.D, 6).tolist(),
            )

    @contextmanager
    def _reader(self, keep: bool = False) -> Iterator[AnyReader]:
        """An open reader; ``keep``: left open for the first iteration (opening parses the
        bag's message definitions, ~0.1–0.2 s)."""
        reader, self._spare = self._spare, None
        if reader is None:
            reader = open_bag(self.path)
        ok = False
        try:
            yield reader
            ok = True
        finally:
            if keep and ok:
                self._spare = reader
            else:
                reader.close()

    def close(self) -> None:
        reader, self._spare = self._spare, None
        if reader is not None:
            reader.close()

    def __del__(self) -> None:
        self.close()

    def _listing(self, types: tuple[str, ...] | None = None) -> str:
        items = [
            f"{t} ({m}, {self._counts[t]} msgs)"
            for t, m in sorted(self._types.items())
            if types is None or m in types
        ]
        return ", ".join(items) or "none"

    def _topic_of(self, name: str, key: str, types: tuple[str, ...]) -> str:
        if name not in self._types:
            raise SourceError(
                f"{self.path}: topic {name} (topics.{key} in pipeline.yaml) is not in the bag; "
                f"topics there: {self._listing()}"
            )
        if self._types[name] not in types:
            raise SourceError(
                f"{self.path}: topic {name} has type {self._types[name]}, "
                f"not {' or '.join(types)} (topics.{key})"
            )
        return name

    def _unique(self, types: tuple[str, ...], key: str) -> str | None:
        cands = sorted(t for t, m in self._types.items() if m in types)
        if len(cands) > 1:
            raise SourceError(
                f"{self.path}: several {' / '.join(types)} topics: {self._listing(types)}; "
                f"choose one with `topics: {{{key}: {cands[0]}}}` for this dataset in pipeline.yaml"
            )
        return cands[0] if cands else None

    def _choose_topic(self, cfg: DatasetConfig) -> tuple[Kind, str]:
        if cfg.topics.detections is not None:
            if cfg.topics.image is not None:
                log.warning("%s: topics.detections is set, so topics.image is ignored", self.path)
            return "detections", self._topic_of(
                cfg.topics.detections, "detections", msgs.DETECTION_TYPES
            )
        if cfg.topics.image is not None:
            return "images", self._topic_of(cfg.topics.image, "image", IMAGE_TYPES)
        image = self._unique(IMAGE_TYPES, "image")
        if image is not None:
            return "images", image
        dets = self._unique(msgs.DETECTION_TYPES, "detections")
        if dets is not None:
            return "detections", dets
        raise SourceError(
            f"{self.path}: no image (sensor_msgs/msg/Image, CompressedImage) or detection "
            f"({', '.join(msgs.DETECTION_TYPES)}) topic; topics there: {self._listing()}"
        )

    def _choose_camera_info(self, cfg: DatasetConfig) -> str | None:
        if cfg.topics.camera_info is not None:
            return self._topic_of(cfg.topics.camera_info, "camera_info", (msgs.CAMERA_INFO,))
        cands = sorted(t for t, m in self._types.items() if m == msgs.CAMERA_INFO)
        if len(cands) > 1:
            # The usual layout: /ns/image_raw next to /ns/camera_info — pick the closest namespace.
            def shared(t: str) -> int:
                return len(os.path.commonprefix([t.split("/")[:-1], self.topic.split("/")]))

            best = max(shared(t) for t in cands)
            top = [t for t in cands if shared(t) == best]
            if len(top) == 1 and best > 1:
                return top[0]
            raise SourceError(
                f"{self.path}: several CameraInfo topics: {self._listing((msgs.CAMERA_INFO,))}; "
                f"choose one with `topics: {{camera_info: {cands[0]}}}` in pipeline.yaml"
            )
        return cands[0] if cands else None

    def _first_camera_info(self, reader: AnyReader) -> CameraModel | None:
        conns = [c for c in reader.connections if c.topic == self.camera_info_topic]
        for conn, _, raw in reader.messages(connections=conns):
            try:
                info: Any = reader.deserialize(raw, conn.msgtype)
                self._camera_frame = str(info.header.frame_id) or None
                return CameraModel.from_camera_info(info)
            except Exception as err:  # a bad calibration or an undecodable message
                raise SourceError(f"{self.path}: topic {conn.topic}: {err}") from err
        return None

    def _choose_odometry(self, cfg: DatasetConfig) -> str | None:
        """The odometry topic (Topics.odometry): named, off, or the one the bag has
        (``/odom`` among several; several others: one error saying how to choose)."""
        if cfg.topics.odometry_off():
            return None
        if cfg.topics.odometry is not None:
            return self._topic_of(cfg.topics.odometry, "odometry", (ODOMETRY,))
        cands = sorted(t for t, m in self._types.items() if m == ODOMETRY)
        if len(cands) > 1 and ODOM_TOPIC in cands:
            return ODOM_TOPIC
        if len(cands) > 1:
            raise SourceError(
                f"{self.path}: several odometry topics: {self._listing((ODOMETRY,))}; choose "
                f"one with `topics: {{odometry: {cands[0]}}}` for this dataset in pipeline.yaml "
                "(or `odometry: none` to read none)"
            )
        return cands[0] if cands else None

    def odometry(self) -> Odometry | None:
        """The odometry topic's messages as ``extract.odometry`` rows (:func:`odometry_rows`);
        None when the bag has none (or the dataset turned it off). A message that does not
        deserialize is left out and counted (``Odometry.unreadable``), never an error."""
        if self.odometry_topic is None:
            return None
        frame = child = None
        recs: list[tuple[Any, ...]] = []
        unreadable = 0
        with self._reader(keep=True) as reader:
            conns = [c for c in reader.connections if c.topic == self.odometry_topic]
            for conn, t_recv, raw in reader.messages(connections=conns):
                try:
                    msg: Any = reader.deserialize(raw, conn.msgtype)
                    rec = odometry_record(msg, int(t_recv))
                except Exception:  # noqa: BLE001 - a damaged message: counted, the rest kept
                    unreadable += 1
                    continue
                if frame is None:
                    frame, child = str(msg.header.frame_id), str(msg.child_frame_id)
                recs.append(rec)
        return Odometry(
            self.odometry_topic, frame or "", child or "", odometry_rows(recs), unreadable
        )

    def static_frames(self) -> StaticFrames:
        """The camera's frame (CameraInfo's, else the first frame message's ``frame_id``) and
        every ``tf2_msgs/TFMessage`` transform on ``/tf_static`` (the last one per child)."""
        tfs: dict[str, StaticTransform] = {}
        with self._reader(keep=True) as reader:
            if self._camera_frame is None:
                conns = [c for c in reader.connections if c.topic == self.topic]
                for conn, _, raw in reader.messages(connections=conns):
                    msg: Any = reader.deserialize(raw, conn.msgtype)
                    self._camera_frame = str(msg.header.frame_id) or None
                    break
            conns = [
                c
                for c in reader.connections
                if c.topic == TF_STATIC_TOPIC and c.msgtype == TF_MESSAGE
            ]
            bad = 0
            for conn, _, raw in reader.messages(connections=conns) if conns else ():
                try:
                    tf_msg: Any = reader.deserialize(raw, conn.msgtype)
                except Exception:  # noqa: BLE001 - a damaged message: the others still count
                    bad += 1
                    continue
                for tf in tf_msg.transforms:
                    tr, q = tf.transform.translation, tf.transform.rotation
                    vals = (tr.x, tr.y, tr.z, q.x, q.y, q.z, q.w)
                    child = str(tf.child_frame_id).lstrip("/")
                    tfs[child] = StaticTransform(
                        str(tf.header.frame_id).lstrip("/"),
                        child,
                        cast("Any", tuple(float(v) for v in vals)),
                    )
            if bad:
                log.warning(
                    "%s: %d %s message(s) do not decode: left out", self.path, bad, TF_STATIC_TOPIC
                )
        camera = self._camera_frame.lstrip("/") if self._camera_frame else None
        return StaticFrames(camera, tuple(tfs.values()))

    def camera(self) -> CameraModel | None:
        return self._camera

    def __len__(self) -> int:
        return self._counts[self.topic]

    def describe(self) -> str:
        return f"bag {self.path}, topic {self.topic} ({self._types[self.topic]}, {len(self)} msgs)"

    def iter_raw(self) -> Iterator[Frame]:
        with self._reader() as reader:
            topics = {self.topic, self.camera_info_topic}
            conns = [c for c in reader.connections if c.topic in topics]
            idx, warned = 0, False
            try:
                for conn, t_recv, raw in reader.messages(connections=conns):
                    msg: Any = reader.deserialize(raw, conn.msgtype)
                    if conn.topic == self.camera_info_topic:
                        if not warned and self._camera is not None:
                            try:
                                same = CameraModel.from_camera_info(msg).same_as(self._camera)
                                why = "changes during the recording"
                            except SourceError as err:
                                same, why = False, f"has an invalid message later ({err})"
                            if not same:
                                log.warning(
                                    "%s: %s %s; using the first message", self.path, conn.topic, why
                                )
                                warned = True
                        continue
                    t_ns = self._stamp(msg.header.stamp, idx) or int(t_recv)
                    if conn.msgtype in msgs.DETECTION_TYPES:
                        dets = detections_from_msg(msg, conn.msgtype)
                        self._check_detections(dets, idx)
                        yield idx, t_ns, dets
                    else:
                        yield idx, t_ns, raw_image_from_msg(msg, conn.msgtype)
                    idx += 1
            except SourceError:
                raise
            except Exception as err:
                raise SourceError(
                    f"{self.path}: cannot read message {idx} of {self.topic}: {err}"
                ) from err

    def _bad(self, idx: int, problem: str) -> SourceError:
        return SourceError(f"{self.path}: topic {self.topic}, message {idx}: {problem}")

    def _stamp(self, stamp: Any, idx: int) -> int:
        """``header.stamp`` in ns; a nanosecond field out of [0, 1e9) is an error."""
        problem = msgs.stamp_problem(
            int(stamp.nanosec if hasattr(stamp, "nanosec") else stamp.nsecs)
        )
        if problem is not None:
            raise self._bad(idx, problem)
        return _stamp_ns(stamp)

    def _check_detections(self, dets: list[TagDetection], idx: int) -> None:
        problem = detection_problem(dets)
        if problem is not None:
            raise self._bad(idx, problem)


# --- image folders -----------------------------------------------------------------------------


def _natural_key(name: str) -> list[Any]:
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]


def _image_files(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTS]
    return sorted(files, key=lambda p: _natural_key(p.name))


class ImageFolderSource(Source):
    """jpg/png files in natural file-name order; ``camera.yaml``; optional ``stamps.csv``."""

    kind: Kind = "images"

    def __init__(
        self, path: Path, camera: CameraModel | None, camera_file: Path | None = None
    ) -> None:
        self.path = Path(path)
        self.files = _image_files(self.path)
        if camera is None and (self.path / "camera.yaml").is_file():
            camera_file = self.path / "camera.yaml"
            camera = read_camera_file(camera_file)
        self._camera = camera
        if camera_file is not None:
            self.camera_origin = str(camera_file)
        self.stamps_ns = self._stamps()
        self.timed = (self.path / "stamps.csv").is_file()

    def _stamps(self) -> NDArray[np.int64]:
        f = self.path / "stamps.csv"
        if not f.is_file():
            return np.arange(len(self.files), dtype=np.int64) * FOLDER_PERIOD_NS
        # every cell range-checked: one line naming the file, the data row and the column
        df = read_csv_table(f, "stamps", STAMPS_HEADER)
        sec = integer_column(f, df, "stamp_sec", -(2**31), 2**32 - 1)  # builtin_interfaces/Time
        nsec = integer_column(f, df, "stamp_nanosec", 0, 999_999_999)
        names = [str(v).strip() for v in df["file"].tolist()]
        rows = dict(zip(names, (sec * 1_000_000_000 + nsec).tolist(), strict=True))
        missing = [p.name for p in self.files if p.name not in rows]
        if missing:
            raise SourceError(f"{f}: no stamp for {len(missing)} image(s), e.g. {missing[0]}")
        return np.array([rows[p.name] for p in self.files], dtype=np.int64)

    def camera(self) -> CameraModel | None:
        return self._camera

    def __len__(self) -> int:
        return len(self.files)

    def describe(self) -> str:
        return f"image folder {self.path} ({len(self)} images)"

    def frame_name(self, frame_idx: int, t_ns: int) -> str:
        return self.files[frame_idx].name

    def iter_raw(self) -> Iterator[Frame]:
        for idx, (p, t_ns) in enumerate(zip(self.files, self.stamps_ns, strict=True)):
            yield idx, int(t_ns), RawImage("file", str(p))


# --- observations ------------------------------------------------------------------------------


class ObservationsSource(Source):
    """``observations.csv``: ``stamp_sec,stamp_nanosec,tag,x,y,z,qx,qy,qz,qw`` (cam_T_tag)."""

    kind: Kind = "observations"

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        f = self.path / "observations.csv"
        out, df = read_stamped_poses(f, OBS_CSV_HEADER, "observations", ordered=False)
        out.insert(1, "tag_id", tag_ids(f, df["tag"]).astype(np.int32))
        out = out.sort_values(["t_ns", "tag_id"], kind="stable").reset_index(drop=True)
        frame_idx = np.unique(out["t_ns"].to_numpy(), return_inverse=True)[1]
        out.insert(1, "frame_idx", frame_idx.astype(np.int32))
        self._obs = out

    def camera(self) -> CameraModel | None:
        return None

    def __len__(self) -> int:
        return int(self._obs["frame_idx"].nunique())

    def observations(self) -> pd.DataFrame:
        return self._obs.copy()

    def iter_raw(self) -> Iterator[Frame]:
        for key, grp in self._obs.groupby(["frame_idx", "t_ns"], sort=True):
            idx, t_ns = cast("tuple[SupportsInt, SupportsInt]", key)  # two integer columns
            yield int(idx), int(t_ns), grp.reset_index(drop=True)
