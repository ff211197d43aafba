"""Live localization: ``world_T_cam`` from AprilTag detections (or images) and the tag map.

Inputs on zenoh (CDR, as zenoh-bridge-ros2dds forwards ROS 2 topics): ``sensor_msgs/msg/CameraInfo``
and either ``apriltag_msgs/msg/AprilTagDetectionArray`` (the apriltag_ros node's output; its
corners sit +0.5 px from OpenCV's convention and are shifted back, as the extract stage does) or
``sensor_msgs/msg/CompressedImage`` / ``Image`` (detected here with pupil-apriltags, the
extract stage's detector). Output: ``geometry_msgs/msg/PoseStamped`` (world_T_cam, the
detection's stamp) — the input of ``tagtrail stream relocalize``.

Per frame the offline pipeline's functions run with its stages' parameters (:class:`Params`; one
implementation, two drivers): the extract stage's filters, IPPE per tag
(:func:`tagtrail.geometry.ippe.solve_ippe`; of its two solutions the one the map agrees with,
:func:`~tagtrail.geometry.ippe.map_branches`), then :func:`tagtrail.geometry.fusion.frame_poses`,
the trajectory stage's per-frame method (Eq. 3.8; ``auto`` = one RANSAC PnP over every corner
of every mapped tag when >= 2 are seen, else the robust fusion of the per-tag estimates; the
offline default ``joint`` holds frames together in time, which a node answering each frame at
once cannot: a pipeline that names ``method: joint`` gets its frames posed by ``auto``, and the
node says so in a warning line when it starts). A frame's tags are taken in
the trajectory stage's order (by tag id); a tag seen twice is left out, as offline. Tag sizes:
the map's (``size_m``), else the pnp stage's ``tag_sizes`` / ``tag_size``. A map made by the
pipeline carries the sizes its pnp stage used, so the node's poses are the offline trajectory
stage's frame-by-frame poses (tests/stream/test_live_offline.py).
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
import pandas as pd
from numpy.typing import NDArray

from tagtrail.errors import DataError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import frame_poses, pnp_frames
from tagtrail.geometry.ippe import ippe_solvable, map_branches, solve_ippe
from tagtrail.geometry.se3 import T_from_xyz_quat, quat_xyzw_of
from tagtrail.io import msgs
from tagtrail.io.sources import detection_problem, detections_from_msg, raw_image_from_msg
from tagtrail.schemas.artifacts import POSE_COLS
from tagtrail.stages import extract as extract_stage
from tagtrail.stages import pnp as pnp_stage
from tagtrail.stages import trajectory as trajectory_stage
from tagtrail.stream import codec
from tagtrail.stream.stats import Deferred, DropError, Stats
from tagtrail.vision.detector import filter_detections
from tagtrail.vision.images import frame_size

log = logging.getLogger("tagtrail.stream")
F64 = NDArray[np.float64]
IMAGE_TYPES = {"compressed": msgs.COMPRESSED_IMAGE, "raw": msgs.IMAGE}
MAX_IMAGE_SIDE = 8192  # px: larger images are dropped before decoding (8192² gray = 64 MiB)
WAIT_S = 1.0  # inputs that arrive before the first CameraInfo are kept this long …
WAIT_N = 30  # … at most this many (1 s of a 30 Hz camera) …
WAIT_BYTES = 64 << 20  # … and at most this much payload


@dataclass(frozen=True)
class Params:
    """The stage parameters the node uses (defaults: the stages' own)."""

    extract: extract_stage.Params = field(default_factory=extract_stage.Params)
    """Detector settings (images) and the detection filters."""
    pnp: pnp_stage.Params = field(default_factory=pnp_stage.Params)
    """Tag sizes of tags the map gives none for."""
    trajectory: trajectory_stage.Params = field(default_factory=trajectory_stage.Params)
    """The per-frame method and its settings."""


def _duplicated(ids: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Entries of ``ids`` that occur more than once (a frame's few: by a set, ~20x cheaper
    than ``np.unique`` when, as nearly always, none does)."""
    flat = ids.reshape(-1).tolist()
    if len(set(flat)) == len(flat):
        return np.zeros(len(flat), bool)
    _, inverse, counts = np.unique(ids, return_inverse=True, return_counts=True)
    return counts[inverse.reshape(-1)] > 1


class Localizer:
    """Per-message handlers of the localize node (bytes in, ``[(key, bytes)]`` out).

    ``tag_map``: ``tag_id, x_m … qw[, size_m]`` (world_T_tag); ``params``: the stages'
    parameters (:class:`Params`).
    """

    def __init__(
        self,
        tag_map: pd.DataFrame,
        params: Params | None = None,
        pose_key: str = "tag_only_pose",
        frame_id: str = "map",
        stats: Stats | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if len(tag_map) == 0:
            raise DataError("localize: the tag map is empty")
        self.params = params or Params()
        ids = tag_map["tag_id"].to_numpy(np.int64)
        order = np.argsort(ids, kind="stable")
        self.ids = ids[order]
        self._mapped = frozenset(self.ids.tolist())
        vals = tag_map[POSE_COLS].to_numpy(np.float64)[order]
        self.world_T_tag = T_from_xyz_quat(vals[:, :3], vals[:, 3:])
        size = (
            tag_map["size_m"].to_numpy(np.float64)[order]
            if "size_m" in tag_map.columns
            else np.full(len(ids), np.nan)
        )
        self.size_m = np.where(
            np.isfinite(size) & (size > 0), size, self.params.pnp.sizes(self.ids)
        )
        self.detector = self.params.extract.detector()
        self.msg_detector = self.params.extract.detector("detections")  # recorded detections
        self.camera: CameraModel | None = None
        self._info_bytes = b""  # the last CameraInfo taken, its stamp left out
        self.pose_key = pose_key
        self.stats = stats
        self.clock = clock
        # inputs before the first CameraInfo: (handler, arrival clock, perf_counter_ns, bytes)
        self.waiting: deque[tuple[Callable[[], Iterable[tuple[str, bytes]]], float, int, int]] = (
            deque()
        )
        self._enc = codec.PoseStampedEncoder(frame_id)
        self.live: Any = None  # the live smoother (smooth()); None: each frame on its own
        self._last_obs: tuple[NDArray[np.int64], F64] | None = None
        method = self.params.trajectory.method
        self.method: Literal["auto", "avg", "lsq", "pnp"] = "auto" if method == "joint" else method
        if method == "joint":
            log.warning(
                "localize: trajectory.method is joint, which holds a recording's frames "
                "together in time; a live node answers each frame at once, so it poses "
                "frames by auto (one RANSAC PnP over the corners of >= 2 mapped tags, "
                "else the fusion of the per-tag poses). Set trajectory.method: auto for "
                "the live node to silence this"
            )

    def frame_pose(
        self, corners_px: F64, tag_ids: NDArray[np.integer], pose: bool = True
    ) -> tuple[F64 | None, int]:
        """``world_T_cam (4, 4)`` of one frame and the number of mapped tags used (None, 0 if
        none). ``corners_px (n, 4, 2)``: distorted pixels, OpenCV convention, SPEC corner order;
        ``tag_ids (n,)``: the frame's (filtered) detections; ``pose`` False: only the tags and
        corners the smoother takes (``_last_obs``), the pose None."""
        assert self.camera is not None
        ids = np.asarray(tag_ids, dtype=np.int64).reshape(-1)
        px = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
        twice = _duplicated(ids)  # offline, the detections table has no corners for these
        mapped = self._mapped
        keep = np.array([i for i, v in enumerate(ids.tolist()) if v in mapped], np.int64)
        keep = keep[np.argsort(ids[keep], kind="stable")]  # the trajectory stage's order
        self._last_obs = None
        if not len(keep):
            return None, 0
        k = np.searchsorted(self.ids, ids[keep])
        # offline, pnp keeps the observations IPPE solves (their poses: below, when needed)
        good = np.flatnonzero(ippe_solvable(px[keep], self.size_m[k], self.camera))
        good = good[~_duplicated(ids[keep][good])]
        if not len(good):
            return None, 0
        sel, kg = keep[good], k[good]
        corners = np.where(twice[sel, None, None], np.nan, px[sel])
        self._last_obs = (kg[~twice[sel]], px[sel][~twice[sel]])  # the smoother's corners
        if not pose:
            return None, len(sel)
        # multi-tag PnP needs no per-tag pose: the IPPE poses only for the fusion, when PnP
        # does not pose the frame (< 2 tags, or it fails)
        p = self.params.trajectory
        if self.method in ("auto", "pnp") and len(sel) >= 2:
            T, by_pnp = pnp_frames(
                np.full((1, 4, 4), np.nan),
                self.world_T_tag[kg],
                np.zeros(len(sel), np.int64),
                corners,
                self.size_m[kg],
                self.camera,
                p.ransac_px,
            )
            if by_pnp[0]:
                return T[0], len(sel)
        both = solve_ippe(px[sel], self.size_m[kg], self.camera)[0]
        # each tag's solution the map agrees with in the frame, as the trajectory stage takes (a
        # frame of one tag keeps its first: nothing to check it against)
        one = np.zeros(len(sel), np.int64)  # the frame of each tag: all this one
        pick = (
            map_branches(one, self.world_T_tag[kg, :3, :3], both[:, :, :3, :3])
            if len(sel) > 1
            else one
        )
        res = frame_poses(
            self.world_T_tag[kg],
            both[np.arange(len(sel)), pick],
            np.zeros(len(sel), np.int64),
            1,
            corners_px=corners,
            size_m=self.size_m[kg],
            camera=self.camera,
            method=self.method,
            loss=p.loss,
            f_scale=p.f_scale,
            rot_weight_m=p.rot_weight_m,
            ransac_px=p.ransac_px,
        )
        return res.world_T_cam[0], int(res.n_tags[0])

    def on_camera_info(self, data: bytes) -> list[tuple[str, bytes]]:
        # the camera taken last (only the stamp differs: bytes 4-12, after the CDR's 4-byte
        # encapsulation header): nothing to parse (~0.3 ms of each frame's latency otherwise)
        same = len(data) > 12 and data[:4] + data[12:] == self._info_bytes
        if same and self.camera is not None:
            return self._release()
        try:
            msg = codec.deserialize(data, msgs.CAMERA_INFO)
        except codec.CodecError as err:
            raise DropError("malformed", str(err)) from err
        try:
            cam = CameraModel.from_camera_info(msg)
        except Exception as err:
            raise DropError("bad_camera_info", str(err)) from err
        if cam.width <= 0 or cam.height <= 0:  # images are checked against it
            raise DropError("bad_camera_info", f"image size {cam.width}x{cam.height}")
        if self.camera is None or not cam.same_as(self.camera):
            log.info("localize: camera %dx%d %s", cam.width, cam.height, cam.distortion_model)
            self.camera = cam
        self._info_bytes = data[:4] + data[12:]
        return self._release()

    def _hold(self, handle: Callable[[], Iterable[tuple[str, bytes]]], size: int) -> None:
        """Keep an input that arrived before the first CameraInfo (:class:`Deferred`): the
        last :data:`WAIT_N` (:data:`WAIT_BYTES`) of them, for :data:`WAIT_S`; an input pushed
        out is dropped as ``no_camera_info``."""
        self.waiting.append((handle, self.clock(), time.perf_counter_ns(), size))
        while len(self.waiting) > WAIT_N or sum(w[3] for w in self.waiting) > WAIT_BYTES:
            self.waiting.popleft()
            self._count(DropError("no_camera_info", f"more than {WAIT_N} inputs before it"))
        raise Deferred

    def _release(self) -> list[tuple[str, bytes]]:
        """Handle the inputs kept until the first CameraInfo, oldest first (those older than
        :data:`WAIT_S`: dropped as ``no_camera_info``); each is counted here."""
        out: list[tuple[str, bytes]] = []
        now = self.clock()
        while self.waiting:
            handle, t, t_perf, _ = self.waiting.popleft()
            try:
                if now - t > WAIT_S:
                    raise DropError("no_camera_info", f"waited {now - t:.2f} s for CameraInfo")
                out += handle()
            except DropError as err:
                self._count(err)
                continue
            except Exception as err:  # noqa: BLE001 - as the node's own handling of a message
                self._count(DropError("error", f"{type(err).__name__}: {err}"))
                continue
            if self.stats is not None:
                self.stats.done(t_perf)
        return out

    def _count(self, err: DropError) -> None:
        if self.stats is not None:
            self.stats.drop(err.reason, str(err))

    def on_detections(self, data: bytes) -> Iterable[tuple[str, bytes]]:
        """The pose of one detection message (before the first CameraInfo: kept, see
        :meth:`_hold`)."""
        if self.camera is None:
            self._hold(lambda: self.on_detections(data), len(data))
        msg = self._decode(data, msgs.DETECTIONS)
        # the extract stage's conversion (−0.5 px) and filters, so live = offline
        assert self.camera is not None
        size = (self.camera.width, self.camera.height)
        found = detections_from_msg(msg)
        problem = detection_problem(found)  # what a bag source refuses, the node drops
        if problem is not None:
            raise DropError("bad_detection", problem)
        dets = list(filter_detections(found, self.msg_detector, Counter(), size))
        ids = np.array([d.tag_id for d in dets], dtype=np.int64)
        px = np.array([d.corners for d in dets], dtype=np.float64)
        return self._publish(msg.header.stamp, px.reshape(-1, 4, 2), ids)

    def on_image(self, data: bytes, kind: str = "compressed") -> Iterable[tuple[str, bytes]]:
        """Detect tags in one image and publish the pose. The image's size is checked before
        it is decoded (:meth:`check_size`): a bad or oversized image costs no memory."""
        from tagtrail.vision.apriltag import detect  # pupil-apriltags only where images are used

        if self.camera is None:
            self._hold(lambda: self.on_image(data, kind), len(data))
        msg = self._decode(data, IMAGE_TYPES[kind])
        raw = raw_image_from_msg(msg, IMAGE_TYPES[kind])
        assert isinstance(raw.data, bytes)  # a message's image: bytes, not a file path
        payload = bytes(raw.data)
        size = frame_size(raw)  # the offline extract's check too
        if size is None:
            raise DropError("bad_image", f"CompressedImage ({raw.encoding!r}): no PNG/JPEG header")
        self.check_size(*size)
        if raw.kind == "raw":
            w, h, step, n = raw.width, raw.height, raw.step, len(payload)
            if step < w or not step * (h - 1) + w <= n <= step * h:
                raise DropError("bad_image", f"Image {w}x{h} step {step}: {n} data bytes")
        try:
            img = raw.decode()
        except Exception as err:
            raise DropError("bad_image", str(err)) from err
        ints, floats = detect(np.ascontiguousarray(img), self.detector, self.camera)
        return self._publish(msg.header.stamp, floats[:, 1:].reshape(-1, 4, 2), ints[:, 0])

    def check_size(self, width: int, height: int) -> None:
        """Refuse (:class:`DropError`) an image whose size is not the camera's (CameraInfo
        ``width``/``height``) or that exceeds :data:`MAX_IMAGE_SIDE` (whatever CameraInfo says)."""
        cam = self.camera
        if cam is not None and (width, height) != (cam.width, cam.height):
            raise DropError(
                "image_size",
                f"a {width}x{height} image from a {cam.width}x{cam.height} camera (CameraInfo)",
            )
        if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
            raise DropError(
                "image_too_large" if width > 0 and height > 0 else "bad_image",
                f"a {width}x{height} image (at most {MAX_IMAGE_SIDE} px a side)",
            )

    def _decode(self, data: bytes, msgtype: str) -> Any:
        try:
            msg = codec.deserialize(data, msgtype)
        except codec.CodecError as err:
            raise DropError("malformed", str(err)) from err
        problem = msgs.stamp_problem(int(msg.header.stamp.nanosec))
        if problem is not None:
            raise DropError("bad_stamp", problem)
        if self.stats is not None:
            self.stats.stamp(int(msg.header.stamp.sec), int(msg.header.stamp.nanosec))
        return msg

    def _publish(
        self, stamp: Any, px: F64, ids: NDArray[np.integer]
    ) -> Iterable[tuple[str, bytes]]:
        if not np.isfinite(px).all():
            raise DropError("non_finite", "detection corners are not finite")
        sec, nsec = int(stamp.sec), int(stamp.nanosec)
        t_ns = sec * 1_000_000_000 + nsec
        # the smoother's step starts from its own extrapolation: the frame's pose only without
        T, _ = self.frame_pose(px, ids, self.live is None or self.live.wants_start(t_ns))
        if self.live is not None:
            out: Iterable[tuple[str, bytes]] = self.live.on_frame(
                t_ns, T, self._last_obs, self.camera
            )
            return out
        if T is None or not np.isfinite(T).all():
            raise DropError("no_pose", "no mapped tag in the frame")
        x, y, z = T[:3, 3].tolist()
        return [(self.pose_key, self._enc(sec, nsec, x, y, z, *quat_xyzw_of(T[:3, :3])))]

    def smooth(self, live: Any) -> None:
        """Pose frames by the live smoother ``live`` (:class:`~tagtrail.stream.continuity.
        LivePoses`) instead of each on its own."""
        self.live = live


def cv2_threads() -> None:
    """One OpenCV thread: the node shares the machine with the relocalize node."""
    cv2.setNumThreads(1)
