"""RViz markers of the relocalization node (``visualization_msgs/msg/MarkerArray``).

Two arrays go out on ``<prefix>/markers``: the reference path (one ``LINE_STRIP``, namespace
``reference_path``, published with the path at start-up and periodically) and, per pose, the
nearest reference point (``SPHERE``), the error segment from the pose to it (``LINE_LIST``) and a
text ``D … m  phi … deg`` above the pose (``TEXT_VIEW_FACING``). Markers have ids fixed per
namespace and no lifetime, so each message replaces the previous one in RViz. The per-pose
array is a :class:`~tagtrail.stream.codec.Template`: built once, patched per message.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from tagtrail.stream import codec

NS_PATH, NS_NEAREST, NS_ERROR, NS_TEXT = "reference_path", "nearest", "error", "text"
TEXT_FORMAT = "D {:7.3f} m  phi {:+7.2f} deg"
TEXT_LEN = len(TEXT_FORMAT.format(0.0, 0.0))
TEXT_LIFT_M = 0.25  # text drawn this far above the pose
_GREEN, _RED, _ORANGE, _WHITE = (
    (0.1, 0.8, 0.2, 1.0),
    (0.9, 0.1, 0.1, 1.0),
    (1.0, 0.6, 0.0, 1.0),
    (1.0, 1.0, 1.0, 1.0),
)


def marker(
    ns: str,
    mid: int,
    mtype: int,
    frame_id: str,
    sec: int,
    nanosec: int,
    *,
    position: Sequence[float] = (0.0, 0.0, 0.0),
    scale: Sequence[float] = (1.0, 1.0, 1.0),
    color: Sequence[float] = _WHITE,
    points: Sequence[Sequence[float]] = (),
    text: str = "",
) -> Any:
    """One ``visualization_msgs/msg/Marker`` (action ADD, identity orientation, no lifetime)."""
    T = codec.types()
    Point = T["geometry_msgs/msg/Point"]
    empty = np.zeros(0, dtype=np.uint8)
    return T["visualization_msgs/msg/Marker"](
        header=codec.header(sec, nanosec, frame_id),
        ns=ns,
        id=mid,
        type=mtype,
        action=0,
        pose=codec.pose(position, (0.0, 0.0, 0.0, 1.0)),
        scale=T["geometry_msgs/msg/Vector3"](*map(float, scale)),
        color=T["std_msgs/msg/ColorRGBA"](*map(float, color)),
        lifetime=T["builtin_interfaces/msg/Duration"](0, 0),
        frame_locked=False,
        points=[Point(*map(float, p)) for p in points],
        colors=[],
        texture_resource="",
        texture=T["sensor_msgs/msg/CompressedImage"](codec.header(0, 0, ""), "", empty),
        uv_coordinates=[],
        text=text,
        mesh_resource="",
        mesh_file=T["visualization_msgs/msg/MeshFile"]("", empty),
        mesh_use_embedded_materials=False,
    )


def marker_array(markers: list[Any]) -> bytes:
    return codec.serialize(codec.types()[codec.MARKER_ARRAY](markers), codec.MARKER_ARRAY)


def path_markers(
    positions: np.ndarray, frame_id: str, sec: int = 0, nanosec: int = 0, width_m: float = 0.02
) -> bytes:
    """The reference path as one LINE_STRIP through ``positions (N, 3)`` (m)."""
    LINE_STRIP = codec.types()["visualization_msgs/msg/Marker"].LINE_STRIP
    m = marker(
        NS_PATH,
        0,
        LINE_STRIP,
        frame_id,
        sec,
        nanosec,
        scale=(width_m, 0.0, 0.0),
        color=_GREEN,
        points=np.asarray(positions, dtype=np.float64).tolist(),
    )
    return marker_array([m])


class PoseMarkers:
    """Per-pose markers: nearest point, error segment, text. ``up (3,)``: unit "up" in world."""

    def __init__(self, frame_id: str, up: Iterable[float]) -> None:
        self.frame_id = frame_id
        self.up = [float(v) for v in up]
        s = codec.sentinel
        sec, nsec = codec.stamp_sentinel()
        placeholder = codec.text_placeholder(TEXT_LEN)
        payload = self._build(sec, nsec, [s(i) for i in range(12)], placeholder)
        self.template = codec.Template(payload, 12, TEXT_LEN)

    def _build(self, sec: int, nanosec: int, d: Sequence[float], text: str) -> bytes:
        M = codec.types()["visualization_msgs/msg/Marker"]
        f = self.frame_id
        return marker_array(
            [
                marker(
                    NS_NEAREST,
                    0,
                    M.SPHERE,
                    f,
                    sec,
                    nanosec,
                    position=d[0:3],
                    scale=(0.08, 0.08, 0.08),
                    color=_RED,
                ),
                marker(
                    NS_ERROR,
                    0,
                    M.LINE_LIST,
                    f,
                    sec,
                    nanosec,
                    scale=(0.015, 0.0, 0.0),
                    color=_ORANGE,
                    points=[d[3:6], d[6:9]],
                ),
                marker(
                    NS_TEXT,
                    0,
                    M.TEXT_VIEW_FACING,
                    f,
                    sec,
                    nanosec,
                    position=d[9:12],
                    scale=(0.0, 0.0, 0.12),
                    color=_WHITE,
                    text=text,
                ),
            ]
        )

    def __call__(
        self,
        sec: int,
        nanosec: int,
        current: Sequence[float],
        nearest: Sequence[float],
        distance_m: float,
        phi_deg: float,
    ) -> bytes:
        """MarkerArray bytes for one pose: ``current``/``nearest`` world positions (m)."""
        ux, uy, uz = self.up
        cx, cy, cz = current
        d = (
            *nearest,
            cx,
            cy,
            cz,
            *nearest,
            cx + TEXT_LIFT_M * ux,
            cy + TEXT_LIFT_M * uy,
            cz + TEXT_LIFT_M * uz,
        )
        text = TEXT_FORMAT.format(distance_m, phi_deg)
        raw = text.encode()
        if len(raw) == TEXT_LEN:
            return self.template.fill(sec, nanosec, d, raw)
        return self._build(sec, nanosec, d, text)  # rare: |D| ≥ 1000 m
