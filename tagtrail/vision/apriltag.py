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

from tagtrail.geometry.camera import CameraModel
from tagtrail.vision.corners import refine_many, truncated
from tagtrail.vision.detector import C_LIBRARY_PIXEL_OFFSET, FAMILY, DetectorConfig
from tagtrail.vision.images import RawImage


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
    key = (cfg.quad_decimate, cfg.quad_sigma, cfg.refine_edges, cfg.decode_sharpening,
           cfg.max_hamming)
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
        floats[:, 1:] = refine_many([img], [floats[:, 1:]], camera)[0].reshape(-1, 8)
    return ints, floats


def _detect_filtered(
    img: NDArray[np.uint8], cfg: DetectorConfig
) -> tuple[NDArray[np.int32], NDArray[Any], int]:
    """:func:`detect` without the corner re-fit; also the number of tags dropped as cut by the
    image border."""
    ints, floats = _keep(cfg, *_detect_raw(img, cfg))
    if cfg.small_tags == "redetect" and cfg.quad_decimate > 1.0:
        more_i, more_f = _keep(cfg, *redetect_small(img, cfg, floats))
        ints, floats = np.concatenate([ints, more_i]), np.concatenate([floats, more_f])
    n_cut = 0
    if not cfg.keep_truncated and len(ints):
        cut = truncated(floats[:, 1:], img.shape[1], img.shape[0])
        n_cut = int(cut.sum())
        ints, floats = ints[~cut], floats[~cut]
    return ints, floats, n_cut


def _keep(
    cfg: DetectorConfig, ints: NDArray[np.int32], floats: NDArray[Any]
) -> tuple[NDArray[np.int32], NDArray[Any]]:
    """The detections that pass the ``max_hamming``/``min_decision_margin``/``tag_ids``
    filters."""
    keep = (ints[:, 1] <= cfg.max_hamming) & (floats[:, 0] >= cfg.min_decision_margin)
    if cfg.tag_ids is not None:
        keep &= np.isin(ints[:, 0], np.asarray(cfg.tag_ids, dtype=np.int32))
    return ints[keep], floats[keep]


def _detect_raw(
    img: NDArray[np.uint8], cfg: DetectorConfig
) -> tuple[NDArray[np.int32], NDArray[Any]]:
    """The C library's detections, unfiltered: ints (m, 2), floats (m, 9) as :func:`detect`."""
    dets = get_detector(cfg).detect(img)
    ints = np.array([(d.tag_id, d.hamming) for d in dets], dtype=np.int32).reshape(-1, 2)
    floats = np.array(
        [(d.decision_margin, *(np.asarray(d.corners).reshape(8) - C_LIBRARY_PIXEL_OFFSET))
         for d in dets],
        dtype=np.float64,
    ).reshape(-1, 9)
    return ints, floats


# Small-tag re-detection (``small_tags: redetect``). Decimation loses the quads of tags under
# ~40 px (the 1-cell black border becomes ~1 px); the decode itself runs at full resolution and
# is not the problem. Candidates: dark, roughly square blobs of an adaptive threshold of the
# half-size image (~1 ms on 816x612), not inside a tag already found; each is re-detected at full
# resolution (quad_decimate 1) in a crop with a margin, the smallest first, up to CROP_BUDGET of
# the image.
SMALL_MIN_PX = 8.0  # candidate bounding box side, full-resolution px
SMALL_MAX_PX = 72.0  # larger tags are found at quad_decimate 2
CROP_MARGIN = 0.75  # crop margin, in candidate sizes
CROP_INSIDE_PX = 1.0  # a crop's detection must keep this far from the crop's cut edges
CROP_BUDGET = 0.25  # crops cover at most this fraction of the image (full resolution costs ~4x)


def small_tag_candidates(
    img: NDArray[np.uint8], found: NDArray[Any]
) -> list[tuple[int, int, int, int]]:
    """Crops ``(x0, y0, x1, y1)`` (full-resolution px, exclusive ends; they may overlap) around
    dark square blobs of ``img`` that may be small tags, leaving out those whose centre lies in a
    tag of ``found`` (m, 9) (see :func:`detect`) and those inside an earlier crop."""
    h, w = img.shape
    small = cv2.resize(img, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    mask = cv2.adaptiveThreshold(small, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV,
                                 11, 7)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    boxes = []
    quads = found[:, 1:].reshape(-1, 4, 2)
    lo_q, hi_q = quads.min(axis=1), quads.max(axis=1)
    for c in contours:
        x, y, bw, bh = cv2.boundingRect(c)
        x, y, bw, bh = 2 * x, 2 * y, 2 * bw, 2 * bh
        if not (SMALL_MIN_PX <= bw <= SMALL_MAX_PX and SMALL_MIN_PX <= bh <= SMALL_MAX_PX):
            continue
        (_, (rw, rh), _) = cv2.minAreaRect(c)
        if max(rw, rh) > 3 * max(min(rw, rh), 1) or cv2.contourArea(c) < 0.6 * rw * rh:
            continue  # not a (perspective) square filled by its black border
        cx, cy = x + bw / 2, y + bh / 2
        if np.any((lo_q[:, 0] <= cx) & (cx <= hi_q[:, 0]) & (lo_q[:, 1] <= cy)
                  & (cy <= hi_q[:, 1])):
            continue
        boxes.append((max(bw, bh), x, y, bw, bh))
    crops: list[tuple[int, int, int, int]] = []
    area, budget = 0, CROP_BUDGET * h * w
    for size, x, y, bw, bh in sorted(boxes):  # the smallest first: the likeliest to be missed
        m = 0.25 * size
        if any(x0 + CROP_INSIDE_PX < x - m and y0 + CROP_INSIDE_PX < y - m
               and x + bw + m < x1 - 1 - CROP_INSIDE_PX and y + bh + m < y1 - 1 - CROP_INSIDE_PX
               for x0, y0, x1, y1 in crops):
            continue  # already inside a crop
        m = CROP_MARGIN * size + 4
        crop = (max(0, int(x - m)), max(0, int(y - m)), min(w, int(x + bw + m + 1)),
                min(h, int(y + bh + m + 1)))
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
        for d in full.detect(np.ascontiguousarray(img[y0:y1, x0:x1])):
            corners = np.asarray(d.corners, dtype=np.float64) - C_LIBRARY_PIXEL_OFFSET
            corners = corners + (x0, y0)
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            # cut by the crop (not by the image): the whole tag is in another crop or nowhere
            if ((x0 > 0 and lo[0] < x0 + CROP_INSIDE_PX) or (y0 > 0 and lo[1] < y0 + CROP_INSIDE_PX)
                    or (x1 < w and hi[0] > x1 - 1 - CROP_INSIDE_PX)
                    or (y1 < h and hi[1] > y1 - 1 - CROP_INSIDE_PX)):
                continue
            centre = corners.mean(axis=0)
            size = float(np.max(hi - lo))
            if any(np.hypot(*(centre - c)) < 0.5 * size for c in centres):
                continue  # the same tag: found decimated, or in an overlapping crop
            centres.append(centre)
            ints.append((d.tag_id, d.hamming))
            floats.append((d.decision_margin, *corners.reshape(8)))
    return (np.array(ints, dtype=np.int32).reshape(-1, 2),
            np.array(floats, dtype=np.float64).reshape(-1, 9))


@functools.cache
def _single_threaded_opencv() -> None:
    cv2.setNumThreads(1)  # one worker per core already; OpenCV's own threads would oversubscribe


def detect_chunk(
    chunk: list[tuple[int, int, RawImage]], cfg: DetectorConfig, camera: CameraModel | None = None
) -> dict[str, NDArray[Any]]:
    """Decode and detect a chunk of frames taken by ``camera`` (runs in a worker process).

    Returns arrays: ``frame_idx`` (n,), ``n_det`` (n,), ``shape`` (n, 2) image (H, W), per
    detection ``det_frame`` (m,), ``det_ints`` (m, 2), ``det_floats`` (m, 9) (see :func:`detect`),
    and ``n_truncated`` (): tags dropped as cut by the image border.
    """
    _single_threaded_opencv()
    n_det, shapes, det_frame, ints, floats = [], [], [], [], []
    imgs: list[NDArray[np.uint8] | None] = []  # None: no tags (the image is not kept)
    n_cut = 0
    for idx, _t_ns, raw in chunk:
        img = raw.decode()
        i, f, cut = _detect_filtered(img, cfg)
        n_cut += cut
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
        refined = refine_many(grays, [floats[k][:, 1:] for k in with_tags], camera)
        for k, r in zip(with_tags, refined, strict=True):
            floats[k][:, 1:] = r.reshape(-1, 8)
    return {
        "frame_idx": np.array([c[0] for c in chunk], dtype=np.int64),
        "n_det": np.array(n_det, dtype=np.int32),
        "shape": np.array(shapes, dtype=np.int64).reshape(-1, 2),
        "det_frame": np.concatenate(det_frame) if det_frame else np.zeros(0, np.int64),
        "det_ints": np.concatenate(ints) if ints else np.zeros((0, 2), np.int32),
        "det_floats": np.concatenate(floats) if floats else np.zeros((0, 9)),
        "n_truncated": np.array(n_cut, dtype=np.int64),
    }
