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


@dataclass(frozen=True)
class GroundTruth:
    """A dataset's ground truth (SPEC layouts): ``trajectory`` (``t_ns`` + pose columns,
    world_T_cam), ``tag_map`` (``tag_id`` + pose columns, world_T_tag) with the GT world's
    ``anchor_id``, read from the folder ``path``."""

    path: Path
    trajectory: pd.DataFrame
    tag_map: pd.DataFrame
    anchor_id: int | None
