"""Scene description for the simulator: tags, walls, camera path — plain data.

Scenes are built in a z-up ``scene`` frame with the floor at z = 0; a planar robot path
``(x, y, yaw)`` carries the camera (optical frame: z along the heading, y down). Ground truth is
expressed in ``world`` = the anchor tag's frame: ``world_T_x = inv(scene_T_anchor) @ scene_T_x``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tagtrail.errors import SpecError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.rotations import wrap_angle
from tagtrail.geometry.se3 import compose, inv, make_T

EPOCH_NS = 1_700_000_000 * 1_000_000_000


@dataclass(frozen=True)
class Mount:
    """Camera mount on the robot: height above the floor and offset ahead of the base (m)."""

    height_m: float = 0.17
    forward_m: float = 0.084


@dataclass(frozen=True, eq=False)
class Tag:
    """A tag36h11 tag: id, black-square edge ``size_m`` and its pose ``scene_T_tag`` (4x4)."""

    tag_id: int
    size_m: float
    scene_T_tag: F64


@dataclass(frozen=True, eq=False)
class Wall:
    """A planar quad ``(4, 3)`` in the scene frame, drawn with a flat grey level (0..255)."""

    corners_scene: F64
    gray: int


@dataclass(frozen=True, eq=False)
class Scene:
    """One recording: static tags and walls seen along ``scene_T_cam`` ``(N, 4, 4)`` at ``t_ns``."""

    name: str
    camera: CameraModel
    tags: tuple[Tag, ...]
    walls: tuple[Wall, ...]
    anchor_id: int
    scene_T_cam: F64
    t_ns: np.ndarray
    parked: bool = False
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        ids = [t.tag_id for t in self.tags]
        if len(set(ids)) != len(ids):
            raise SpecError(f"scene {self.name}: duplicate tag ids")
        if self.anchor_id not in ids:
            raise SpecError(f"scene {self.name}: anchor tag {self.anchor_id} is not in the scene")
        if len(self.t_ns) != len(self.scene_T_cam) or len(self.t_ns) == 0:
            raise SpecError(f"scene {self.name}: needs as many stamps as camera poses (>0)")

    @property
    def tag_ids(self) -> np.ndarray:
        return np.array([t.tag_id for t in self.tags], dtype=np.int64)

    @property
    def tag_sizes(self) -> F64:
        return np.array([t.size_m for t in self.tags], dtype=np.float64)

    @property
    def scene_T_tags(self) -> F64:
        return np.stack([t.scene_T_tag for t in self.tags])

    @property
    def world_T_scene(self) -> F64:
        anchor = next(t for t in self.tags if t.tag_id == self.anchor_id)
        return inv(anchor.scene_T_tag)

    def world_T_cam(self) -> F64:
        return compose(self.world_T_scene, self.scene_T_cam)

    def world_T_tags(self) -> F64:
        return compose(self.world_T_scene, self.scene_T_tags)

    def cam_T_tags(self) -> F64:
        """``(N, M, 4, 4)``: every tag in every camera frame."""
        return compose(inv(self.scene_T_cam)[:, None], self.scene_T_tags[None])


def scene_T_cam_planar(xy: F64, yaw: F64, mount: Mount = Mount()) -> F64:
    """Camera poses ``(N, 4, 4)`` of a planar robot at ``xy`` ``(N, 2)`` m, heading ``yaw`` (rad).

    Optical frame: z = heading, x = right of the heading, y = down.
    """
    c, s = np.cos(yaw), np.sin(yaw)
    zeros, ones = np.zeros_like(c), np.ones_like(c)
    x_ax = np.stack([s, -c, zeros], -1)
    y_ax = np.stack([zeros, zeros, -ones], -1)
    z_ax = np.stack([c, s, zeros], -1)
    R = np.stack([x_ax, y_ax, z_ax], -1)
    pos = np.stack(
        [
            xy[:, 0] + mount.forward_m * c,
            xy[:, 1] + mount.forward_m * s,
            np.full_like(c, mount.height_m),
        ],
        -1,
    )
    return make_T(R, pos)


def upright_pose(center: F64, normal_xy: F64) -> F64:
    """``scene_T_x`` of an upright plate at ``center`` (3,) facing the horizontal ``normal_xy``.

    z = the normal (out of the face), y = up, x = y × z (right, as seen facing the plate).
    """
    n = np.array([normal_xy[0], normal_xy[1], 0.0])
    n /= np.linalg.norm(n)
    up = np.array([0.0, 0.0, 1.0])
    return make_T(np.stack([np.cross(up, n), up, n], -1), center)


def wall_quad(p0: F64, p1: F64, height_m: float) -> F64:
    """A vertical wall ``(4, 3)`` standing on the floor segment ``p0 → p1`` (2,) metres."""
    return np.array(
        [
            [p0[0], p0[1], 0.0],
            [p1[0], p1[1], 0.0],
            [p1[0], p1[1], height_m],
            [p0[0], p0[1], height_m],
        ]
    )


def box_walls(
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    height_m: float = 1.2,
    grays: tuple[int, ...] = (178, 160, 186, 168),
) -> tuple[Wall, ...]:
    """The four walls of the rectangular room ``[x0, x1] x [y0, y1]``."""
    pts = [np.array(p, dtype=np.float64) for p in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
    return tuple(
        Wall(wall_quad(pts[i], pts[(i + 1) % 4], height_m), grays[i % len(grays)]) for i in range(4)
    )


def resample_path(poly: F64, n: int, closed: bool) -> tuple[F64, F64, float]:
    """``n`` points evenly spaced by arc length on a dense polyline ``(K, 2)``; headings from the
    local tangent. Returns ``(xy (n, 2), yaw (n,), length_m)``.
    """
    pts = np.vstack([poly, poly[:1]]) if closed else poly
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    length = float(s[-1])
    q = np.linspace(0.0, length, n, endpoint=not closed)
    xy = np.stack([np.interp(q, s, pts[:, 0]), np.interp(q, s, pts[:, 1])], -1)
    h = 1e-3 * length
    if closed:
        qa, qb = (q + h) % length, (q - h) % length
    else:
        qa, qb = np.minimum(q + h, length), np.maximum(q - h, 0.0)
    d = np.stack(
        [
            np.interp(qa, s, pts[:, 0]) - np.interp(qb, s, pts[:, 0]),
            np.interp(qa, s, pts[:, 1]) - np.interp(qb, s, pts[:, 1]),
        ],
        -1,
    )
    return xy, np.arctan2(d[:, 1], d[:, 0]), length


def rounded_rect(x0: float, y0: float, x1: float, y1: float, r: float, k: int = 64) -> F64:
    """Dense counter-clockwise polyline ``(K, 2)`` of a rounded rectangle, starting at the
    middle of its bottom edge."""
    arcs = [
        ((x1 - r, y0 + r), -np.pi / 2),
        ((x1 - r, y1 - r), 0.0),
        ((x0 + r, y1 - r), np.pi / 2),
        ((x0 + r, y0 + r), np.pi),
    ]
    out = [np.array([[(x0 + x1) / 2, y0]])]
    for (cx, cy), a0 in arcs:
        a = a0 + np.linspace(0.0, np.pi / 2, k)
        out.append(np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], -1))
    return np.vstack(out)


def ease_curvature(poly: F64, closed: bool, ramp_m: float, step_m: float = 1e-3) -> F64:
    """The path of a robot that drives ``poly`` ``(K, 2)`` with a finite angular acceleration.

    A path made of straights and arcs (:func:`rounded_rect`) asks the robot to switch its yaw rate
    instantly where they meet; the camera, mounted ahead of the base, would then swing sideways
    and its path get a heading kink of ~10 degrees within a centimetre (at 0.5 m radius) -- which a
    real robot cannot do, and which makes a reference heading there ill-defined. Here the
    curvature (as a function of arc length) is averaged over ``ramp_m``: every straight-arc
    junction becomes a clothoid of length ``ramp_m`` (the yaw rate ramps linearly), the heading
    turns by the same total, and the path is integrated again from its first point. Returns a
    dense polyline ``(M, 2)`` with ``step_m`` spacing (a closed path is made to close exactly by
    spreading its tiny closure error linearly along the loop).
    """
    pts = np.vstack([poly, poly[:1]]) if closed else poly
    length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
    n = max(int(round(length / step_m)), 8)
    xy, yaw, length = resample_path(poly, n, closed)
    ds = length / n if closed else length / (n - 1)
    heading = np.unwrap(yaw)
    kappa = np.diff(heading) / ds  # (n-1,) curvature of each step
    if closed:
        kappa = np.r_[
            kappa,
            wrap_angle(
                heading[0]
                + 2 * np.pi * round((heading[-1] - heading[0]) / (2 * np.pi))
                - heading[-1]
            )
            / ds,
        ]
    w = max(int(round(ramp_m / ds)), 1)
    box = np.ones(w) / w
    if closed:
        padded = np.r_[kappa[-w:], kappa, kappa[:w]]
        kappa = np.convolve(padded, box, mode="same")[w:-w]
    else:
        kappa = np.convolve(
            np.r_[np.full(w, kappa[0]), kappa, np.full(w, kappa[-1])], box, mode="same"
        )[w:-w]
    theta = heading[0] + np.r_[0.0, np.cumsum(kappa)] * ds  # heading at each step's start
    mid = 0.5 * (theta[:-1] + theta[1:])  # midpoint rule: exact on arcs to O(ds^2)
    steps = ds * np.stack([np.cos(mid), np.sin(mid)], -1)
    out: F64 = xy[0] + np.vstack([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
    if closed:
        gap = out[-1] - xy[0]  # the loop's end should meet its start
        out = out[:-1] - np.linspace(0.0, 1.0, len(out))[:-1, None] * gap
    return out


def circle_poly(radius: float, k: int = 720) -> F64:
    """Dense counter-clockwise circle ``(K, 2)`` about the origin, starting at ``(radius, 0)``."""
    a = np.linspace(0.0, 2 * np.pi, k, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a)], -1)


def stamps_ns(n: int, fps: float, epoch_ns: int = EPOCH_NS) -> np.ndarray:
    """``n`` int64 stamps from ``epoch_ns`` at ``fps`` frames per second."""
    return epoch_ns + np.round(np.arange(n) * (1e9 / fps)).astype(np.int64)
