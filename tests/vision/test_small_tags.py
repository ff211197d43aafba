"""``small_tags: redetect`` (issue 12): tags quad_decimate 2 loses, re-detected at full resolution
in crops. Recall only — timing lives in bench/bench_recall.py."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from tagtrail.stages import extract

MODES = {"full": {"quad_decimate": 1.0}, "dec2": {"quad_decimate": 2.0},
         "redetect": {"quad_decimate": 2.0, "small_tags": "redetect"}}


def _detect_all(frames: list[np.ndarray]) -> dict[str, list[tuple[Any, Any]]]:
    from tagtrail.vision.apriltag import detect

    return {m: [detect(f, extract.Params(**o).detector()) for f in frames]
            for m, o in MODES.items()}


@pytest.fixture(scope="module")
def swatbotics(realdata: Path) -> dict[str, list[tuple[Any, Any]]]:
    """72 real photos (816x612) of wall tags, many ~20-40 px."""
    files = sorted((realdata / "swatbotics_mapping_feb_2014" / "images").glob("*.JPG"))
    return _detect_all([cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files])


@pytest.fixture(scope="module")
def rendered() -> dict[str, list[tuple[Any, Any]]]:
    """Frames of the simulator's room loop with 6 cm tags (most ~12-40 px)."""
    from tagtrail.sim.render import Renderer
    from tagtrail.sim.scenarios import SimOptions, room

    opts = SimOptions(tag_size_m=0.06)
    scene = room(opts)[0]
    renderer, rng = Renderer(scene, opts.realism, seed=0), np.random.default_rng(0)
    frames = [cv2.cvtColor(renderer.render(scene.scene_T_cam[i], rng), cv2.COLOR_RGB2GRAY)
              for i in range(0, len(scene.t_ns), 30)]
    return _detect_all(frames)


def _found(dets: list[tuple[Any, Any]]) -> int:
    return sum(len(ints) for ints, _ in dets)


@pytest.mark.parametrize("frames", ["swatbotics", "rendered"])
def test_redetect_finds_what_full_resolution_finds(frames: str, request: Any) -> None:
    res = request.getfixturevalue(frames)
    full, dec2 = res["full"], res["dec2"]
    both = sum(len(set(r[0][:, 0]) & set(f[0][:, 0]))
               for r, f in zip(res["redetect"], full, strict=True))
    assert both >= 0.95 * _found(full)
    assert _found(res["redetect"]) > _found(dec2)
    for ints, _ in res["redetect"]:  # no tag twice in one frame (these scenes' ids are unique)
        assert len(set(ints[:, 0])) == len(ints)


@pytest.mark.parametrize("frames", ["swatbotics", "rendered"])
def test_redetected_corners_agree_with_full_resolution(frames: str, request: Any) -> None:
    """Tags of the decimated pass keep its corners exactly; tags re-detected in a crop get the
    corners full resolution gives them (both re-fitted to the same border edges)."""
    res = request.getfixturevalue(frames)
    diffs = []
    for (ri, rf), (di, df), (fi, ff) in zip(res["redetect"], res["dec2"], res["full"],
                                            strict=True):
        np.testing.assert_array_equal(ri[:len(di)], di)
        np.testing.assert_allclose(rf[:len(di)], df, atol=1e-9)
        for k in range(len(di), len(ri)):
            j = np.flatnonzero(fi[:, 0] == ri[k, 0])
            assert len(j) == 1
            diffs.append(np.abs(rf[k, 1:] - ff[j[0], 1:]).max())
    assert diffs
    # the crop's threshold tiles differ from the full image's: measured median <= 0.03 px,
    # max 0.19 px
    assert np.median(diffs) < 0.05
    assert np.max(diffs) < 0.3


def test_small_tags_is_validated() -> None:
    with pytest.raises(ValueError, match="small_tags"):
        extract.Params(small_tags="on")  # type: ignore[arg-type]
    assert extract.Params().detector().small_tags == extract.Params().small_tags
