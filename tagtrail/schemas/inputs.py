"""What the runner hands a stage besides artifacts: an opened :class:`Source`, a
:class:`GroundTruth`. Stages see these types only; ``tagtrail.io`` implements and reads them."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import pandas as pd

from tagtrail.geometry.camera import CameraModel

Kind = Literal["images", "detections", "observations"]
Frame = tuple[int, int, Any]  # (frame_idx, t_ns, payload): a RawImage or TagDetection list


@dataclass(frozen=True)
class Odometry:
    """A recording's wheel odometry (``nav_msgs/msg/Odometry``), as read: ``topic``, its
    ``frame_id`` (e.g. ``odom``) and ``child_frame_id`` (e.g. ``base_link``, the first message's),
    and ``rows`` with the columns of ``extract.odometry`` (schemas.artifacts; one row per message
    in bag order, nothing dropped or repaired: the stage counts what is wrong); ``unreadable``:
    messages that did not deserialize (left out)."""

    topic: str
    frame_id: str
    child_frame_id: str
    rows: pd.DataFrame
    unreadable: int = 0


@dataclass(frozen=True)
class StaticTransform:
    """One ``/tf_static`` transform ``parent_T_child``: position (m) and quaternion, x y z qx qy
    qz qw (``geometry_msgs/Transform`` of ``header.frame_id`` → ``child_frame_id``)."""

    parent: str
    child: str
    xyz_q_xyzw: tuple[float, float, float, float, float, float, float]


@dataclass(frozen=True)
class StaticFrames:
    """What a recording says about its frames: ``camera_frame`` (the CameraInfo's
    ``header.frame_id``, else the detections' or images'; None when unknown) and every
    ``/tf_static`` transform (latest per child frame)."""

    camera_frame: str | None = None
    transforms: tuple[StaticTransform, ...] = ()


class Source(Protocol):
    """A dataset's recording, opened: ``kind`` says what its frames carry."""

    kind: Kind
    path: Path
    camera_origin: str  # where camera() comes from, for messages
    timed: bool  # stamps are capture times (False: an image folder's file order at 10 Hz)

    def camera(self) -> CameraModel | None: ...
    def __len__(self) -> int: ...
    def iter_raw(self) -> Iterator[Frame]: ...
    def chunks(self, size: int) -> Iterator[list[Frame]]: ...
    def observations(self) -> pd.DataFrame: ...
    def describe(self) -> str: ...
    def frame_name(self, frame_idx: int, t_ns: int) -> str: ...
    def odometry(self) -> Odometry | None: ...  # None: no odometry (or the dataset turned it off)
    def static_frames(self) -> StaticFrames: ...


@dataclass(frozen=True)
class GroundTruth:
    """A dataset's ground truth (SPEC layouts): ``trajectory`` (``t_ns`` + pose columns,
    world_T_cam), ``tag_map`` (``tag_id`` + pose columns, world_T_tag) with the GT world's
    ``anchor_id``, read from the folder ``path``."""

    path: Path
    trajectory: pd.DataFrame
    tag_map: pd.DataFrame
    anchor_id: int | None
