"""Stage ``extract``: a dataset source → frames, tag detections, camera model, given observations.

Image sources are decoded and detected by worker processes over chunks of frames
(:mod:`tagtrail.pool`): the parent only reads the bag (raw message bytes / file paths),
workers decode and run pupil-apriltags (tag36h11), then re-fit each tag's corners to its border's
edges (:mod:`tagtrail.vision.corners`, ``refit_corners``; corners 3-6x closer to the truth; ~20 %
of the detector's time for tags with cells over 10 px, 1.5-1.7x for small tags, whose
neighbouring edges it models). No detector is ever built in the calling
process, and workers' exit status is not trusted (see :mod:`tagtrail.vision.apriltag` for the
upstream exit-time segfault this avoids); idle workers are kept for the next extract run.
Tags whose white quiet zone runs off the image are dropped (``keep_truncated``): the detector
puts one of their edges on the border. Detection sources (``apriltag_msgs``: no image to re-fit
with) are filtered with the same ``max_hamming`` / ``min_decision_margin`` / ``tag_ids`` /
``keep_truncated`` rules; observation sources fill ``observations`` and leave ``detections``
empty. Image frames whose decoded size is not the camera's (``width``/``height`` of camera.yaml
or CameraInfo) are left out — their poses would be wrong — with a warning naming them; a
:class:`SourceError` when that leaves no frame.

Outputs (columns as docs/ARCHITECTURE.md): ``frames`` (every frame of the camera's size, with or
without tags), ``detections`` (corners in px, detector order, OpenCV convention — pixel centres
at integers —, in the raw, distorted image), ``camera`` (the ``CameraModel``; None
for observation sources), ``observations`` (cam_T_tag given by the source). Rows sorted by
(frame_idx, tag_id). ``odometry``: the recording's wheel odometry (``nav_msgs/Odometry``, the
topic ``topics.odometry`` names or the one the bag has), one row per message as recorded --
empty without odometry; bad messages (NaN values, stamps going back, a single message, an
unusable covariance) are kept and counted in one warning naming the topic: the odometry prior
decides what to use. ``mount``: the odometry's frames, the camera's frame and ``base_T_camera``
composed from ``/tf_static`` (null when no chain links base and camera).
"""

from __future__ import annotations

import logging
import os
import time
from collections import Counter
from collections.abc import Iterator
from typing import Annotated, Any, Literal

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from pydantic import Field, field_validator

from tagtrail.errors import SourceError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.frames import chain
from tagtrail.geometry.se3 import T_from_xyz_quat, xyz_quat_from_T
from tagtrail.pool import map_tasks
from tagtrail.schemas.artifacts import CORNER_COLS, POSE_COLS, columns
from tagtrail.schemas.documents import MountDoc
from tagtrail.schemas.inputs import Frame, Source
from tagtrail.schemas.ranges import TagId
from tagtrail.stages.base import StageParams
from tagtrail.vision.detector import FILTERS, DetectorConfig, explain_drops, filter_detections

log = logging.getLogger("tagtrail.extract")

INPUTS = {"source": "source"}
OUTPUTS = ("frames", "detections", "camera", "observations", "odometry", "mount")
PRIMARY = "detections"  # what `tagtrail show extract --csv` exports
OBSERVATION_COLS = columns("extract.observations")
ODOMETRY_COLS = columns("extract.odometry")
AUTO_HAMMING = {"images": 0, "detections": 2}  # max_hamming: auto (its description says why)


class Params(StageParams):
    """Detector settings (tag36h11, pupil-apriltags defaults) and output filters."""

    quad_decimate: float = Field(2.0, ge=1.0, le=8.0)
    """Detect quads on the image shrunk by this factor (faster; small tags are re-detected at full
    resolution, ``small_tags``); 1.0: full resolution."""
    quad_sigma: float = Field(0.0, ge=0.0, le=10.0)
    """Gaussian blur (px, sigma) applied before quad detection; 0: none (helps on noisy images)."""
    refine_edges: bool = True
    """Let the detector snap each quad's edges to the strong image gradients (the C library's
    refine_edges)."""
    decode_sharpening: float = Field(0.25, ge=0.0, le=10.0)
    """Sharpening of the decoded tag image (the C library's decode_sharpening); helps with small,
    blurred tags."""
    max_hamming: Annotated[int, Field(ge=0, le=3)] | Literal["auto"] = Field(
        "auto",
        description="bit errors corrected (the C library's bits_corrected, 0-3) or kept "
        "from detection messages. auto (default, on evidence, bench/bench_hamming.py): 0 for "
        "images, 2 for detection messages. No false detection at any of 0-3 on the real photos, "
        "noise, real clutter or 4000 random tag-like codes; on images 2 adds no tag on the real "
        "photos and 2 of 66 on rendered frames, one of them with its corners 2.4 px off (a "
        "small tag decoded with 2 bit errors); TagSLAM test 1's recorded detections with "
        "hamming 1-2 (110 of 764; TagSLAM uses them) bring its trajectory from 22.1 to 12.8 mm "
        "of TagSLAM's. 3: ~5 s to build the decode table per worker",
    )
    min_decision_margin: float = Field(
        20.0,
        ge=0.0,
        le=1e6,
        description="drop detections whose decision margin is lower "
        "(not applied to sources that carry no margin: TagSLAM's, Isaac ROS')",
    )
    tag_ids: tuple[TagId, ...] | None = None
    """Keep only these tag ids (null: every tag36h11 id)."""
    refit_corners: bool | Literal["edges"] = Field(
        True,
        description="re-fit corners to the border's edges (vision.corners): true: by the "
        "image gradient, then again with the neighbouring edges' part of the tag's intensity "
        "profile taken out (the most accurate; ~3 ms a tag); edges: the gradient fit alone "
        "(~0.3 ms a tag: live nodes at frame rate); false: the detector's own",
    )
    keep_truncated: bool = Field(
        False,
        description="keep tags whose white quiet zone runs off the image (their corners "
        "are unreliable)",
    )
    small_tags: Literal["redetect", "off"] = Field(
        "redetect",
        description="redetect (default): the tags quad_decimate loses (shorter side "
        "under ~35 px) re-detected at full resolution in crops around tag-like dark blobs not in "
        "a found tag (1.1-1.5x the decimated pass's time, bench/bench_recall.py); off: the "
        "decimated pass only",
    )
    EXECUTION_ONLY = frozenset({"workers", "chunk_size"})  # same output whatever their values

    @field_validator("max_hamming", mode="before")
    @classmethod
    def _hamming_range(cls, value: Any) -> Any:
        if isinstance(value, int) and not isinstance(value, bool) and not 0 <= value <= 3:
            raise ValueError(f"max_hamming is 0-3 or auto (got {value})")
        return value

    @field_validator("small_tags", mode="before")
    @classmethod
    def _yaml_off(cls, value: Any) -> Any:
        """YAML 1.1 reads a bare ``off`` as false: take it as the word it was written as."""
        return "off" if value is False else value

    workers: int = Field(0, ge=0, le=1024, description="detector processes; 0 = all cores")
    chunk_size: int = Field(16, ge=1, le=1024, description="frames per task sent to a worker")

    def detector(self, kind: str = "images") -> DetectorConfig:
        """The detector settings and filters for a source of ``kind`` (``images`` or
        ``detections``: what ``max_hamming: auto`` resolves to)."""
        hamming = self.max_hamming
        if hamming == "auto":
            hamming = AUTO_HAMMING["detections" if kind == "detections" else "images"]
        return DetectorConfig(
            quad_decimate=self.quad_decimate,
            quad_sigma=self.quad_sigma,
            refine_edges=self.refine_edges,
            decode_sharpening=self.decode_sharpening,
            max_hamming=hamming,
            min_decision_margin=self.min_decision_margin,
            tag_ids=None if self.tag_ids is None else tuple(sorted(set(self.tag_ids))),
            refit_corners=self.refit_corners,
            keep_truncated=self.keep_truncated,
            small_tags=self.small_tags,
        )


def run(source: Source, params: Params) -> dict[str, Any]:
    """Read the source (opened by the runner) and detect tags; see the module docstring."""
    src = source
    if src.kind == "observations":
        obs = src.observations()[OBSERVATION_COLS]
        frames = obs.groupby(["frame_idx", "t_ns"], sort=True).size().reset_index(name="n_det")
        return {
            "frames": _frames_table(
                frames["t_ns"], frames["frame_idx"], frames["n_det"], getattr(src, "timed", True)
            ),
            "detections": _detections_table(*_empty_detections()),
            "camera": None,
            "observations": _typed(obs, OBSERVATION_COLS),
            **odometry_outputs(src),
        }
    camera = src.camera()
    if camera is None:
        raise SourceError(
            f"{src.describe()}: no camera intrinsics — record sensor_msgs/msg/CameraInfo, put a "
            "camera.yaml in the image folder, or set `camera: <camera_info.yaml>` for this "
            "dataset in pipeline.yaml"
        )
    start = time.perf_counter()
    if src.kind == "detections":
        t_ns, frame_idx, n_det, det = _from_detection_msgs(
            src, params.detector("detections"), camera
        )
    else:
        t_ns, frame_idx, n_det, det = _detect_images(src, params, camera)
    n_frames = len(frame_idx)
    if n_frames == 0:
        raise SourceError(f"{src.describe()}: no frames")
    dt = max(time.perf_counter() - start, 1e-9)
    log.info(
        "extract: %d frames, %d detections in %.2f s (%.1f frames/s) from %s",
        n_frames,
        len(det[0]),
        dt,
        n_frames / dt,
        src.describe(),
    )
    obs = pd.DataFrame({c: np.zeros(0) for c in OBSERVATION_COLS})
    return {
        "frames": _frames_table(t_ns, frame_idx, n_det, getattr(src, "timed", True)),
        "detections": _detections_table(*det),
        "camera": camera,
        "observations": _typed(obs, OBSERVATION_COLS),
        **odometry_outputs(src),
    }


# --- odometry ----------------------------------------------------------------------------------


def odometry_outputs(src: Source) -> dict[str, Any]:
    """``{"odometry": table, "mount": MountDoc}`` of the source (module docstring)."""
    odo = src.odometry()
    if odo is None:
        return {"odometry": empty_odometry(), "mount": MountDoc()}
    rows = odo.rows[ODOMETRY_COLS].reset_index(drop=True)
    report_odometry(src, odo.topic, rows, odo.unreadable)
    frames = src.static_frames()
    base_T_camera = None
    if frames.camera_frame is not None and odo.child_frame_id:
        edges = []
        for tf in frames.transforms:
            v = np.asarray(tf.xyz_q_xyzw, dtype=np.float64)
            if np.isfinite(v).all() and np.linalg.norm(v[3:]) > 1e-9:
                edges.append((tf.parent, tf.child, T_from_xyz_quat(v[:3], v[3:])))
        T = chain(edges, odo.child_frame_id, frames.camera_frame)
        if T is not None:
            xyz, q = xyz_quat_from_T(T)
            base_T_camera = [float(x) for x in (*xyz, *q)]
    log.info(
        "%s: odometry %s, %d messages, %s -> %s; base_T_camera %s",
        src.describe(),
        odo.topic,
        len(rows),
        odo.frame_id or "?",
        odo.child_frame_id or "?",
        "from /tf_static"
        if base_T_camera is not None
        else f"not recorded (no /tf_static chain {odo.child_frame_id} -> {frames.camera_frame})",
    )
    return {
        "odometry": rows,
        "mount": MountDoc(
            odom_frame=odo.frame_id or None,
            base_frame=odo.child_frame_id or None,
            camera_frame=frames.camera_frame,
            base_T_camera=base_T_camera,
            source="tf_static" if base_T_camera is not None else None,
            topic=odo.topic,
            covariance=covariance_kind(rows),
        ),
    }


def empty_odometry() -> pd.DataFrame:
    """``extract.odometry`` without rows (the source has no odometry)."""
    df = pd.DataFrame({c: np.zeros(0, np.float64) for c in ODOMETRY_COLS})
    df["t_ns"] = df["t_ns"].astype(np.int64)
    return df


def covariance_kind(rows: pd.DataFrame) -> Literal["varying", "constant", "unusable"]:
    """``unusable``: no finite variance; ``constant``: each variance one value throughout (a
    placeholder); ``varying`` otherwise."""
    var = rows[ODOMETRY_COLS[-3:]].to_numpy(np.float64)
    if not np.isfinite(var).any():
        return "unusable"
    same = [np.unique(c[np.isfinite(c)]).size <= 1 for c in var.T]
    return "constant" if all(same) and np.isfinite(var).all() else "varying"


def odometry_problems(rows: pd.DataFrame) -> dict[str, int]:
    """What is wrong with odometry rows: messages with a value not finite (pose or twist),
    stamps not after the previous one, a lone message, messages without a usable covariance."""
    vals = rows[ODOMETRY_COLS[1:-3]].to_numpy(np.float64)
    var = rows[ODOMETRY_COLS[-3:]].to_numpy(np.float64)
    t = rows["t_ns"].to_numpy(np.int64)
    return {
        "not finite": int((~np.isfinite(vals)).any(axis=1).sum()),
        "stamps going back": int((np.diff(t) <= 0).sum()),
        "a single message": int(len(rows) == 1),
        "no usable covariance": int((~np.isfinite(var)).any(axis=1).sum()),
    }


def report_odometry(
    src: Source, topic: str, rows: pd.DataFrame, unreadable: int = 0
) -> dict[str, int]:
    """One warning naming the topic when odometry rows have problems (:func:`odometry_problems`;
    kept) or messages did not decode (``unreadable``, left out by the source). Returns the
    counts."""
    counts = {"unreadable (left out)": unreadable, **odometry_problems(rows)}
    bad = {k: v for k, v in counts.items() if v}
    if bad and (not rows.empty or unreadable):
        what = ", ".join(k if k == "a single message" else f"{v} {k}" for k, v in bad.items())
        log.warning(
            "%s: odometry %s (%d messages): %s; kept as recorded (the odometry prior decides)",
            src.describe(),
            topic,
            len(rows),
            what,
        )
    elif rows.empty:
        log.warning("%s: odometry %s has no messages", src.describe(), topic)
    return counts


# --- detection sources -------------------------------------------------------------------------


def _from_detection_msgs(
    src: Source, cfg: DetectorConfig, camera: CameraModel
) -> tuple[Any, Any, Any, Any]:
    t_ns, frame_idx, n_det, ints, floats = [], [], [], [], []
    dropped: Counter[str] = Counter()
    n_total = 0
    for idx, t, dets in src.iter_raw():
        kept = 0
        n_total += len(dets)
        for d in filter_detections(dets, cfg, dropped, (camera.width, camera.height)):
            ints.append((t, idx, d.tag_id, d.hamming))
            floats.append((d.decision_margin, *d.corners.reshape(8)))
            kept += 1
        t_ns.append(t)
        frame_idx.append(idx)
        n_det.append(kept)
    report_filters(src, cfg, dropped, n_total, len(ints))
    i = np.array(ints, dtype=np.int64).reshape(-1, 4)
    det = (i[:, 0], i[:, 1], i[:, 2:4].astype(np.int32), np.array(floats).reshape(-1, 9))
    return t_ns, frame_idx, n_det, det


def report_filters(
    src: Source, cfg: DetectorConfig, dropped: Counter[str], n_total: int, n_kept: int
) -> None:
    """Say what the filters did: a filter the source's fields do not allow is not applied (said
    once); one dropping most detections is named with the setting to change (a warning); when
    they leave none of the source's detections, a :class:`SourceError` names the filters that
    did it -- not the later "no tag observations"."""
    most, unapplied = explain_drops(dropped, n_total, cfg)
    for line in unapplied:
        log.info("%s: %s", src.describe(), line)
    if n_total and not n_kept:
        causes = most or [f"the filters drop all {n_total} detections ({_counts(dropped)})"]
        raise SourceError(f"{src.describe()}: no detection is left: {'; '.join(causes)}")
    for line in most:
        log.warning("%s: %s", src.describe(), line)
    if not most and n_kept < n_total:
        log.info(
            "%s: kept %d of %d detections, dropped %s",
            src.describe(),
            n_kept,
            n_total,
            _counts(dropped),
        )


def _counts(dropped: Counter[str]) -> str:
    return ", ".join(f"{dropped[k]} by {k}" for k in FILTERS if dropped.get(k))


# --- image sources -----------------------------------------------------------------------------


def _n_workers(requested: int) -> int:
    if requested > 0:
        return requested
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _detect_images(src: Source, params: Params, camera: CameraModel) -> tuple[Any, Any, Any, Any]:
    t_of: dict[int, int] = {}

    def chunks() -> Iterator[list[Frame]]:
        for chunk in src.chunks(params.chunk_size):
            t_of.update((idx, t) for idx, t, _ in chunk)
            yield chunk

    cfg = params.detector()
    parts = list(_map_chunks(chunks(), cfg, params, camera, len(src)))
    frame_idx = np.concatenate([p["frame_idx"] for p in parts]) if parts else np.zeros(0, int)
    order = np.argsort(frame_idx, kind="stable")
    frame_idx = frame_idx[order]
    n_det = np.concatenate([p["n_det"] for p in parts])[order] if parts else np.zeros(0, int)
    shapes = np.concatenate([p["shape"] for p in parts])[order] if parts else np.zeros((0, 2))
    dropped: Counter[str] = Counter()
    for p in parts:  # what each filter dropped, counted by the workers
        dropped.update(
            {
                k[len("dropped_") :]: int(v)
                for k, v in p.items()
                if k.startswith("dropped_") and int(v)
            }
        )
    t_ns = np.array([t_of[int(i)] for i in frame_idx], dtype=np.int64)
    det_frame = np.concatenate([p["det_frame"] for p in parts]) if parts else np.zeros(0, int)
    det_t = np.array([t_of[int(i)] for i in det_frame], dtype=np.int64)
    ints = np.concatenate([p["det_ints"] for p in parts]) if parts else np.zeros((0, 2), int)
    floats = np.concatenate([p["det_floats"] for p in parts]) if parts else np.zeros((0, 9))
    wrong = np.any(shapes != [camera.height, camera.width], axis=1)
    if wrong.any():  # another size than the intrinsics': their poses would be wrong
        _report_wrong_size(src, camera, frame_idx[wrong], t_ns[wrong], shapes[wrong], len(wrong))
        keep = ~np.isin(det_frame, frame_idx[wrong])
        det_t, det_frame, ints, floats = det_t[keep], det_frame[keep], ints[keep], floats[keep]
        t_ns, frame_idx, n_det = t_ns[~wrong], frame_idx[~wrong], n_det[~wrong]
    n_total = len(ints) + sum(dropped.values())
    report_filters(src, cfg, dropped, n_total, len(ints))
    return t_ns, frame_idx, n_det, (det_t, det_frame, ints, floats)


def _report_wrong_size(
    src: Source,
    camera: CameraModel,
    frame_idx: NDArray[Any],
    t_ns: NDArray[Any],
    shapes: NDArray[Any],
    n_frames: int,
) -> None:
    """Warn about the frames (of ``n_frames``) whose decoded size ``shapes (k, 2)`` (H, W) is not
    the camera's: they are left out; a :class:`SourceError` when no frame is left."""
    size = [f"{w}x{h}" for h, w in shapes.tolist()]
    found = ", ".join(f"{k} ({n} frame{'s' * (n > 1)})" for k, n in Counter(size).most_common())
    cam = f"{camera.width}x{camera.height}"
    if len(frame_idx) == n_frames:
        raise SourceError(
            f"{src.path}: no frame has the size {cam} of the camera ({src.camera_origin}), they "
            f"are {found}; give the camera calibration for their resolution (or images of {cam})"
        )
    names = [
        f"{src.frame_name(int(i), int(t))} ({k})"
        for i, t, k in zip(frame_idx, t_ns, size, strict=True)
    ]
    more = f" and {len(names) - 5} more" if len(names) > 5 else ""
    log.warning(
        "%s: %d of %d frames left out, their size is not the camera's %s (%s): %s%s",
        src.describe(),
        len(names),
        n_frames,
        cam,
        src.camera_origin,
        ", ".join(names[:5]),
        more,
    )


def _map_chunks(
    chunks: Iterator[list[Frame]],
    cfg: DetectorConfig,
    params: Params,
    camera: CameraModel,
    n_frames: int,
) -> Iterator[dict[str, NDArray[Any]]]:
    """``detect_chunk`` with ``cfg`` over ``chunks`` in worker processes (never in this one), or
    as tasks of the cluster the node runs on (``pool.task_mapper``)."""
    workers = min(_n_workers(params.workers), max(1, -(-n_frames // params.chunk_size)))
    yield from map_tasks(
        "tagtrail.vision.apriltag:detect_chunk", ((chunk, cfg, camera) for chunk in chunks), workers
    )


# --- tables ------------------------------------------------------------------------------------


def _empty_detections() -> tuple[Any, Any, Any, Any]:
    return (
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, 2), np.int32),
        np.zeros((0, 9)),
    )


def _frames_table(t_ns: Any, frame_idx: Any, n_det: Any, timed: bool) -> pd.DataFrame:
    """``timed``: the stamps are capture times (False for an image folder without stamps.csv:
    then no motion prior links its frames)."""
    return pd.DataFrame(
        {
            "t_ns": np.asarray(t_ns, dtype=np.int64),
            "frame_idx": np.asarray(frame_idx, dtype=np.int32),
            "n_det": np.asarray(n_det, dtype=np.int32),
            "timed": np.full(len(np.asarray(t_ns)), bool(timed)),
        }
    )


def _detections_table(t_ns: Any, frame_idx: Any, ints: Any, floats: Any) -> pd.DataFrame:
    """One row per detection, sorted by (frame_idx, tag_id), detector order within ties."""
    frame_idx = np.asarray(frame_idx, dtype=np.int64)
    order = np.lexsort((ints[:, 0], frame_idx))
    out = pd.DataFrame(
        {
            "t_ns": np.asarray(t_ns, dtype=np.int64)[order],
            "frame_idx": frame_idx[order].astype(np.int32),
            "tag_id": ints[order, 0].astype(np.int32),
            "hamming": ints[order, 1].astype(np.int32),
            "decision_margin": floats[order, 0].astype(np.float64),
        }
    )
    for k, col in enumerate(CORNER_COLS):
        out[col] = floats[order, 1 + k].astype(np.float64)
    return out


def _typed(df: pd.DataFrame, cols: list[str]) -> pd.DataFrame:
    out = df[cols].reset_index(drop=True).copy()
    out["t_ns"] = out["t_ns"].astype(np.int64)
    out["frame_idx"] = out["frame_idx"].astype(np.int32)
    out["tag_id"] = out["tag_id"].astype(np.int32)
    for c in POSE_COLS:
        out[c] = out[c].astype(np.float64)
    return out
