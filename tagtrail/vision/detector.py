"""Detector settings, the detections they give, and the one set of filter rules applied to them.

No C library here: detection-message sources and the live nodes use these without loading
pupil-apriltags (that is :mod:`tagtrail.vision.apriltag`, loaded only where images are detected).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tagtrail.vision.corners import truncated

FAMILY = "tag36h11"
# The AprilTag C library (pupil-apriltags, apriltag_ros) puts corners +0.5 px from OpenCV's pixel
# convention (measured +0.49 px); tagtrail works in OpenCV's.
C_LIBRARY_PIXEL_OFFSET = 0.5


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings plus the filters applied to its output (hashable: a cache key). No
    defaults here: ``stages.extract.Params.detector()`` is the one source of them."""

    quad_decimate: float
    quad_sigma: float
    refine_edges: bool
    decode_sharpening: float
    max_hamming: int
    min_decision_margin: float
    tag_ids: tuple[int, ...] | None
    refit_corners: bool
    keep_truncated: bool
    small_tags: str  # "redetect": re-detect small-tag candidates at full resolution; "off"


@dataclass(frozen=True)
class TagDetection:
    """One tag in one frame. ``corners``: (4, 2) px, detector order, OpenCV convention."""

    tag_id: int
    hamming: int
    decision_margin: float
    corners: NDArray[np.float64]
    family: str = "tag36h11"


def filter_detections(
    dets: list[TagDetection], cfg: DetectorConfig, dropped: Counter[str],
    image_size: tuple[int, int] | None = None,
) -> Iterator[TagDetection]:
    """The image path's filters, applied to detection messages; counts what it drops.
    ``image_size`` (width, height): for the quiet-zone test (``keep_truncated``)."""
    for d in dets:
        if d.family and "36h11" not in d.family:
            dropped[f"of family {d.family} (tagtrail reads tag36h11)"] += 1
        elif d.hamming > cfg.max_hamming:
            dropped[f"with hamming > max_hamming {cfg.max_hamming}"] += 1
        elif d.decision_margin < cfg.min_decision_margin:
            dropped[f"with decision_margin < min_decision_margin {cfg.min_decision_margin}"] += 1
        elif cfg.tag_ids is not None and d.tag_id not in cfg.tag_ids:
            dropped["not in tag_ids"] += 1
        elif (image_size is not None and not cfg.keep_truncated
              and truncated(d.corners, *image_size)[0]):
            dropped["cut by the image border (keep_truncated: false)"] += 1
        else:
            yield d
