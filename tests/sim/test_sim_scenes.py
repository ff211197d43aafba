"""Scenario geometry (tag counts, visibility, parked poses, frames) and renderer details."""

from __future__ import annotations

import numpy as np
import pytest

from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.se3 import inv, make_T
from tagtrail.sim.camera import limo_camera, tag_visibility
from tagtrail.sim.render import Realism, Renderer, clip_near
from tagtrail.sim.scenarios import ROOM_QUERIES, SimOptions, build
from tagtrail.sim.scene import (
    Scene,
    Tag,
    ease_curvature,
    resample_path,
    rounded_rect,
    stamps_ns,
    upright_pose,
)
from tests.sim.helpers import detector

OPTS = SimOptions()


def _visible(scene: Scene) -> np.ndarray:
    return tag_visibility(
        scene.camera, scene.cam_T_tags(), scene.tag_sizes, max_range_m=OPTS.max_range_m
    ).visible


def test_circle_has_24_tags_and_sees_two_or_more() -> None:
    (scene,) = build("circle", OPTS)
    assert len(scene.tags) == 24 and scene.anchor_id == 0
    assert 600 <= len(scene.t_ns) <= 1000
    assert (_visible(scene).sum(axis=1) >= 2).mean() > 0.9


def test_room_reference_and_parked_queries() -> None:
    ref, *queries = build("room", OPTS)
    assert 12 <= len(ref.tags) <= 20 and 600 <= len(ref.t_ns) <= 1000
    vis = _visible(ref)
    assert (vis.sum(axis=1) >= 2).mean() > 0.9 and vis.any(axis=0).all()
    loop, yaw_loop, _ = resample_path(rounded_rect(1.0, 1.0, 4.0, 3.0, 0.5), 4000, True)
    assert [q.name for q in queries] == ["query_1", "query_2", "query_3"]
    for q, (_, _, turn) in zip(queries, ROOM_QUERIES, strict=True):
        assert q.parked and 20 <= len(q.t_ns) <= 40
        assert np.ptp(q.scene_T_cam, axis=0).max() == 0  # static
        base = q.scene_T_cam[0, :2, 3] - OPTS.mount.forward_m * q.scene_T_cam[0, :2, 2]
        assert 0.2 <= np.linalg.norm(loop - base, axis=1).min() <= 0.5
        assert 3 <= abs(turn) <= 30
        assert _visible(q)[0].sum() >= 2
        assert q.t_ns[0] > ref.t_ns[-1]


def test_room_loop_has_no_heading_kinks() -> None:
    """The robot's yaw rate ramps in and out of the corners (finite angular acceleration), so
    the camera, mounted ahead of the base, does not swing sideways: its path heading changes by
    at most its turn rate (0.6 rad/s at 0.3 m/s on 0.5 m corners, ~1.15 deg per frame) plus a
    little, never the ~5 deg per frame of a straight-arc junction taken instantly."""
    ref = build("room", OPTS)[0]
    p = ref.world_T_cam()[:, [0, 2], 3]
    step = np.diff(np.vstack([p, p[:1]]), axis=0)
    heading = np.degrees(np.arctan2(step[:, 1], step[:, 0]))
    turn = (np.diff(np.r_[heading, heading[:1]]) + 180.0) % 360.0 - 180.0
    assert np.abs(turn).max() < 1.6 and abs(turn.sum()) == pytest.approx(360.0, abs=1e-6)
    raw = rounded_rect(1.0, 1.0, 4.0, 3.0, 0.5)
    dense, _, length = resample_path(raw, 5000, True)
    eased = ease_curvature(raw, True, 0.2)
    _, _, eased_length = resample_path(eased, 20000, True)
    assert np.linalg.norm(eased[::20, None] - dense[None], axis=2).min(axis=1).max() < 0.01
    assert np.linalg.norm(eased[-1] - eased[0]) < 2e-3 and eased_length == pytest.approx(
        length, abs=0.01
    )


def test_corridor_sees_one_or_two_tags_and_stays_connected() -> None:
    (scene,) = build("corridor", OPTS)
    vis = _visible(scene)
    n = vis.sum(axis=1)
    assert ((n >= 1) & (n <= 2)).mean() > 0.9 and n.max() <= 2
    co = vis.T.astype(int) @ vis.astype(int)
    assert all(co[i, i + 1] >= 10 for i in range(len(scene.tags) - 1))  # chain of co-visibility


def test_world_is_the_anchor_frame_with_the_floor_as_its_xz_plane() -> None:
    for name in ("circle", "room", "corridor", "hall"):
        scene = build(name, SimOptions(frames=50))[0]
        world_T_cam = scene.world_T_cam()
        # camera y (down) is world -y: the anchor tag is upright, so world y is "up"
        np.testing.assert_allclose(world_T_cam[:, :3, 1], np.tile([0, -1, 0], (50, 1)), atol=1e-12)
        assert np.ptp(world_T_cam[:, 1, 3]) < 1e-12  # constant height
        anchor = scene.tag_ids.tolist().index(scene.anchor_id)
        np.testing.assert_allclose(scene.world_T_tags()[anchor], np.eye(4), atol=1e-12)


def test_frames_fps_speed() -> None:
    (a,) = build("corridor", SimOptions(speed_mps=0.6, fps=10))
    assert len(a.t_ns) == pytest.approx(12.0 / 0.6 * 10, abs=2)
    assert np.all(np.diff(a.t_ns) == 100_000_000)
    (b,) = build("corridor", SimOptions(frames=7))
    assert len(b.t_ns) == 7


def test_near_plane_clipping() -> None:
    poly = np.array([[0.0, 0, -1], [1, 0, -1], [1, 0, 1], [0, 0, 1]])
    clipped = clip_near(poly, 0.05)
    assert clipped[:, 2].min() == pytest.approx(0.05) and len(clipped) == 4
    # A 1 m tag beside the camera, half behind it: only the half in front may be drawn, on the
    # right of the image; rays of the left half would hit the plane behind the camera.
    cam = limo_camera()
    scene_T_cam = make_T(np.eye(3), np.zeros(3))  # the scene frame is the optical frame here
    R_tag = np.column_stack([[0, 0, -1.0], [0, -1.0, 0], [-1.0, 0, 0]])  # faces -x: us
    tag = Tag(0, 0.8, make_T(R_tag, [0.3, 0.0, 0.05]))
    scene = Scene("clip", cam, (tag,), (), 0, scene_T_cam[None], stamps_ns(1, 30))
    r = Renderer(scene, Realism(0, 0, 1, 1, 0))
    empty = Renderer(
        Scene(
            "none",
            cam,
            (Tag(1, 0.1, make_T(np.eye(3), [0, 0, -5])),),
            (),
            1,
            scene_T_cam[None],
            stamps_ns(1, 30),
        ),
        Realism(0, 0, 1, 1, 0),
    )
    diff = r.render_ideal(scene_T_cam) != empty.render_ideal(scene_T_cam)
    cols = np.flatnonzero(diff.any(axis=0)) - r.offset[0]
    fx, cx = cam.K[0, 0], cam.K[0, 2]
    assert diff.any() and cols.min() > cx + fx * 0.3 / 0.6  # front part: z < 0.55


def test_texture_orientation_and_corner_order() -> None:
    """A frontal tag: detector corner 0 is bottom-left, 1 bottom-right (SPEC tag frame)."""
    cam = limo_camera()
    R_tag = np.diag([1.0, -1.0, -1.0])  # tag x = camera x, tag y = up, tag z towards camera
    tag = Tag(7, 0.16, make_T(R_tag, [0.0, 0.0, 0.8]))
    scene = Scene("one", cam, (tag,), (), 7, np.eye(4)[None], stamps_ns(1, 30))
    img = Renderer(scene, Realism(0, 0, 1, 1, 0)).render(np.eye(4))
    (d,) = detector(1.0).detect(np.ascontiguousarray(img[..., 0]))
    assert d.tag_id == 7 and d.hamming == 0
    c = d.corners
    assert c[0, 0] < c[1, 0] and c[0, 1] > c[3, 1]  # 0 left of 1, 0 below 3 (image y down)
    expect = tag_visibility(
        cam, inv(np.eye(4))[None, None] @ tag.scene_T_tag[None, None], np.array([0.16])
    ).corners_px[0, 0]
    np.testing.assert_allclose(c - 0.5, expect, atol=0.3)


LENSES = {
    "rational_polynomial": [0.3, -0.1, 0.002, -0.001, 0.02, 0.1, 0.01, 0.0],
    "equidistant": [0.3, 0.05, -0.02, 0.0],
}


@pytest.mark.parametrize("model", ["plumb_bob", *LENSES])
def test_rendered_corners_follow_the_camera_model(model: str) -> None:
    """Off-centre tag: detected corners are where ``tag_visibility`` projects them, whatever
    the distortion model (and not where a distortion-free camera would)."""
    limo = limo_camera()
    cam = limo if model == "plumb_bob" else CameraModel(640, 480, limo.K, LENSES[model], model)
    R_tag = np.diag([1.0, -1.0, -1.0])
    tag = Tag(3, 0.16, make_T(R_tag, [0.32, 0.2, 0.7]))
    scene = Scene("one", cam, (tag,), (), 3, np.eye(4)[None], stamps_ns(1, 30))
    img = Renderer(scene, Realism(0, 0, 1, 1, 0)).render(np.eye(4))
    (d,) = detector(1.0).detect(np.ascontiguousarray(img[..., 0]))
    vis = tag_visibility(cam, tag.scene_T_tag[None, None], np.array([0.16]))
    assert vis.visible[0, 0] and d.tag_id == 3
    np.testing.assert_allclose(d.corners - 0.5, vis.corners_px[0, 0], atol=0.3)
    pinhole = CameraModel(640, 480, limo.K, [], "none")
    assert (
        np.abs(
            tag_visibility(pinhole, tag.scene_T_tag[None, None], np.array([0.16])).corners_px[0, 0]
            - vis.corners_px[0, 0]
        ).max()
        > 2.0
    )


def test_upright_pose_axes() -> None:
    T = upright_pose(np.array([1.0, 2.0, 0.3]), np.array([-1.0, 0.0]))
    np.testing.assert_allclose(
        T[:3, :3], np.column_stack([[0, -1, 0], [0, 0, 1], [-1, 0, 0]]), atol=1e-12
    )
