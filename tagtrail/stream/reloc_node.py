"""Live relocalization (paper §3.2.2): D and phi of each incoming pose against the reference.

:class:`Relocalizer` holds what the node computes once — the reference as a
:class:`~tagtrail.geometry.reference_path.ReferencePath` (the object the offline ``report``
stage uses), the alignment transform, the reference ``Path``/markers CDR, the encoders — and
:meth:`Relocalizer.process` does the per-pose work: apply the alignment, ``k*``, D, phi
(Eqs. 3.12–3.15, ``trajectory`` mode) and the path tracker's quantities through
:meth:`~tagtrail.geometry.association.PathTracker.track`, the report stage's per-pose call, so
live values equal the offline report's (long references use
:class:`~tagtrail.geometry.pathindex.PathIndex`, exact). With ``progress`` association the node
keeps the previous match, as the report stage does along a query.
:meth:`Relocalizer.handle` is bytes in → ``[(key, CDR bytes)]`` out; the zenoh driver is
:func:`serve`.

Alignment files (``--alignment``), all JSON:

- ``summary.json`` of ``tagtrail relocalize`` (its ``"alignment"`` block and ``"plane"``);
- the ``align`` stage's ``alignment`` artifact (the block itself: ``model, scale, rotation_deg,
  translation, …``); planar models (``similarity``, ``rigid``) act in the plane named by the
  file's ``"plane"`` (else ``--plane``), ``model: none`` is the identity;
- any of these with ``"ref_A_query"``: a 4×4 ``[sR | t]`` matrix (query world → reference world),
  the only form for the 3-D models ``sim3``/``se3`` (their block holds no rotation axis).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

from tagtrail.errors import SourceError
from tagtrail.geometry import se3
from tagtrail.geometry.association import PathTracker, TrackParams
from tagtrail.geometry.reference_path import PLANES, ReferencePath, reference_plane
from tagtrail.geometry.registration import Alignment, world_transform
from tagtrail.io.msgs import stamp_problem
from tagtrail.schemas.artifacts import poses
from tagtrail.stages import report as report_stage
from tagtrail.stream import codec
from tagtrail.stream.markers import PoseMarkers, path_markers
from tagtrail.stream.stats import DropError, Stats

F64 = np.ndarray
OUTPUTS = (  # in publication order: the state (what stream follow steers by) first
    "state",
    "distance_m",
    "heading_error_deg",
    "current_pose",
    "nearest_pose",
    "markers",
    "cross_track_m",
    "progress_m",
    "curvature_1pm",
    "lookahead_pose",
)
REFERENCE_PATH = "reference_path"
# each output's ROS 2 type (SPEC Streaming); "json": the state document
OUTPUT_TYPES = {
    "distance_m": "std_msgs/msg/Float64",
    "heading_error_deg": "std_msgs/msg/Float64",
    "state": "json",
    "current_pose": "geometry_msgs/msg/PoseStamped",
    "nearest_pose": "geometry_msgs/msg/PoseStamped",
    "markers": "visualization_msgs/msg/MarkerArray",
    REFERENCE_PATH: "nav_msgs/msg/Path",
    "cross_track_m": "std_msgs/msg/Float64",
    "progress_m": "std_msgs/msg/Float64",
    "curvature_1pm": "std_msgs/msg/Float64",
    "lookahead_pose": "geometry_msgs/msg/PoseStamped",
}


class Outputs(NamedTuple):
    """One pose's result: stamp, D (m), phi, k*, planar (u, v) of the pose and of ``ref[k*]``,
    the 3-D poses ``(x, y, z, qx, qy, qz, qw)`` of the (aligned) query and of ``ref[k*]``, then
    the path tracker's cross-track (m), progress (m), curvature (1/m), lookahead point (u, v)
    and 3-D pose (on the reference, with the orientation of its nearer sample) and lost flag."""

    sec: int
    nanosec: int
    distance_m: float
    heading_error_rad: float
    heading_error_deg: float
    nearest_ref_idx: int
    u: float
    v: float
    ref_u: float
    ref_v: float
    current: tuple[float, ...]
    nearest: tuple[float, ...]
    cross_track_m: float = math.nan  # the path tracker's (geometry.association)
    progress_m: float = math.nan
    curvature_1pm: float = math.nan
    lookahead_u: float = math.nan
    lookahead_v: float = math.nan
    lost: bool = False
    lookahead: tuple[float, ...] = ()  # 3-D pose of the lookahead point, as current/nearest


def load_alignment(
    path: Path, ref_traj: pd.DataFrame, plane: str | None = None
) -> tuple[F64, F64, str | None]:
    """``(ref_A_query (4, 4), ref_R_query (3, 3), the file's plane or None)`` from an alignment
    file (module docstring); ``plane``: for a planar block of a file that names none."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
        block = doc.get("alignment", doc) if isinstance(doc, dict) else None
        if not isinstance(block, dict):
            raise ValueError("not a JSON object")
        file_plane = doc.get("plane")
        if file_plane is not None and file_plane not in PLANES:
            raise ValueError(f"unknown plane {file_plane!r}")
        matrix = doc.get("ref_A_query", block.get("ref_A_query"))
        if matrix is not None:
            A = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
            s = np.cbrt(np.linalg.det(A[:3, :3]))
            if not np.isfinite(A).all() or s <= 0:
                raise ValueError("ref_A_query is not a similarity transform")
            return A, A[:3, :3] / s, file_plane
        model = block.get("model")
        if model in (None, "none"):
            if model is None:
                raise ValueError("no 'model' (expected summary.json or an alignment block)")
            return np.eye(4), np.eye(3), file_plane
        if model not in ("similarity", "rigid"):
            raise ValueError(f"a {model} alignment needs its 'ref_A_query' matrix")
        a = math.radians(float(block["rotation_deg"]))
        R2 = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        t = np.asarray(block["translation"], dtype=np.float64).reshape(2)
        al = Alignment(model, float(block["scale"]), R2, t, np.ones(2, bool), 0.0)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise SourceError(f"{path}: not an alignment file: {err}") from err
    plane = file_plane or plane or report_stage.Params().plane
    A, R = world_transform(al, reference_plane(plane, *poses(ref_traj)))
    return A, R, file_plane


def _quat_mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def _optical_axis(qx: float, qy: float, qz: float, qw: float) -> tuple[float, float, float]:
    """``R[:, 2]`` (the camera's z axis in world) of a unit quaternion: all a heading needs."""
    return 2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx), 1 - 2 * (qx * qx + qy * qy)


class Relocalizer:
    """The live node's state and per-pose function (see the module docstring).

    ``ref_traj``: the reference trajectory (``t_ns, x_m … qw``, world_T_cam); ``plane``: SPEC
    plane name (default: the report stage's); ``alignment``: ``(A, R)`` from
    :func:`load_alignment` or None; ``frame_id`` of the outputs; ``path_max_points``: the
    published Path/markers are decimated to at most this many poses (0: all) — D and phi always
    use every sample; ``track``: association and tracker settings (default: the report stage's).
    """

    def __init__(
        self,
        ref_traj: pd.DataFrame,
        plane: str | None = None,
        alignment: tuple[F64, F64] | None = None,
        frame_id: str = "map",
        prefix: str = "relocalization",
        pose_type: str = "pose_stamped",
        path_max_points: int = 10_000,
        track: TrackParams | None = None,
    ) -> None:
        P, R = poses(ref_traj)
        plane = report_stage.Params().plane if plane is None else plane
        self.path = ReferencePath(P, reference_plane(plane, *poses(ref_traj)))
        self.tracker = PathTracker(
            self.path, track or report_stage.track_params(report_stage.Params())
        )
        self.pose_type = pose_type
        self.key = {k: f"{prefix}/{k}" for k in (*OUTPUTS, REFERENCE_PATH)}
        self._ref7 = ref_traj[["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]].to_numpy(np.float64)
        self._A: tuple[tuple[float, ...], ...] | None = None
        self._q_al: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0)
        if alignment is not None and not np.allclose(alignment[0], np.eye(4), atol=0, rtol=0):
            A, Ra = alignment
            self._A = tuple(tuple(map(float, row)) for row in A[:3])
            self._q_al = tuple(map(float, se3.quat_xyzw_from_R(Ra)))
        n = self.path.plane.n
        up = -n if float(n @ R[:, :, 1].mean(axis=0)) > 0 else n  # camera y is "down"
        self._pose_enc = codec.PoseStampedEncoder(frame_id)
        self._markers = PoseMarkers(frame_id, up)
        keep = np.arange(len(P))
        if 0 < path_max_points < len(P):
            keep = np.unique(np.linspace(0, len(P) - 1, path_max_points).round().astype(int))
        ref = self._ref7[keep]
        self.path_cdr = codec.encode_path(ref[:, :3], ref[:, 3:], 0, 0, frame_id)
        self.path_markers_cdr = path_markers(ref[:, :3], frame_id)

    def process(self, p: codec.PoseIn) -> Outputs:
        """D, phi, k* of one pose (Eqs. 3.12–3.15 via ``ReferencePath.query_point``).

        Raises :class:`DropError` for a non-finite pose or a zero quaternion.
        """
        vals = (p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw)
        if not all(map(math.isfinite, vals)):
            raise DropError("non_finite", f"pose {vals}")
        n2 = p.qx * p.qx + p.qy * p.qy + p.qz * p.qz + p.qw * p.qw
        if n2 < 1e-12:
            raise DropError("bad_quaternion", f"quaternion {vals[3:]} has no direction")
        s = 1.0 / math.sqrt(n2)
        q = (p.qx * s, p.qy * s, p.qz * s, p.qw * s)
        x, y, z = p.x, p.y, p.z
        if self._A is not None:
            (a, b, c, tx), (d, e, f, ty), (g, h, i, tz) = self._A
            x, y, z = (
                a * x + b * y + c * z + tx,
                d * x + e * y + f * z + ty,
                g * x + h * y + i * z + tz,
            )
            q = _quat_mul(self._q_al, q)
        u, v, hq = self.path.planar_point(x, y, z, *_optical_axis(*q))
        if not math.isfinite(u * u + v * v):  # finite but huge coordinates
            raise DropError("non_finite", f"pose {vals} gives planar ({u}, {v})")
        m = self.tracker.track(u, v, hq)
        if not math.isfinite(m.distance_m):
            raise DropError("non_finite", f"pose {vals} gives D = {m.distance_m}")
        k = m.ref_idx
        j, t = m.lookahead_seg, m.lookahead_t
        a, b = self._ref7[j], self._ref7[j + 1]
        la = (*(a[:3] + t * (b[:3] - a[:3])).tolist(), *(b if t > 0.5 else a)[3:].tolist())
        ref_u, ref_v = self.path.uv[k].tolist()
        return Outputs(
            p.sec,
            p.nanosec,
            m.distance_m,
            m.phi_rad,
            math.degrees(m.phi_rad),
            k,
            u,
            v,
            ref_u,
            ref_v,
            (x, y, z, *q),
            tuple(self._ref7[k].tolist()),
            m.cross_track_m,
            m.progress_m,
            m.curvature_1pm,
            m.lookahead_u,
            m.lookahead_v,
            m.lost,
            la,
        )

    def encode(self, o: Outputs) -> list[tuple[str, bytes]]:
        """The CDR/JSON payloads of one result, keyed, in publication order."""
        return list(self.iter_encode(o))

    def iter_encode(self, o: Outputs) -> Iterator[tuple[str, bytes]]:
        """:meth:`encode` lazily: the state is sent before the markers are even built."""
        key, enc = self.key, self._pose_enc
        # = json.dumps of the SPEC state dict (floats are finite; json uses float.__repr__)
        yield (
            key["state"],
            (
                f'{{"stamp_sec": {o.sec}, "stamp_nanosec": {o.nanosec}, "distance_m": '
                f'{o.distance_m!r}, "heading_error_deg": {o.heading_error_deg!r}, '
                f'"heading_error_rad": {o.heading_error_rad!r}, "nearest_ref_idx": '
                f'{o.nearest_ref_idx}, "u": {o.u!r}, "v": {o.v!r}, "cross_track_m": '
                f'{o.cross_track_m!r}, "progress_m": {o.progress_m!r}, "curvature_1pm": '
                f'{o.curvature_1pm!r}, "lookahead_u": {o.lookahead_u!r}, "lookahead_v": '
                f'{o.lookahead_v!r}, "lost": {"true" if o.lost else "false"}}}'
            ).encode(),
        )
        yield key["distance_m"], codec.encode_float64(o.distance_m)
        yield key["heading_error_deg"], codec.encode_float64(o.heading_error_deg)
        yield key["current_pose"], enc(o.sec, o.nanosec, *o.current)
        yield key["nearest_pose"], enc(o.sec, o.nanosec, *o.nearest)
        yield (
            key["markers"],
            self._markers(
                o.sec, o.nanosec, o.current[:3], o.nearest[:3], o.distance_m, o.heading_error_deg
            ),
        )
        yield key["cross_track_m"], codec.encode_float64(o.cross_track_m)
        yield key["progress_m"], codec.encode_float64(o.progress_m)
        yield key["curvature_1pm"], codec.encode_float64(o.curvature_1pm)
        yield key["lookahead_pose"], enc(o.sec, o.nanosec, *o.lookahead)

    def handle(self, data: bytes, stats: Stats | None = None) -> Iterator[tuple[str, bytes]]:
        """Payload in (CDR pose of ``pose_type``), keyed outputs out (an iterator, to publish as
        they are encoded). Bad input raises :class:`DropError` here, before any output."""
        try:
            p = codec.decode_pose(data, self.pose_type)
        except codec.CodecError as err:
            raise DropError("malformed", str(err)) from err
        problem = stamp_problem(p.nanosec)
        if problem is not None:
            raise DropError("bad_stamp", problem)
        out = self.process(p)
        if stats is not None:
            stats.stamp(p.sec, p.nanosec)
        return self.iter_encode(out)

    def reference_outputs(self) -> list[tuple[str, bytes]]:
        """The reference path and its marker, for start-up and periodic republishing."""
        return [
            (self.key[REFERENCE_PATH], self.path_cdr),
            (self.key["markers"], self.path_markers_cdr),
        ]


def serve(
    reloc: Relocalizer,
    session: Any,
    pose_key: str,
    *,
    congestion: str = "block",
    express: bool = False,
    path_period_s: float = 1.0,
    duration_s: float | None = None,
    count: int | None = None,
    stats_period_s: float = 10.0,
    stop: Any = None,
    foxglove: Any = None,
    wire: Any = None,
) -> dict[str, Any]:
    """Run the node on an open zenoh ``session`` until stopped; returns the stats summary.

    Subscribes to ``pose_key``, publishes every output under the prefix, republishes the
    reference path (and its marker) every ``path_period_s`` (0: once) at low priority and answers
    ``get`` on ``<prefix>/reference_path``. ``foxglove``: a
    :class:`~tagtrail.stream.foxglove.FoxgloveServer` that also gets every output (stopped here
    too). ``wire``: the :class:`~tagtrail.stream.wire.Wire` to speak (default: the bridge's).
    Closes the session on the way out.
    """
    import zenoh  # only where a session is used

    from tagtrail.stream.node import Node

    stats = Stats("relocalize")
    node = Node(session, stats, congestion, express, wire)
    node.types.update({reloc.key[k]: t for k, t in OUTPUT_TYPES.items()})
    node.types[pose_key] = codec.POSE_TYPES[reloc.pose_type]
    node.count = count

    def handle(data: bytes) -> Iterator[tuple[str, bytes]]:
        out = reloc.handle(data, stats)
        return out if foxglove is None else foxglove.tee(out)

    def republish() -> None:
        node.publish(reference, background=True)
        if foxglove is not None:
            foxglove.latch(reloc.reference_outputs())

    try:
        # the reference outputs never change: made zenoh payloads once, so that a republish
        # does not copy ~1 MB (10,000 path poses) again while holding the GIL
        reference = [(k, zenoh.ZBytes(v)) for k, v in reloc.reference_outputs()]
        path_payload = dict(reference)[reloc.key[REFERENCE_PATH]]
        for k in OUTPUTS:
            node.publisher(reloc.key[k])
        node.queryable(reloc.key[REFERENCE_PATH], lambda: path_payload)
        node.subscribe(pose_key, handle)
        node.every(path_period_s, republish)
    except BaseException:
        node.close()
        if foxglove is not None:
            foxglove.close()
        raise
    try:
        return node.run(duration_s, stats_period_s, stop)
    finally:
        if foxglove is not None:
            foxglove.close()
