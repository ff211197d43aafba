"""CDR payloads as zenoh-bridge-ros2dds forwards them: the 4-byte encapsulation header + CDR.

Generic encode/decode goes through the shared rosbags typestore (:mod:`tagtrail.io.msgs`, ROS 2
Humble + apriltag_msgs). The per-pose hot path avoids building message objects:

- :func:`decode_pose` reads ``geometry_msgs/msg/PoseStamped``, ``PoseWithCovarianceStamped`` or
  ``nav_msgs/msg/Odometry`` with ``struct`` (header + ``pose``), checking lengths, so a payload
  of another type is rejected rather than misread;
- :class:`PoseStampedEncoder` and :func:`encode_float64` pack the bytes directly;
- :class:`Template` serializes a message once with sentinel values, records where they land,
  and then only patches those bytes (used for the per-pose ``MarkerArray``).

Each of these is checked against rosbags byte for byte in ``tests/stream/test_codec.py``.
"""

from __future__ import annotations

import operator
import struct
from collections.abc import Sequence
from typing import Any, NamedTuple, cast

import numpy as np

from tagtrail.io import msgs

CDR_LE = b"\x00\x01\x00\x00"
POSE_TYPES = {
    "pose_stamped": "geometry_msgs/msg/PoseStamped",
    "pose_with_covariance": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "odometry": "nav_msgs/msg/Odometry",
}
# bytes after the 7 pose doubles: PoseWithCovariance's covariance; Odometry's + the twist part
_TAIL = {"pose_stamped": 0, "pose_with_covariance": 288, "odometry": 288 + 48 + 288}
POSE_STAMPED = msgs.POSE_STAMPED
PATH = "nav_msgs/msg/Path"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
_F64 = struct.Struct("<4sd")
_U32 = {"<": struct.Struct("<I"), ">": struct.Struct(">I")}
_STAMP = {"<": struct.Struct("<iI"), ">": struct.Struct(">iI")}
_POSE = {"<": struct.Struct("<7d"), ">": struct.Struct(">7d")}


class CodecError(ValueError):
    """A payload that is not a valid CDR message of the expected type."""


class PoseIn(NamedTuple):
    """A decoded pose: header stamp, frame, position (m) and quaternion ``q_xyzw``."""

    sec: int
    nanosec: int
    frame_id: str
    x: float
    y: float
    z: float
    qx: float
    qy: float
    qz: float
    qw: float


def types() -> Any:
    """The message classes of the shared typestore (``types()["std_msgs/msg/Header"]``…)."""
    return msgs.typestore().types


def serialize(msg: Any, msgtype: str | None = None) -> bytes:
    """CDR bytes (little endian, with the encapsulation header) of a rosbags message."""
    return bytes(msgs.typestore().serialize_cdr(msg, msgtype or msg.__msgtype__))


def deserialize(data: bytes, msgtype: str) -> Any:
    """A rosbags message from CDR bytes; any failure is a :class:`CodecError`."""
    if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
        raise CodecError(f"not a CDR payload (encapsulation {bytes(data[:4]).hex() or 'none'})")
    try:
        return msgs.typestore().deserialize_cdr(data, msgtype)
    except Exception as err:  # rosbags raises struct.error, IndexError, UnicodeDecodeError, …
        raise CodecError(f"not a {msgtype}: {type(err).__name__}: {err}") from err


def header(sec: int, nanosec: int, frame_id: str) -> Any:
    T = types()
    return T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](sec, nanosec), frame_id)


def pose(xyz: Sequence[float], q_xyzw: Sequence[float]) -> Any:
    T = types()
    return T["geometry_msgs/msg/Pose"](
        T["geometry_msgs/msg/Point"](*map(float, xyz)),
        T["geometry_msgs/msg/Quaternion"](*map(float, q_xyzw)),
    )


def pose_stamped(
    sec: int, nanosec: int, frame_id: str, xyz: Sequence[float], q_xyzw: Sequence[float]
) -> Any:
    return types()[POSE_STAMPED](header(sec, nanosec, frame_id), pose(xyz, q_xyzw))


def _string_end(data: bytes, pos: int, e: str) -> tuple[str, int]:
    """Read a CDR string at ``pos`` (4-aligned); returns it and the offset after it."""
    if pos + 4 > len(data):
        raise CodecError("truncated string length")
    n = _U32[e].unpack_from(data, pos)[0]
    end = pos + 4 + n
    if n == 0 or end > len(data) or data[end - 1] != 0:
        raise CodecError("invalid CDR string")
    try:
        return data[pos + 4 : end - 1].decode("utf-8"), end
    except UnicodeDecodeError as err:
        raise CodecError("string is not UTF-8") from err


def decode_pose(data: bytes, kind: str = "pose_stamped") -> PoseIn:
    """The header and pose of a PoseStamped / PoseWithCovarianceStamped / Odometry payload.

    ``kind``: a key of :data:`POSE_TYPES`. Raises :class:`CodecError` when the payload is not
    a CDR message of that type (wrong encapsulation, length, string); values are not checked.
    """
    if len(data) < 20 or data[0] != 0 or data[1] not in (0, 1):
        raise CodecError(f"not a CDR payload ({len(data)} bytes)")
    e = "<" if data[1] == 1 else ">"
    sec, nsec = _STAMP[e].unpack_from(data, 4)
    frame_id, pos = _string_end(data, 12, e)
    if kind == "odometry":
        pos = 4 + ((pos - 4 + 3) & ~3)
        _, pos = _string_end(data, pos, e)
    elif kind not in _TAIL:
        raise CodecError(f"unknown pose type {kind!r}")
    pos = 4 + ((pos - 4 + 7) & ~7)  # CDR alignment counts from after the encapsulation header
    end = pos + 56 + _TAIL[kind]
    if not end <= len(data) <= end + 7:  # at most the final padding may follow
        raise CodecError(f"{len(data)} bytes is not a {POSE_TYPES[kind]} with frame {frame_id!r}")
    return PoseIn(sec, nsec, frame_id, *_POSE[e].unpack_from(data, pos))


def encode_float64(value: float) -> bytes:
    """``std_msgs/msg/Float64``."""
    return _F64.pack(CDR_LE, value)


def _frame_bytes(frame_id: str) -> tuple[bytes, int]:
    raw = frame_id.encode("utf-8") + b"\x00"
    pad = -(8 + 4 + len(raw)) % 8  # after sec, nanosec, length, string: align the pose to 8
    return raw, pad


class PoseStampedEncoder:
    """``geometry_msgs/msg/PoseStamped`` with a fixed ``frame_id``, packed directly (~1 µs)."""

    def __init__(self, frame_id: str) -> None:
        raw, pad = _frame_bytes(frame_id)
        self.frame_id = frame_id
        self._s = struct.Struct(f"<4siII{len(raw)}s{pad}x7d")
        self._raw = raw

    def __call__(
        self,
        sec: int,
        nanosec: int,
        x: float,
        y: float,
        z: float,
        qx: float,
        qy: float,
        qz: float,
        qw: float,
    ) -> bytes:
        return self._s.pack(
            CDR_LE, sec, nanosec, len(self._raw), self._raw, x, y, z, qx, qy, qz, qw
        )


class PoseWithCovarianceEncoder:
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` with a fixed ``frame_id``, packed
    directly: the pose and its 6x6 covariance (row-major; x, y, z, then rotations about the
    frame's x, y, z axes, as ROS orders it)."""

    def __init__(self, frame_id: str) -> None:
        raw, pad = _frame_bytes(frame_id)
        self.frame_id = frame_id
        self._s = struct.Struct(f"<4siII{len(raw)}s{pad}x43d")
        self._raw = raw

    def __call__(
        self, sec: int, nanosec: int, xyz_q: Sequence[float], cov: Sequence[float]
    ) -> bytes:
        return self._s.pack(CDR_LE, sec, nanosec, len(self._raw), self._raw, *xyz_q, *cov)


# --- templates -------------------------------------------------------------------------------

_STAMP_SENTINEL = (0x7E5A3C01, 0x3C5A7E02)


def sentinel(i: int) -> float:
    """A float64 whose 8 bytes are unlikely anywhere else in a message (``i`` < 250)."""
    packed = bytes([0x5A, i + 1, 0x3C, 0xA5, 0x96, 0xC3, 0x71, 0x42])
    return cast(float, struct.unpack("<d", packed)[0])


def text_placeholder(n: int) -> str:
    return "\x01\x02" * (n // 2) + "\x01" * (n % 2)


class Template:
    """Patch-in-place encoder of one message layout (see the module docstring).

    ``payload``: the CDR of a message built with header stamps ``_STAMP_SENTINEL``, doubles
    ``sentinel(0..n_doubles-1)`` and one string ``text_placeholder(text_len)`` (``text_len`` 0:
    none). :meth:`fill` returns the payload with the stamps, the doubles (in order) and the text
    (exactly ``text_len`` bytes once UTF-8 encoded) written in — one ``struct.pack`` call, the
    constant bytes in between passed as ``s`` fields.
    """

    def __init__(self, payload: bytes, n_doubles: int, text_len: int = 0) -> None:
        self.payload = payload
        self.text_len = text_len
        # patches: (offset, struct format, slots in the value tuple (consts…, sec, nsec, doubles…,
        # text)) — slots are filled in once the number of constants is known
        patches: list[tuple[int, str, tuple[str | int, ...]]] = []
        stamps = _find_all(payload, struct.pack("<iI", *_STAMP_SENTINEL))
        if not stamps:
            raise ValueError("template: no header stamp found")
        patches += [(at, "iI", ("sec", "nsec")) for at in stamps]
        for i in range(n_doubles):
            hits = _find_all(payload, struct.pack("<d", sentinel(i)))
            if len(hits) != 1:
                raise ValueError(f"template: double {i} found {len(hits)} times")
            patches.append((hits[0], "d", (i,)))
        if text_len:
            hits = _find_all(payload, text_placeholder(text_len).encode())
            if len(hits) != 1:
                raise ValueError("template: the text placeholder is not unique")
            patches.append((hits[0], f"{text_len}s", ("text",)))
        fmt, pos = "<", 0
        consts: list[bytes] = []
        order: list[tuple[str, str | int]] = []
        for at, f, slots in sorted(patches):
            if at > pos:
                fmt += f"{at - pos}s"
                order.append(("const", len(consts)))
                consts.append(payload[pos:at])
            fmt += f
            order += [("var", s) for s in slots]
            pos = at + struct.calcsize("<" + f)
        if pos < len(payload):
            fmt += f"{len(payload) - pos}s"
            order.append(("const", len(consts)))
            consts.append(payload[pos:])
        nc = len(consts)
        var = {"sec": nc, "nsec": nc + 1, "text": nc + 2 + n_doubles}
        idx = [
            x if kind == "const" else var[x] if isinstance(x, str) else nc + 2 + x
            for kind, x in order
        ]
        self._consts = tuple(consts)
        self._struct = struct.Struct(fmt)
        self._get = operator.itemgetter(*idx)
        self._n_doubles = n_doubles

    def fill(self, sec: int, nanosec: int, doubles: Sequence[float], text: bytes = b"") -> bytes:
        if len(doubles) != self._n_doubles or len(text) != self.text_len:
            raise ValueError("template: wrong number of doubles or text length")
        return self._struct.pack(*self._get((*self._consts, sec, nanosec, *doubles, text)))


def _find_all(buf: bytes, pat: bytes) -> list[int]:
    out, i = [], buf.find(pat)
    while i >= 0:
        out.append(i)
        i = buf.find(pat, i + 1)
    return out


def stamp_sentinel() -> tuple[int, int]:
    return _STAMP_SENTINEL


def pose_list(
    positions: np.ndarray, quats: np.ndarray, sec: int, nanosec: int, frame_id: str
) -> list[Any]:
    """PoseStamped messages of ``positions (N, 3)`` (m) and ``quats (N, 4)`` (xyzw)."""
    T = types()
    H, Tm = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    P, Pt, Q = (
        T["geometry_msgs/msg/Pose"],
        T["geometry_msgs/msg/Point"],
        T["geometry_msgs/msg/Quaternion"],
    )
    PS = T[POSE_STAMPED]
    return [
        PS(H(Tm(sec, nanosec), frame_id), P(Pt(*p), Q(*q)))
        for p, q in zip(positions.tolist(), quats.tolist(), strict=True)
    ]


def encode_path(
    positions: np.ndarray, quats: np.ndarray, sec: int, nanosec: int, frame_id: str
) -> bytes:
    """``nav_msgs/msg/Path`` of ``positions (N, 3)`` and ``quats (N, 4)`` (built once)."""
    path = types()[PATH](
        header(sec, nanosec, frame_id), pose_list(positions, quats, sec, nanosec, frame_id)
    )
    return serialize(path, PATH)
