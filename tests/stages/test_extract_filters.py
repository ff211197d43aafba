"""extract's filters explain themselves: a filter dropping most detections is named with the
setting to change, one that drops them all stops the run saying so, and a quality filter whose
field the source does not carry is not applied (said once). Bags written in tmp_path."""

from __future__ import annotations

import bz2
import logging
from pathlib import Path

import numpy as np
import pytest

from tagtrail.errors import SourceError
from tagtrail.geometry.camera import CameraModel
from tagtrail.schemas.pipeline import DatasetConfig
from tagtrail.stages import extract
from tests.extracting import extract_from
from tests.io import bags

CAM = CameraModel.from_dict(
    {
        "width": 640,
        "height": 480,
        "distortion_model": "plumb_bob",
        "K": [500, 0, 320, 0, 500, 240, 0, 0, 1],
        "D": [0] * 5,
    }
)
SQUARE = np.array([[300.0, 260.0], [340.0, 260.0], [340.0, 220.0], [300.0, 220.0]])


def _ros2_bag(tmp_path: Path, quality: list[tuple[int, float]]) -> Path:
    """apriltag_ros (ROS 2) detections, one per frame, of (hamming, decision_margin)."""
    out = [("/camera_info", bags.T0_NS, bags.camera_info_msg(CAM))]
    for k, (ham, margin) in enumerate(quality):
        t = bags.T0_NS + k * 50_000_000
        out.append(("/detections", t, bags.detections_msg(t, [(4, ham, margin, SQUARE + k)])))
    return bags.write_bag(tmp_path / "bag", out)


def test_a_filter_dropping_every_detection_stops_naming_it(tmp_path: Path) -> None:
    bag = _ros2_bag(tmp_path, [(0, 8.0)] * 10)
    with pytest.raises(
        SourceError,
        match=r"no detection is left: min_decision_margin 20 drops "
        r"10 of 10 detections; set extract.min_decision_margin: 0$",
    ):
        extract_from(bag)
    assert len(extract_from(bag, extract.Params(min_decision_margin=0))["detections"]) == 10


def test_a_filter_dropping_most_detections_is_named(tmp_path: Path, caplog) -> None:
    bag = _ros2_bag(tmp_path, [(2, 60.0)] * 6 + [(1, 60.0)] + [(0, 60.0)] * 3)
    with caplog.at_level(logging.INFO, logger="tagtrail.extract"):
        det = extract_from(bag, extract.Params(max_hamming=0))["detections"]
    assert len(det) == 3
    assert "max_hamming 0 drops 7 of 10 detections; set extract.max_hamming: 2" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="tagtrail.extract"):
        det = extract_from(bag)["detections"]  # max_hamming auto: 2 for detection messages
    assert len(det) == 10 and " drops " not in caplog.text and " dropped " not in caplog.text


def test_max_hamming_auto_resolves_per_source_kind() -> None:
    params = extract.Params()
    assert params.max_hamming == "auto"
    assert params.detector().max_hamming == 0 and params.detector("images").max_hamming == 0
    assert params.detector("detections").max_hamming == 2
    assert extract.Params(max_hamming=1).detector("detections").max_hamming == 1
    with pytest.raises(ValueError, match="max_hamming is 0-3 or auto"):
        extract.Params(max_hamming=4)


def test_unapplied_quality_filters_are_said_once(tmp_path: Path, caplog) -> None:
    """Isaac ROS detections carry neither hamming nor decision margin: both filters are not
    applied, each said once for the whole recording; the table reads -1 / NaN."""

    bag, truth = bags.isaac_bag(tmp_path, CAM)
    with caplog.at_level(logging.INFO, logger="tagtrail.extract"):
        det = extract_from(bag)["detections"]
    lines = [r.getMessage() for r in caplog.records]
    assert (
        sum(
            "max_hamming is not applied to 10 detections: the source carries no hamming" in m
            for m in lines
        )
        == 1
    )
    assert (
        sum(
            "min_decision_margin is not applied to 10 detections: the source carries no "
            "decision margin" in m
            for m in lines
        )
        == 1
    )
    assert (det["hamming"] == -1).all() and det["decision_margin"].isna().all()
    corners = det[[f"c{k}{a}" for k in range(4) for a in "xy"]].to_numpy().reshape(-1, 4, 2)
    order = np.array(truth).reshape(5, 2, 4, 2).reshape(-1, 4, 2)  # frame, then tag id
    assert np.abs(corners - order).max() < 1e-9


def test_tagslam_test_1_hamming_drops_are_counted(realdata: Path, tmp_path: Path, caplog) -> None:
    """TagSLAM test 1: 110 of its 772 detections have hamming 1-2; max_hamming 0 drops them
    (not most: counted at info level), max_hamming 2 keeps them; no margin to filter on; 8 are
    of tags cut by the image border (keep_truncated)."""
    root = realdata / "tagslam_test_1"
    bag = tmp_path / "tag_detections.bag"
    bag.write_bytes(bz2.decompress((root / "tag_detections.bag.bz2").read_bytes()))
    cfg = DatasetConfig(source=bag, camera=root / "cameras.yaml")
    with caplog.at_level(logging.INFO, logger="tagtrail.extract"):
        strict = extract_from(cfg, extract.Params(max_hamming=0))["detections"]
    assert (
        "kept 654 of 772 detections, dropped 110 by max_hamming, 8 by keep_truncated" in caplog.text
    )
    assert "min_decision_margin is not applied to 772 detections" in caplog.text
    every = extract_from(cfg, extract.Params(max_hamming=2))["detections"]
    assert len(strict) == 654 and len(every) == 764
    assert sorted(every["hamming"].unique().tolist()) == [0, 1, 2]
