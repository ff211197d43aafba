"""Profiles: named sets of ``pipeline.yaml`` defaults for a robot or the simulator.

A profile is nothing but defaults: the topics a dataset reads (``topics:``), the stage
parameters (``stages:``), the topics ``tagtrail stream record`` records and the keys the live
nodes subscribe to. ``tagtrail init --profile NAME`` writes them into the pipeline file, where
they are ordinary settings to read and edit; the live nodes and ``stream record`` take the same
``--profile`` (their flags, and a pipeline file when there is one, win over it).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict

from tagtrail.errors import SpecError

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DETECTIONS = "apriltag_msgs/msg/AprilTagDetectionArray"
ODOMETRY = "nav_msgs/msg/Odometry"


class LiveKeys(BaseModel):
    """The zenoh keys of ``stream localize`` (bridge keys: topic names without the ``/``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    camera_info_key: str
    detections_key: str = "detections"
    image_key: str | None = None  # set: detect tags in images on this key
    image_type: str = "compressed"
    pose_key: str = "tag_only_pose"
    odom_key: str | None = None  # the base's odometry for `stream localize --smooth`
    camera_forward_m: float | None = None  # the camera ahead of the turning centre (m)


class Profile(BaseModel):
    """One profile (module docstring); ``record`` = ``(topic, ROS type)`` pairs, of which the
    ``optional`` topics (the wheel odometry) are recorded and replayed when present."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str
    description: str
    topics: dict[str, str]
    record: tuple[tuple[str, str], ...]
    stages: dict[str, dict[str, Any]]
    optional: tuple[str, ...] = ()
    live: LiveKeys


# The LIMO: an anchor tag upright on a wall, the floor the anchor's x-z plane (NOTES "The LIMO";
# the original tool's plane). No tag size: nothing documents the LIMO's tags (print your own and
# give `init --tag-size`). The `sim` profile carries the simulator's size (SimOptions), which
# `tagtrail simulate` documents and renders.
_LIMO_STAGES: dict[str, dict[str, Any]] = {"report": {"plane": "xz"}}
LIMO_CAMERA_FORWARD_M = 0.084  # the camera ahead of the base's centre (NOTES "The LIMO")

PROFILES: dict[str, Profile] = {
    p.name: p
    for p in (
        Profile(
            name="limo",
            description="the real LIMO, the original workflow: apriltag_ros on the robot publishes "
            "/detections with /camera_info (and its wheel odometry /odom)",
            topics={"detections": "/detections", "camera_info": "/camera_info"},
            record=(
                ("/detections", DETECTIONS),
                ("/camera_info", CAMERA_INFO),
                ("/odom", ODOMETRY),
            ),
            optional=("/odom",),
            stages=_LIMO_STAGES,
            live=LiveKeys(
                detections_key="detections",
                camera_info_key="camera_info",
                odom_key="odom",
                camera_forward_m=LIMO_CAMERA_FORWARD_M,
            ),
        ),
        Profile(
            name="limo-images",
            description="the real LIMO's camera driver: raw 640x480 images on "
            "/camera/color/image_raw with /camera/color/camera_info (tags detected by tagtrail)",
            topics={"image": "/camera/color/image_raw", "camera_info": "/camera/color/camera_info"},
            record=(
                ("/camera/color/image_raw", IMAGE),
                ("/camera/color/camera_info", CAMERA_INFO),
                ("/odom", ODOMETRY),
            ),
            optional=("/odom",),
            stages=_LIMO_STAGES,
            live=LiveKeys(
                image_key="camera/color/image_raw",
                image_type="raw",
                camera_info_key="camera/color/camera_info",
                odom_key="odom",
                camera_forward_m=LIMO_CAMERA_FORWARD_M,
            ),
        ),
        Profile(
            name="sim",
            description="recordings of `tagtrail simulate --compressed`: jpeg images on "
            "/camera/color/image_raw/compressed with /camera/color/camera_info",
            topics={
                "image": "/camera/color/image_raw/compressed",
                "camera_info": "/camera/color/camera_info",
            },
            record=(
                ("/camera/color/image_raw/compressed", COMPRESSED_IMAGE),
                ("/camera/color/camera_info", CAMERA_INFO),
            ),
            stages={"pnp": {"tag_size": 0.16}, "report": {"plane": "auto"}},
            live=LiveKeys(
                image_key="camera/color/image_raw/compressed",
                image_type="compressed",
                camera_info_key="camera/color/camera_info",
            ),
        ),
    )
}


def get_profile(name: str | None) -> Profile | None:
    """The profile called ``name`` (None for None); an unknown name is a :class:`SpecError`."""
    if name is None:
        return None
    if name not in PROFILES:
        raise SpecError(
            f"unknown profile {name!r}; choose one of {', '.join(PROFILES)} "
            "(tagtrail init --list-profiles)"
        )
    return PROFILES[name]


def describe(profile: Profile) -> str:
    """A few lines for ``--list-profiles``: name, what it is for, its topics and parameters."""
    topics = ", ".join(f"{t} ({m.rsplit('/', 1)[-1]})" for t, m in profile.record)
    stages = ", ".join(f"{s}.{k}={v}" for s, ps in profile.stages.items() for k, v in ps.items())
    if "tag_size" not in profile.stages.get("pnp", {}):
        stages += " (no tag size: give init --tag-size)"
    return f"{profile.name}: {profile.description}\n  records: {topics}\n  parameters: {stages}"
