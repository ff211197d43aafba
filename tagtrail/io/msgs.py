"""ROS 2 message types tagtrail reads and writes, without a ROS installation.

One typestore for the whole package: ROS 2 Humble's standard types plus ``apriltag_msgs`` and
``isaac_ros_apriltag_interfaces`` registered from their ``.msg`` text (Humble sqlite3 bags store
no message definitions). :data:`DETECTION_SOURCES` declares, per detection message type, its
corner pixel convention and which quality fields it carries (what ``extract``'s filters can use).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from tagtrail.vision.detector import C_LIBRARY_PIXEL_OFFSET

# apriltag_msgs 2.0.1 (the ROS 2 apriltag_ros output), verbatim field lists.
APRILTAG_MSGS = {
    "apriltag_msgs/msg/Point": "float64 x\nfloat64 y\n",
    "apriltag_msgs/msg/AprilTagDetection": (
        "string family\nint32 id\nint32 hamming\nfloat32 goodness\nfloat32 decision_margin\n"
        "apriltag_msgs/Point centre\napriltag_msgs/Point[4] corners\nfloat64[9] homography\n"
    ),
    "apriltag_msgs/msg/AprilTagDetectionArray": (
        "std_msgs/Header header\napriltag_msgs/AprilTagDetection[] detections\n"
    ),
}
# isaac_ros_apriltag_interfaces (NVIDIA Isaac ROS, isaac_ros_common): field lists of its .msg
# files; no hamming, no decision margin; corners as geometry_msgs/Point (z unused).
ISAAC_MSGS = {
    "isaac_ros_apriltag_interfaces/msg/AprilTagDetection": (
        "string family\nint32 id\ngeometry_msgs/Point center\ngeometry_msgs/Point[4] corners\n"
        "geometry_msgs/PoseWithCovarianceStamped pose\n"
    ),
    "isaac_ros_apriltag_interfaces/msg/AprilTagDetectionArray": (
        "std_msgs/Header header\nisaac_ros_apriltag_interfaces/AprilTagDetection[] detections\n"
    ),
}

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DETECTIONS = "apriltag_msgs/msg/AprilTagDetectionArray"
# TagSLAM's (ROS 1 apriltag_ros of berndpfrommer): per-tag id, family (the detector's name: mit,
# umich, or empty), hamming, corners; no decision margin. Its definition travels in the bag.
TAGSLAM_DETECTIONS = "apriltag_msgs/msg/ApriltagArrayStamped"
ISAAC_DETECTIONS = "isaac_ros_apriltag_interfaces/msg/AprilTagDetectionArray"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

C_LIBRARY = C_LIBRARY_PIXEL_OFFSET  # the AprilTag C library's corners: +0.5 px from OpenCV's


@dataclass(frozen=True)
class DetectionType:
    """What one detection message type carries. ``writer``: the node that publishes it (for
    messages); ``pixel_offset``: px subtracted from its corners to reach OpenCV's convention,
    per value of the message's ``family`` field (``default_offset`` for any other); ``hamming``
    / ``decision_margin``: the message has the field (else the filter on it is not applied);
    ``family``: the message names the tag family (else tagtrail's tag36h11 is assumed);
    ``rectified``: corners are in the rectified (undistorted) image, not the raw one."""

    msgtype: str
    writer: str
    default_offset: float
    hamming: bool
    decision_margin: bool
    family: bool
    rectified: bool = False
    offsets: tuple[tuple[str, float], ...] = ()

    def pixel_offset(self, family: str) -> float:
        """The offset for a message whose ``family`` field reads ``family``."""
        return dict(self.offsets).get(family, self.default_offset)

    def convention(self) -> str:
        """The corner convention in words, for messages."""
        if self.offsets:
            per = ", ".join(f"{f or 'empty'}: {o:+.1f} px" for f, o in self.offsets)
            return f"corners shifted by -(offset) to OpenCV's convention ({per})"
        if self.default_offset:
            return f"corners {self.default_offset:+.1f} px from OpenCV's (the C library's)"
        return "corners in OpenCV's convention"

    def missing(self) -> list[str]:
        """The quality fields the message lacks (``hamming``, ``decision_margin``)."""
        return [f for f in ("hamming", "decision_margin") if not getattr(self, f)]


DETECTION_SOURCES: dict[str, DetectionType] = {
    DETECTIONS: DetectionType(
        DETECTIONS,
        "apriltag_ros (ROS 2, the AprilTag C library)",
        C_LIBRARY,
        hamming=True,
        decision_margin=True,
        family=True,
    ),
    # family holds the detector's name: MIT (corners already OpenCV's: TagSLAM's test 16 maps at
    # 0.10 px with them as recorded) or umich (the C library); empty = MIT (the default).
    TAGSLAM_DETECTIONS: DetectionType(
        TAGSLAM_DETECTIONS,
        "TagSLAM's apriltag_ros (ROS 1)",
        0.0,
        hamming=True,
        decision_margin=False,
        family=False,
        offsets=(("mit", 0.0), ("umich", C_LIBRARY)),
    ),
    # cuAprilTags / VPI on the rectified image, "a drop-in replacement for the reference
    # detector": taken in the C library's convention (not measured: no capture to hand).
    ISAAC_DETECTIONS: DetectionType(
        ISAAC_DETECTIONS,
        "isaac_ros_apriltag (NVIDIA Isaac ROS)",
        C_LIBRARY,
        hamming=False,
        decision_margin=False,
        family=True,
        rectified=True,
    ),
}
DETECTION_TYPES = tuple(DETECTION_SOURCES)


def stamp_problem(nanosec: int) -> str | None:
    """What is wrong with a ``header.stamp`` whose nanoseconds field is ``nanosec`` (None: in
    range). Bag sources refuse such a message in one line; the live nodes drop and count it."""
    if 0 <= nanosec < 1_000_000_000:
        return None
    return f"header.stamp nanoseconds {nanosec} not in [0, 999999999]"


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The shared Humble typestore with apriltag_msgs and isaac_ros_apriltag_interfaces."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in {**APRILTAG_MSGS, **ISAAC_MSGS}.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store
