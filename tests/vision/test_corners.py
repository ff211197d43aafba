"""Corner re-fit (io.corners) against an exact, independent render (tests/io/exact_tag.py).

The truth is the projection of the tag's corners; the images are rendered by ray tracing
stratified sub-pixel samples, nothing quantized. The detector's corners (pupil-apriltags, −0.5 px
to OpenCV's convention) are the baseline the re-fit must beat.
"""

from __future__ import annotations

import numpy as np
import pytest

from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.se3 import R_from_rotvec, make_T
from tagtrail.vision.corners import refine_corners, refine_many, truncated
from tagtrail.vision.detector import C_LIBRARY_PIXEL_OFFSET
from tests.extracting import extract_from
from tests.sim.helpers import detector
from tests.vision.exact_tag import FISHEYE, LIMO, compose, render_tag, true_corners

SIZE = 0.16


def random_views(n: int, seed: int) -> list[tuple[np.ndarray, int]]:
    """Tags 0.6–2 m away anywhere in the view, tilted up to 45° (roll up to 15°)."""
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(n):
        z = rng.uniform(0.6, 2.0)
        tilt = R_from_rotvec(np.radians(rng.uniform(-45, 45, 3) * [1, 1, 1 / 3]))
        R = R_from_rotvec([np.pi, 0.0, 0.0]) @ tilt  # facing the camera
        t = np.array([rng.uniform(-0.25, 0.25) * z, rng.uniform(-0.15, 0.15) * z, z])
        views.append((make_T(R, t), int(rng.integers(0, 587))))
    return views


def detect_and_refit(camera: CameraModel, noise: float, n: int, seed: int) -> np.ndarray:
    """(views, 2) RMS corner error (px) of the detector and of the re-fit, one row a view."""
    rng = np.random.default_rng(seed + 100)
    errors = []
    for cam_T_tag, tag_id in random_views(n, seed):
        img = render_tag(camera, cam_T_tag, SIZE, tag_id, rng, noise=noise)
        found = [d for d in detector(2.0).detect(img) if d.tag_id == tag_id]
        assert found, f"tag {tag_id} not detected at {cam_T_tag[:3, 3]}"
        raw = found[0].corners - C_LIBRARY_PIXEL_OFFSET
        truth = true_corners(camera, cam_T_tag, SIZE)
        fitted = refine_corners(img, raw, camera)
        errors.append([np.sqrt(np.mean((c - truth) ** 2)) for c in (raw, fitted)])
    return np.array(errors)


@pytest.mark.parametrize("camera", [LIMO, FISHEYE], ids=["plumb_bob", "equidistant"])
def test_refit_is_several_times_closer_to_the_truth(camera: CameraModel) -> None:
    e = detect_and_refit(camera, noise=0.0, n=12, seed=1)
    raw, fit = np.sqrt(np.mean(e**2, axis=0))
    print(f"\ncorner RMS: detector {raw:.4f} px, re-fit {fit:.4f} px")
    assert fit < 0.03 and fit < raw / 2.5  # measured 0.016 vs 0.058 px (K only, 30 views)
    assert e[:, 1].max() < 0.06


@pytest.mark.slow  # 10 rendered views with sensor noise (~5 s): make test-all
def test_refit_with_sensor_noise() -> None:
    e = detect_and_refit(LIMO, noise=2.0, n=10, seed=2)
    raw, fit = np.sqrt(np.mean(e**2, axis=0))
    print(f"\ncorner RMS with noise 2: detector {raw:.4f} px, re-fit {fit:.4f} px")
    assert fit < 0.035 and fit < raw / 1.5


def test_frontal_tag_corners_to_a_hundredth_of_a_pixel() -> None:
    cam_T_tag = make_T(R_from_rotvec([np.pi, 0.0, 0.0]), np.array([0.013, 0.021, 1.0]))
    img = render_tag(LIMO, cam_T_tag, SIZE, 7, np.random.default_rng(0))
    raw = detector(2.0).detect(img)[0].corners - C_LIBRARY_PIXEL_OFFSET
    truth = true_corners(LIMO, cam_T_tag, SIZE)
    assert np.abs(refine_corners(img, raw, LIMO) - truth).max() < 0.01
    assert np.abs(raw - truth).max() > 0.05  # what the detector alone gives here


def edge_offsets(c: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Signed outward offset (px) of each edge of the quad ``c`` ``(4, 2)`` from the true edge
    (mean of its end corners' distances from the true line)."""
    a, b = truth, np.roll(truth, -1, axis=0)
    d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    n = np.stack([d[:, 1], -d[:, 0]], axis=1)
    n *= np.sign(np.einsum("ki,ki->k", n, a - truth.mean(axis=0)))[:, None]
    return 0.5 * (np.einsum("ki,ki->k", c - a, n) + np.einsum("ki,ki->k", np.roll(c, -1, 0) - a, n))


@pytest.mark.parametrize("background", [90.0, 236.0])
def test_blurred_small_tags_are_not_pulled_by_the_neighbouring_edges(background: float) -> None:
    """1 px blur on 3.4 px cells: the border's inner edge and the quiet zone's outer edge reach
    into the gradient's band. Before their profile was modelled (vision.corners' neighbour
    model) they moved the edges by a bias set by what lies beyond the quiet zone and by the
    data bits, which frames cannot average away: here mean -0.036 px on a dark background,
    +0.048 px on a white one, edges RMS 0.068 px; since: -0.001 / +0.003 px, RMS 0.021 /
    0.023 px."""
    rng = np.random.default_rng(11)
    offsets = []
    for tag_id, dx in [(0, 0.0), (7, 0.013), (13, 0.027), (21, 0.005), (7, 0.021), (0, 0.009)]:
        cam_T_tag = make_T(R_from_rotvec([np.pi, 0.0, 0.0]), np.array([dx, 0.02 + dx, 2.6]))
        img = render_tag(LIMO, cam_T_tag, SIZE, tag_id, rng, ss=6, blur=1.0, background=background)
        found = [d for d in detector(2.0).detect(img) if d.tag_id == tag_id]
        assert found
        fitted = refine_corners(img, found[0].corners - C_LIBRARY_PIXEL_OFFSET, LIMO)
        offsets.append(edge_offsets(fitted, true_corners(LIMO, cam_T_tag, SIZE)))
    e = np.array(offsets)
    rms = np.sqrt(np.mean(e**2))
    print(f"\nbackground {background:.0f}: mean {e.mean():+.4f} px, RMS {rms:.4f}")
    assert abs(e.mean()) < 0.03
    assert rms < 0.05


def test_oblique_tags_with_narrow_cells_are_refitted() -> None:
    """A tag turned 55 deg about its vertical axis 2.4 m away: its cells are ~2.2 px across the
    foreshortened edges (MIN_CELL_PX applies to the shortest side). Left to the detector before
    (cells under 2.5 px were not re-fitted): edge offsets RMS 0.107 px, -0.10 / -0.10 / +0.03 /
    +0.11 px edge by edge (a bias every frame repeats); re-fitted, the neighbouring edges
    modelled: 0.033 px."""
    rng = np.random.default_rng(12)
    offsets, before = [], []
    for tag_id, dx in [(0, 0.0), (7, 0.011), (13, 0.023), (0, 0.017), (7, 0.005)]:
        R = R_from_rotvec([np.pi, 0.0, 0.0]) @ R_from_rotvec([0.0, np.radians(55.0), 0.0])
        cam_T_tag = make_T(R, np.array([dx - 0.1, 0.02, 2.4]))
        img = render_tag(LIMO, cam_T_tag, SIZE, tag_id, rng, ss=6, background=170.0)
        found = [d for d in detector(2.0).detect(img) if d.tag_id == tag_id]
        assert found
        raw = found[0].corners - C_LIBRARY_PIXEL_OFFSET
        fitted = refine_corners(img, raw, LIMO)
        assert not np.array_equal(fitted, raw)
        offsets.append(edge_offsets(fitted, true_corners(LIMO, cam_T_tag, SIZE)))
        before.append(edge_offsets(raw, true_corners(LIMO, cam_T_tag, SIZE)))
    rms = np.sqrt(np.mean(np.square(offsets)))
    print(
        f"\noblique 55 deg: edge offsets RMS {rms:.4f} px, the detector's "
        f"{np.sqrt(np.mean(np.square(before))):.4f} px, mean {np.mean(before, axis=0)}"
    )
    assert rms < 0.05


def test_unreliable_or_degenerate_input_keeps_the_corners() -> None:
    img = np.full((480, 640), 128, dtype=np.uint8)
    quad = np.array([[100.0, 100.0], [160.0, 100.0], [160.0, 160.0], [100.0, 160.0]])
    # flat image: no edge support -> unchanged
    assert np.array_equal(refine_corners(img, quad, LIMO), quad)
    tiny = quad * 0.1 + 300  # 6 px tag: cells under MIN_CELL_PX
    assert np.array_equal(refine_corners(img, tiny, None), tiny)
    nan = quad.copy()
    nan[2, 0] = np.nan
    assert np.array_equal(refine_corners(img, nan, LIMO), nan, equal_nan=True)
    off = quad + [600.0, 0.0]  # mostly outside the image
    assert np.array_equal(refine_corners(img, off, LIMO), off)
    assert refine_corners(img, np.zeros((0, 4, 2)), LIMO).shape == (0, 4, 2)


def test_batch_equals_one_at_a_time() -> None:
    rng = np.random.default_rng(3)
    (T1, id1), (T2, id2) = random_views(2, seed=3)
    T1[:3, 3], T2[:3, 3] = [-0.35, 0.0, 1.2], [0.35, 0.05, 1.4]  # side by side
    img = compose([render_tag(LIMO, T1, SIZE, id1, rng), render_tag(LIMO, T2, SIZE, id2, rng)])
    dets = [d for d in detector(2.0).detect(img) if d.tag_id in (id1, id2)]
    assert len(dets) == 2
    raw = np.array([d.corners - C_LIBRARY_PIXEL_OFFSET for d in dets])
    batch = refine_corners(img, raw, LIMO)
    assert batch.shape == raw.shape
    for k in range(len(raw)):
        np.testing.assert_allclose(batch[k], refine_corners(img, raw[k], LIMO), atol=1e-9)


def test_truncated_tags_are_the_ones_whose_quiet_zone_leaves_the_image() -> None:
    quad = np.array([[100.0, 100.0], [180.0, 100.0], [180.0, 180.0], [100.0, 180.0]])  # 10 px cells
    assert not truncated(quad, 640, 480)[0]
    assert not truncated(quad - 90.4, 640, 480)[0]  # quiet zone ends at -0.4: inside
    assert truncated(quad - 90.7, 640, 480)[0]  # ... at -0.7: cut
    assert truncated(quad + [455.0, 0.0], 640, 480)[0]  # right quiet zone at 645
    assert truncated(quad + [0.0, 295.0], 640, 480)[0]  # bottom
    nan = quad.copy()
    nan[0, 0] = np.nan
    np.testing.assert_array_equal(truncated(np.stack([quad, nan]), 640, 480), [False, True])


def test_detector_drops_a_tag_cut_by_the_border_unless_asked() -> None:
    from dataclasses import replace

    from tagtrail.stages import extract
    from tagtrail.vision.apriltag import detect

    # a tag whose right quiet zone runs ~3 px off the image (black square 5 px inside)
    cam_T_tag = make_T(R_from_rotvec([np.pi, 0.0, 0.0]), np.array([0.62, 0.0, 1.0]))
    img = render_tag(LIMO, cam_T_tag, SIZE, 5, np.random.default_rng(0), ss=4)
    assert truncated(true_corners(LIMO, cam_T_tag, SIZE), 640, 480)[0]
    assert [d.tag_id for d in detector(2.0).detect(img)] == [5]  # the detector still finds it
    cfg = extract.Params(min_decision_margin=0).detector()
    assert len(detect(img, cfg)[0]) == 0
    assert detect(img, replace(cfg, keep_truncated=True))[0][:, 0].tolist() == [5]


def test_frames_batched_equal_frames_one_at_a_time() -> None:
    rng = np.random.default_rng(4)
    grays, raws = [], []
    for cam_T_tag, tag_id in random_views(3, seed=4):
        img = render_tag(LIMO, cam_T_tag, SIZE, tag_id, rng, ss=4)
        grays.append(img)
        raws.append(
            np.array(
                [d.corners - C_LIBRARY_PIXEL_OFFSET for d in detector(2.0).detect(img)]
            ).reshape(-1, 4, 2)
        )
    grays.insert(1, grays[0])
    raws.insert(1, np.zeros((0, 4, 2)))  # a frame without tags
    batch = refine_many(grays, raws, LIMO)
    assert [b.shape for b in batch] == [r.shape for r in raws]
    for gray, raw, b in zip(grays, raws, batch, strict=True):
        np.testing.assert_allclose(b, refine_corners(gray, raw, LIMO), atol=1e-9)
    assert refine_many([], [], LIMO) == []


def test_extract_drops_cut_tags_says_so_and_refits_the_rest(
    tmp_path, caplog: pytest.LogCaptureFixture
) -> None:
    """Stage extract on an image folder: a whole tag (re-fitted, ~0.01 px) and a cut one."""
    import logging

    import cv2
    import yaml

    from tagtrail.schemas.pipeline import DatasetConfig
    from tagtrail.stages import extract

    rng = np.random.default_rng(5)
    whole = make_T(R_from_rotvec([np.pi, 0.2, 0.0]), np.array([-0.2, 0.05, 1.1]))
    cut = make_T(R_from_rotvec([np.pi, 0.0, 0.0]), np.array([0.62, 0.0, 1.0]))
    img = compose([render_tag(LIMO, whole, SIZE, 3, rng), render_tag(LIMO, cut, SIZE, 5, rng)])
    cv2.imwrite(str(tmp_path / "frame0.png"), img)
    K = LIMO.K
    (tmp_path / "camera.yaml").write_text(
        yaml.safe_dump(
            {
                "camera": {
                    "width": 640,
                    "height": 480,
                    "fx": float(K[0, 0]),
                    "fy": float(K[1, 1]),
                    "cx": float(K[0, 2]),
                    "cy": float(K[1, 2]),
                    "distortion": LIMO.D.tolist(),
                }
            }
        )
    )
    src = DatasetConfig(source=tmp_path)
    with caplog.at_level(logging.INFO, logger="tagtrail.extract"):
        det = extract_from(src, extract.Params(workers=1))["detections"]
    assert det["tag_id"].tolist() == [3]
    assert "kept 1 of 2 detections, dropped 1 by keep_truncated" in caplog.text
    corners = det[[f"c{k}{a}" for k in range(4) for a in "xy"]].to_numpy().reshape(4, 2)
    assert np.abs(corners - true_corners(LIMO, whole, SIZE)).max() < 0.03
    kept = extract_from(src, extract.Params(workers=1, keep_truncated=True))["detections"]
    assert sorted(kept["tag_id"].tolist()) == [3, 5]


def test_edges_alone_refit_at_a_tenth_of_the_time() -> None:
    """``refit_corners: edges`` (live nodes at frame rate): the gradient fit without the
    intensity-profile model. On sharp renders it is as close to the truth as the full re-fit
    (the model matters under blur: the test above) and far closer than the detector; it skips
    the model's work (~90 % of the full re-fit's time, bench: 1.2 vs 17.7 ms a frame of ~5
    tags)."""
    rng = np.random.default_rng(5)
    views = random_views(8, seed=3)
    imgs, raws, truths = [], [], []
    for cam_T_tag, tag_id in views:
        img = render_tag(LIMO, cam_T_tag, SIZE, tag_id, rng)
        found = [d for d in detector(2.0).detect(img) if d.tag_id == tag_id]
        assert found
        imgs.append(img)
        raws.append(found[0].corners[None] - C_LIBRARY_PIXEL_OFFSET)
        truths.append(true_corners(LIMO, cam_T_tag, SIZE))
    full = refine_many(imgs, raws, LIMO)
    edges = refine_many(imgs, raws, LIMO, model=False)
    rms = {
        name: float(np.sqrt(np.mean([(c[0] - t) ** 2 for c, t in zip(got, truths, strict=True)])))
        for name, got in (("detector", raws), ("edges", edges), ("full", full))
    }
    print(f"\ncorner RMS px: {rms}")
    assert rms["edges"] < 0.03 and rms["edges"] < rms["detector"] / 2.5
    assert not all(np.array_equal(a, b) for a, b in zip(full, edges, strict=True))
