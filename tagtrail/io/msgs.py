"""ROS 2 message types tagtrail reads and writes, without a ROS installation.

One typestore for the whole package: ROS 2 Humble's standard types plus ``apriltag_msgs``
registered from their ``.msg`` text (Humble sqlite3 bags store no message definitions).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

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

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DETECTIONS = "apriltag_msgs/msg/AprilTagDetectionArray"
# TagSLAM's (ROS 1 apriltag_ros of berndpfrommer): per-tag id, family (the detector's name: mit,
# umich, or empty), hamming, corners; no decision margin. Its definition travels in the bag.
TAGSLAM_DETECTIONS = "apriltag_msgs/msg/ApriltagArrayStamped"
DETECTION_TYPES = (DETECTIONS, TAGSLAM_DETECTIONS)
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The shared Humble typestore with apriltag_msgs registered."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in APRILTAG_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store
