"""The AprilTag C library (pupil-apriltags, tag36h11), guarded, and the per-chunk worker task.

Two defects of pupil-apriltags 1.0.4.post11 are worked around here:

- ``Detector.__del__`` frees the tag family and *then* destroys the detector, whose teardown
  reads the freed family (a use-after-free; upstream pupil-labs/apriltags#46): intermittent
  segfaults, mostly at interpreter exit. :class:`GuardedDetector` detaches the family first, and
  detectors are cached for the process lifetime (:func:`get_detector`) — in tagtrail they live only
  in worker processes, which leave through ``os._exit`` (multiprocessing's fork/forkserver) and
  whose results are collected before they exit.
- ``Detector.__init__`` casts ``decode_sharpening`` to ``int`` (0.25 → 0); the double the C
  library reads is set again here. ``max_hamming`` is the C library's ``bits_corrected`` (the
  binding hard-codes 2).

Corners are returned in the OpenCV pixel convention (pixel centres at integers): the C library
puts them at +0.5 px (measured +0.49 px against OpenCV); with ``refit_corners`` they are then
re-fitted to the image gradient of the tag's border (:mod:`tagtrail.vision.corners`).
"""

from __future__ import annotations

import ctypes
import functools
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from pupil_apriltags import Detector

from tagtrail.errors import SourceError
from tagtrail.geometry.camera import CameraModel
from tagtrail.vision.corners import refine_many, truncated
from tagtrail.vision.detector import C_LIBRARY_PIXEL_OFFSET, FAMILY, DetectorConfig
from tagtrail.vision.images import RawImage, frame_size


class GuardedDetector(Detector):  # type: ignore[misc]
    """pupil-apriltags' single-threaded tag36h11 detector with the fixes above."""

    def __init__(self, cfg: DetectorConfig) -> None:
        super().__init__(
            families=FAMILY,
            nthreads=1,
            quad_decimate=cfg.quad_decimate,
            quad_sigma=cfg.quad_sigma,
            refine_edges=int(cfg.refine_edges),
            decode_sharpening=cfg.decode_sharpening,
        )
        self.tag_detector_ptr.contents.decode_sharpening = float(cfg.decode_sharpening)
        self.libc.apriltag_detector_remove_family.restype = None
        fam = self.tag_families[FAMILY]
        self.libc.apriltag_detector_remove_family(self.tag_detector_ptr, fam)
        self.libc.apriltag_detector_add_family_bits(
            self.tag_detector_ptr, fam, ctypes.c_int(int(cfg.max_hamming))
        )

    def __del__(self) -> None:
        ptr = getattr(self, "tag_detector_ptr", None)
        if ptr is not None:
            for fam in self.tag_families.values():
                self.libc.apriltag_detector_remove_family(ptr, fam)
        super().__del__()


_DETECTORS: dict[tuple[object, ...], GuardedDetector] = {}


def get_detector(cfg: DetectorConfig) -> GuardedDetector:
    """A detector for ``cfg``'s detector settings (not its output filters or re-fit), created
    once and kept for the life of the process."""
    key = (
        cfg.quad_decimate,
        cfg.quad_sigma,
        cfg.refine_edges,
        cfg.decode_sharpening,
        cfg.max_hamming,
    )
    det = _DETECTORS.get(key)
    if det is None:
        det = _DETECTORS[key] = GuardedDetector(cfg)
    return det


def detect(
    img: NDArray[np.uint8], cfg: DetectorConfig, camera: CameraModel | None = None
) -> tuple[NDArray[np.int32], NDArray[Any]]:
    """Detect tags in a gray image ``(H, W)`` uint8 taken by ``camera`` (its lens distortion
    for the corner re-fit; None: no distortion).

    Returns ``ints`` (m, 2) = (tag_id, hamming) and ``floats`` (m, 9) = (decision_margin,
    c0x, c0y, …, c3x, c3y) — corners in px, detector order, OpenCV convention — after the
    ``max_hamming``/``min_decision_margin``/``tag_ids``/``keep_truncated`` filters, in detector
    order.
    """
    ints, floats, _ = _detect_filtered(img, cfg)
    if cfg.refit_corners and len(floats):
        floats[:, 1:] = refine_many(
            [img], [floats[:, 1:]], camera, model=cfg.refit_corners is True
        )[0].reshape(-1, 8)
    return ints, floats


def _detect_filtered(
    img: NDArray[np.uint8], cfg: DetectorConfig
) -> tuple[NDArray[np.int32], NDArray[Any], dict[str, int]]:
    """:func:`detect` without the corner re-fit; also how many detections each filter dropped
    (``min_decision_margin``, ``tag_ids``, ``keep_truncated``). With ``small_tags: redetect``
    a tag dropped for its margin at the decimated pass is tried again at full resolution (and
    counted again if dropped again); one dropped for its id is not."""
    ints, floats = _detect_raw(img, cfg)
    keep, low, other = _filters(cfg, ints, floats)
    dropped = {"min_decision_margin": int(low.sum()), "tag_ids": int(other.sum())}
    if cfg.small_tags == "redetect" and cfg.quad_decimate > 1.0:
        more_i, more_f = redetect_small(img, cfg, floats[keep | other])
        k2, low2, other2 = _filters(cfg, more_i, more_f)
        dropped["min_decision_margin"] += int(low2.sum())
        dropped["tag_ids"] += int(other2.sum())
        ints = np.concatenate([ints[keep], more_i[k2]])
        floats = np.concatenate([floats[keep], more_f[k2]])
    else:
        ints, floats = ints[keep], floats[keep]
    dropped["keep_truncated"] = 0
    if not cfg.keep_truncated and len(ints):
        cut = truncated(floats[:, 1:], img.shape[1], img.shape[0])
        dropped["keep_truncated"] = int(cut.sum())
        ints, floats = ints[~cut], floats[~cut]
    return ints, floats, dropped


def _filters(
    cfg: DetectorConfig, ints: NDArray[np.int32], floats: NDArray[Any]
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """Masks of the detections that pass the ``max_hamming``/``min_decision_margin``/``tag_ids``
    filters, that ``min_decision_margin`` drops, and that ``tag_ids`` drops (of the rest)."""
    ok = ints[:, 1] <= cfg.max_hamming  # the C library's own bound: not counted
    low = ok & (floats[:, 0] < cfg.min_decision_margin)
    other = np.zeros(len(ints), bool)
    if cfg.tag_ids is not None:
        other = ok & ~low & ~np.isin(ints[:, 0], np.asarray(cfg.tag_ids, dtype=np.int32))
    return ok & ~low & ~other, low, other


# The C library reads out of bounds (a segfault, measured with pupil-apriltags 1.0.4.post11) on an
# image whose shorter side is under 3 pixels once decimated (16 px at quad_decimate 8, 2 px at
# 1); no tag fits in fewer than 4 decimated pixels a side, so such an image is not handed to it.
MIN_DECIMATED_SIDE_PX = 4.0


def guarded_detect(detector: Any, img: NDArray[np.uint8], quad_decimate: float) -> list[Any]:
    """``detector.detect(img)``, or no detection where the image is too small to hold a tag at
    ``quad_decimate`` (which would crash the C library)."""
    if min(img.shape[:2]) < MIN_DECIMATED_SIDE_PX * max(1.0, quad_decimate):
        return []
    return list(detector.detect(img))


def _detect_raw(
    img: NDArray[np.uint8], cfg: DetectorConfig
) -> tuple[NDArray[np.int32], NDArray[Any]]:
    """The C library's detections, unfiltered: ints (m, 2), floats (m, 9) as :func:`detect`."""
    dets = guarded_detect(get_detector(cfg), img, cfg.quad_decimate)
    ints = np.array([(d.tag_id, d.hamming) for d in dets], dtype=np.int32).reshape(-1, 2)
    floats = np.array(
        [
            (d.decision_margin, *(np.asarray(d.corners).reshape(8) - C_LIBRARY_PIXEL_OFFSET))
            for d in dets
        ],
        dtype=np.float64,
    ).reshape(-1, 9)
    return ints, floats


# Small-tag re-detection (``small_tags: redetect``). Decimation loses the quads of tags whose
# shorter side is under ~35 px (their 1-cell border and quiet zone become ~1 px); the decode itself
# runs at full resolution and is not the problem. Candidates: dark blobs of an adaptive threshold
# of the image at 2/3 size (at half size the quiet zone of ~15 px tags vanishes and the tag merges
# with what surrounds it) that look like a tag's border, not inside a tag already found; each is
# re-detected at full resolution (quad_decimate 1) in a crop around it, the smallest first, up to
# CROP_BUDGET of the image.
SEARCH_SCALE = 2 / 3
SEARCH_INTERP = cv2.INTER_LINEAR  # INTER_AREA is ~5x slower at 2/3
SEARCH_BLOCK = 11  # adaptive threshold window at SEARCH_SCALE (~16 full-resolution px)
SEARCH_C = 7  # a pixel is dark this far below its window's mean (gray levels)
SMALL_MIN_PX = 6.0  # a candidate's shorter bounding-box side, full-resolution px
SMALL_MAX_PX = 40.0  # shorter sides above this are found at quad_decimate 2
SMALL_MAX_LONG_PX = 96.0  # the longer side (tags seen at a grazing angle are long and thin)
SMALL_MAX_ASPECT = 6.0
# A tag's border with the dark data cells joined to it: holes (the white cells) cover ~20-60 % of
# its outline, and the outline (a perspective square) fills much of its bounding box; solid dark
# blobs and thin strokes are neither.
SMALL_MIN_HOLES = 0.15
SMALL_MIN_FILL = 0.2
CROP_MARGIN = 0.15  # crop margin, in candidate sizes, plus CROP_MARGIN_PX: the quiet zone and
CROP_MARGIN_PX = 4  # some of the background the C library's threshold needs
# The C library thresholds in 4x4-px tiles from the image origin: crops start on that grid, so a
# crop's pixels are thresholded as in the full image (and its tags get the same corners).
CROP_ALIGN_PX = 4
CROP_INSIDE_PX = 1.0  # a crop's detection must keep this far from the crop's cut edges
CROP_BUDGET = 0.2  # crops cover at most this fraction of the image (full resolution costs ~3x)


def tag_like_blobs(img: NDArray[np.uint8]) -> NDArray[np.float64]:
    """Dark blobs of the gray image ``img`` (H, W) that may be small tags (see above): (k, 4)
    bounding boxes ``x, y, w, h`` in full-resolution px."""
    h, w = img.shape
    small = cv2.resize(
        img, (round(w * SEARCH_SCALE), round(h * SEARCH_SCALE)), interpolation=SEARCH_INTERP
    )
    mask = cv2.adaptiveThreshold(
        small, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV, SEARCH_BLOCK, SEARCH_C
    )
    contours, hier = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return np.zeros((0, 4))
    # every contour's box at once (a Python loop over ~1000 contours costs as much as finding
    # them): CCOMP's top level are the outlines of dark blobs, nested ones included; their
    # children are their holes
    parent = hier[0][:, 3]
    n_pts = np.fromiter(map(len, contours), np.int64, len(contours))
    starts = np.cumsum(n_pts) - n_pts
    pts = np.concatenate(contours).reshape(-1, 2)
    lo, hi = np.minimum.reduceat(pts, starts), np.maximum.reduceat(pts, starts)
    size = (hi - lo + 1) / SEARCH_SCALE
    short, long = size.min(axis=1), size.max(axis=1)
    blob = np.flatnonzero(
        (parent < 0)
        & (SMALL_MIN_PX <= short)
        & (short <= SMALL_MAX_PX)
        & (long <= SMALL_MAX_LONG_PX)
        & (long <= SMALL_MAX_ASPECT * short)
    )
    hole = np.flatnonzero(np.isin(parent, blob))
    area = np.zeros(len(contours))
    for k in np.concatenate([blob, hole]):
        area[k] = cv2.contourArea(contours[k])
    holes = np.bincount(parent[hole], weights=area[hole], minlength=len(contours))
    keep = blob[
        (holes[blob] >= SMALL_MIN_HOLES * area[blob])
        & (area[blob] >= SMALL_MIN_FILL * np.prod(hi[blob] - lo[blob], axis=1))
    ]
    return np.column_stack([lo[keep] / SEARCH_SCALE, size[keep]])


def small_tag_candidates(
    img: NDArray[np.uint8], found: NDArray[Any]
) -> list[tuple[int, int, int, int]]:
    """Crops ``(x0, y0, x1, y1)`` (full-resolution px, exclusive ends; they may overlap) around
    the tag-like blobs of ``img`` (:func:`tag_like_blobs`), leaving out those whose centre lies
    in a tag of ``found`` (m, 9) (see :func:`detect`) and those inside an earlier crop."""
    h, w = img.shape
    boxes = tag_like_blobs(img)
    centre = boxes[:, None, :2] + boxes[:, None, 2:] / 2
    quads = found[:, 1:].reshape(-1, 4, 2)
    in_found = (quads.min(axis=1) <= centre) & (centre <= quads.max(axis=1))
    boxes = boxes[~np.all(in_found, axis=2).any(axis=1)]
    crops: list[tuple[int, int, int, int]] = []
    area, budget = 0, CROP_BUDGET * h * w
    for x, y, bw, bh in boxes[np.argsort(boxes[:, 2:].max(axis=1), kind="stable")]:
        # the smallest first: the likeliest to be missed
        size = max(bw, bh)
        m = CROP_MARGIN * size
        if any(
            x0 + CROP_INSIDE_PX < x - m
            and y0 + CROP_INSIDE_PX < y - m
            and x + bw + m < x1 - 1 - CROP_INSIDE_PX
            and y + bh + m < y1 - 1 - CROP_INSIDE_PX
            for x0, y0, x1, y1 in crops
        ):
            continue  # already inside a crop
        m += CROP_MARGIN_PX
        x0, y0 = (max(0, int(v - m)) // CROP_ALIGN_PX * CROP_ALIGN_PX for v in (x, y))
        crop = (x0, y0, min(w, int(x + bw + m + 1)), min(h, int(y + bh + m + 1)))
        area += (crop[2] - crop[0]) * (crop[3] - crop[1])
        if area > budget:
            break
        crops.append(crop)
    return crops


def redetect_small(
    img: NDArray[np.uint8], cfg: DetectorConfig, found: NDArray[Any]
) -> tuple[NDArray[np.int32], NDArray[Any]]:
    """Tags the decimated pass (``found`` (m, 9)) missed, re-detected at full resolution in crops
    around small-tag candidates (:func:`small_tag_candidates`): ints (k, 2), floats (k, 9) in the
    full image's pixels, unfiltered; none of them a tag already in ``found`` or found twice."""
    full = get_detector(replace(cfg, quad_decimate=1.0))
    h, w = img.shape
    centres = [q.mean(axis=0) for q in found[:, 1:].reshape(-1, 4, 2)]
    ints, floats = [], []
    for x0, y0, x1, y1 in small_tag_candidates(img, found):
        for d in guarded_detect(full, np.ascontiguousarray(img[y0:y1, x0:x1]), 1.0):
            corners = np.asarray(d.corners, dtype=np.float64) - C_LIBRARY_PIXEL_OFFSET
            corners = corners + (x0, y0)
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            # cut by the crop (not by the image): the whole tag is in another crop or nowhere
            if (
                (x0 > 0 and lo[0] < x0 + CROP_INSIDE_PX)
                or (y0 > 0 and lo[1] < y0 + CROP_INSIDE_PX)
                or (x1 < w and hi[0] > x1 - 1 - CROP_INSIDE_PX)
                or (y1 < h and hi[1] > y1 - 1 - CROP_INSIDE_PX)
            ):
                continue
            centre = corners.mean(axis=0)
            size = float(np.max(hi - lo))
            if any(np.hypot(*(centre - c)) < 0.5 * size for c in centres):
                continue  # the same tag: found decimated, or in an overlapping crop
            centres.append(centre)
            ints.append((d.tag_id, d.hamming))
            floats.append((d.decision_margin, *corners.reshape(8)))
    return (
        np.array(ints, dtype=np.int32).reshape(-1, 2),
        np.array(floats, dtype=np.float64).reshape(-1, 9),
    )


@functools.cache
def _single_threaded_opencv() -> None:
    cv2.setNumThreads(1)  # one worker per core already; OpenCV's own threads would oversubscribe
    # a damaged image is one error line (its decode returns None), not OpenCV's log lines too
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def detect_chunk(
    chunk: list[tuple[int, int, RawImage]], cfg: DetectorConfig, camera: CameraModel | None = None
) -> dict[str, NDArray[Any]]:
    """Decode and detect a chunk of frames taken by ``camera`` (runs in a worker process).

    Returns arrays: ``frame_idx`` (n,), ``n_det`` (n,), ``shape`` (n, 2) image (H, W), per
    detection ``det_frame`` (m,), ``det_ints`` (m, 2), ``det_floats`` (m, 9) (see :func:`detect`),
    and per filter (``dropped_<filter>`` ()) the detections it dropped (:func:`_detect_filtered`).
    """
    _single_threaded_opencv()
    n_det, shapes, det_frame, ints, floats = [], [], [], [], []
    imgs: list[NDArray[np.uint8] | None] = []  # None: no tags (the image is not kept)
    dropped: dict[str, int] = {}
    for idx, t_ns, raw in chunk:
        size = frame_size(raw) if camera is not None else None
        if camera is not None and size is not None and size != (camera.width, camera.height):
            # not the camera's size: left out by extract, so not decoded (a 1 MB PNG can say
            # 20000x20000: 400 MB once decoded)
            n_det.append(0)
            shapes.append((size[1], size[0]))
            det_frame.append(np.zeros(0, np.int64))
            ints.append(np.zeros((0, 2), np.int32))
            floats.append(np.zeros((0, 9)))
            imgs.append(None)
            continue
        try:
            img = raw.decode()
        except SourceError as err:
            raise SourceError(
                f"frame {idx} (stamp {t_ns // 10**9}.{t_ns % 10**9:09d} s): {err}"
            ) from err
        i, f, drops = _detect_filtered(img, cfg)
        for name, n in drops.items():
            dropped[name] = dropped.get(name, 0) + n
        n_det.append(len(i))
        shapes.append(img.shape)
        det_frame.append(np.full(len(i), idx, dtype=np.int64))
        ints.append(i)
        floats.append(f)
        imgs.append(img if len(i) else None)
    if cfg.refit_corners:  # the whole chunk in one fit
        with_tags = [k for k, f in enumerate(floats) if len(f)]
        grays = []
        for k in with_tags:
            gray = imgs[k]
            assert gray is not None  # a frame with tags keeps its image
            grays.append(gray)
        refined = refine_many(
            grays, [floats[k][:, 1:] for k in with_tags], camera, model=cfg.refit_corners is True
        )
        for k, r in zip(with_tags, refined, strict=True):
            floats[k][:, 1:] = r.reshape(-1, 8)
    return {
        "frame_idx": np.array([c[0] for c in chunk], dtype=np.int64),
        "n_det": np.array(n_det, dtype=np.int32),
        "shape": np.array(shapes, dtype=np.int64).reshape(-1, 2),
        "det_frame": np.concatenate(det_frame) if det_frame else np.zeros(0, np.int64),
        "det_ints": np.concatenate(ints) if ints else np.zeros((0, 2), np.int32),
        "det_floats": np.concatenate(floats) if floats else np.zeros((0, 9)),
        **{f"dropped_{name}": np.array(n, dtype=np.int64) for name, n in dropped.items()},
    }
