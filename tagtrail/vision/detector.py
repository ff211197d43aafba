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
    refit_corners: bool | str  # True, "edges" (the gradient fit alone) or False
    keep_truncated: bool
    small_tags: str  # "redetect": re-detect small-tag candidates at full resolution; "off"


@dataclass(frozen=True)
class TagDetection:
    """One tag in one frame. ``corners``: (4, 2) px, detector order, OpenCV convention.
    A quality field the source does not carry reads ``hamming`` -1, ``decision_margin`` NaN;
    ``family`` "" when the source does not name it (tagtrail's tag36h11 is assumed)."""

    tag_id: int
    hamming: int
    decision_margin: float
    corners: NDArray[np.float64]
    family: str = "tag36h11"


# Filter names = the extract parameters that set them; dropped counts are keyed by them, and by
# "unapplied:<name>" for detections the filter could not judge (the source lacks the field).
FILTERS = ("family", "max_hamming", "min_decision_margin", "tag_ids", "keep_truncated")


def filter_detections(
    dets: list[TagDetection],
    cfg: DetectorConfig,
    dropped: Counter[str],
    image_size: tuple[int, int] | None = None,
) -> Iterator[TagDetection]:
    """The image path's filters, applied to detection messages; counts what each drops in
    ``dropped`` (keys :data:`FILTERS`; ``hamming=<k>`` per dropped hamming value) and what it
    could not judge (``unapplied:max_hamming`` / ``unapplied:min_decision_margin``: the field is
    not carried, so that filter is not applied). ``image_size`` (width, height): for the
    quiet-zone test (``keep_truncated``)."""
    for d in dets:
        if d.hamming < 0:
            dropped["unapplied:max_hamming"] += 1
        if d.decision_margin != d.decision_margin:  # NaN
            dropped["unapplied:min_decision_margin"] += 1
        if d.family and "36h11" not in d.family:
            dropped["family"] += 1
            dropped[f"family={d.family}"] += 1
        elif d.hamming > cfg.max_hamming:
            dropped["max_hamming"] += 1
            dropped[f"hamming={d.hamming}"] += 1
        elif d.decision_margin < cfg.min_decision_margin:
            dropped["min_decision_margin"] += 1
        elif cfg.tag_ids is not None and d.tag_id not in cfg.tag_ids:
            dropped["tag_ids"] += 1
        elif (
            image_size is not None
            and not cfg.keep_truncated
            and truncated(d.corners, *image_size)[0]
        ):
            dropped["keep_truncated"] += 1
        else:
            yield d


def _setting(name: str, cfg: DetectorConfig, dropped: Counter[str]) -> tuple[str, str]:
    """(the filter as set, the change that keeps what it drops) for messages."""
    if name == "family":
        fams = sorted(k.split("=", 1)[1] for k in dropped if k.startswith("family="))
        return (
            f"the family filter (tagtrail reads {FAMILY}; found {', '.join(fams)})",
            f"record {FAMILY} tags or choose another detections topic",
        )
    if name == "max_hamming":
        worst = max(
            (int(k.split("=")[1]) for k in dropped if k.startswith("hamming=")),
            default=cfg.max_hamming + 1,
        )
        return f"max_hamming {cfg.max_hamming}", f"set extract.max_hamming: {min(worst, 3)}"
    if name == "min_decision_margin":
        return (
            f"min_decision_margin {cfg.min_decision_margin:g}",
            "set extract.min_decision_margin: 0",
        )
    if name == "tag_ids":
        return (
            f"tag_ids {list(cfg.tag_ids or ())}",
            "set extract.tag_ids: null (all) or list the ids recorded",
        )
    return "keep_truncated false", "set extract.keep_truncated: true"


def explain_drops(
    dropped: Counter[str], n_total: int, cfg: DetectorConfig
) -> tuple[list[str], list[str]]:
    """What the filters did to ``n_total`` detections, counted by :func:`filter_detections`:
    ``(most, unapplied)`` — one line per filter that dropped more than half of them, naming the
    filter and the setting to change ("min_decision_margin 20 drops 1471 of 1471 detections;
    set extract.min_decision_margin: 0"), and one per filter not applied for lack of its field
    (said only when the setting would have dropped something)."""
    most = []
    for name in FILTERS:
        n = dropped.get(name, 0)
        if n and 2 * n > n_total:
            what, change = _setting(name, cfg, dropped)
            most.append(f"{what} drops {n} of {n_total} detections; {change}")
    unapplied = []
    for name, active in (
        ("max_hamming", True),
        ("min_decision_margin", cfg.min_decision_margin > 0),
    ):
        n = dropped.get(f"unapplied:{name}", 0)
        if n and active:
            field = name.split("_", 1)[1]
            unapplied.append(
                f"{name} is not applied to {n} detections: the source carries no "
                f"{field.replace('_', ' ')}"
            )
    return most, unapplied
