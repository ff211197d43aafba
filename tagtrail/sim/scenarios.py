"""The simulator's scenarios: each builds the scenes (one per recording) it writes.

``circle``: 24 tags on a ring (r = 2.3 m) around a circular path (r = 1.5 m), the paper's
simulation experiment. ``room``: a closed loop in a 5 x 4 m room with 18 wall tags (``reference``)
plus three parked queries ``query_1..3``. ``corridor``: a 15 m corridor with tags on boards,
one or two in view at a time. ``hall``: a 14 x 2.4 m hall with tags flat on both walls (seen
obliquely, one to three at a time), driven out and back with a U-turn. ``corridor_gap``: the
corridor with a blank stretch of wall (~5 s without a tag in view); ``room_blank_turn``: the
room's loop with a bare west wall (~2 s without a tag while turning): odometry's test scenes.
``observations``: the circle's tags and path, written as camera-to-tag observations instead of
images. The anchor (default: the first tag) is upright on a wall/board, so the floor is the x–z
plane of ``world``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from tagtrail.errors import SpecError
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.camera import CameraModel
from tagtrail.sim.camera import limo_camera
from tagtrail.sim.odometry import Slip
from tagtrail.sim.render import Realism, tag_bits
from tagtrail.sim.scene import (
    EPOCH_NS,
    Mount,
    Scene,
    Tag,
    Wall,
    box_walls,
    circle_poly,
    ease_curvature,
    resample_path,
    rounded_rect,
    scene_T_cam_planar,
    stamps_ns,
    upright_pose,
)
from tagtrail.stages import pnp

SCENARIOS = (
    "circle",
    "room",
    "corridor",
    "hall",
    "corridor_gap",
    "room_blank_turn",
    "observations",
)
RECORDINGS = {
    "circle": ("circle",),
    "room": ("reference", "query_1", "query_2", "query_3"),
    "corridor": ("corridor",),
    "hall": ("hall",),
    "corridor_gap": ("corridor_gap",),
    "room_blank_turn": ("room_blank_turn",),
    "observations": ("observations",),
}
# Parked test poses of the room: (fraction of the loop, offset to the left m, turn deg).
ROOM_QUERIES = ((0.08, 0.30, 12.0), (0.45, 0.30, -20.0), (0.70, 0.45, 30.0))
QUERY_EPOCH_STEP_NS = 3600 * 1_000_000_000  # queries are "later sessions", an hour apart
# The room loop's straight-arc junctions are eased over this arc length (the robot's yaw rate
# ramps up in ~0.7 s at 0.3 m/s instead of jumping): see scene.ease_curvature.
ROOM_CURVATURE_RAMP_M = 0.2
# corridor_gap: the first board after the blank stretch (the last before it is at 7.6 m).
GAP_NEXT_X_M = 11.8
# ... and its boards are turned less towards the robot than the corridor's 50°: seen from afar
# too obliquely to be detected, they come into view at ~3 m (no stray far detection in the gap).
GAP_TURN_DEG = 15.0
# The stretches without a tag in view, (start, end) s after the first frame at the default
# options (0.3 m/s, 30 fps, seed 0). Measured with the renderer and the pipeline's extract
# (quad_decimate 2): corridor_gap 5.57 s of frames with no detection from 20.83 s, then sparse
# far detections; room_blank_turn 2.23 s from 17.83 s (the heading turns ~55° in it). With
# --detections (the visibility model: 3.5 m, 65°) the same stretches are 7.7 s and 2.2 s.
BLANK_STRETCH_S = {"corridor_gap": (20.9, 26.2), "room_blank_turn": (17.9, 20.0)}
# room_blank_turn: where the north (y = 4) and south (y = 0) walls carry their tags.
BLANK_TURN_NORTH_X_M = (4.1, 3.1, 2.1, 1.1, 0.15)
BLANK_TURN_SOUTH_X_M = (0.8, 1.8, 2.8, 3.8, 4.7)


@dataclass(frozen=True)
class SimOptions:
    """Everything a simulation run can be told (units in the names; see ``tagtrail simulate``)."""

    frames: int | None = None  # frames of a moving recording; None: path length / speed * fps
    fps: float = 30.0
    speed_mps: float = 0.3
    query_frames: int = 30
    tag_size_m: float = pnp.Params().tag_size  # the pipeline's default: it measures them right
    tag_sizes_m: Mapping[int, float] = field(default_factory=dict)
    tag_ids: tuple[int, ...] | None = None  # relabel the scenario's tags, in layout order
    anchor_id: int | None = None  # default: the first tag
    camera: CameraModel = field(default_factory=limo_camera)
    mount: Mount = Mount()
    storage: str = "mcap"
    compressed: bool = False
    jpeg_quality: int = 90
    detections: bool = False
    seed: int = 0
    noise_t_m: float = 0.0  # observations: std of translation noise, per axis
    noise_r_deg: float = 0.0  # observations: std of rotation noise, per axis
    corner_noise_px: float = 0.3  # --detections: std of corner noise, per coordinate
    max_range_m: float = 3.5  # detections/observations: farthest tag reported
    max_incidence_deg: float = 65.0
    realism: Realism = Realism()
    odom: bool | None = None  # write /odom + /tf_static; None: yes for bags, no for observations
    odom_scale_error: float | None = None  # both wheels' scale error; None: drawn 1-3 % per wheel
    odom_slip: tuple[float, float, float] | None = None  # (start_s, duration_s, fraction)
    force: bool = False
    progress: bool = False

    def __post_init__(self) -> None:
        checks = {
            "fps": self.fps > 0,
            "speed": self.speed_mps > 0,
            "query-frames": self.query_frames > 0,
            "frames": self.frames is None or self.frames >= 2,
            "tag-size": self.tag_size_m > 0 and all(v > 0 for v in self.tag_sizes_m.values()),
            "storage": self.storage in ("mcap", "sqlite3"),
            "jpeg-quality": 1 <= self.jpeg_quality <= 100,
            "noise-t": self.noise_t_m >= 0,
            "noise-r-deg": self.noise_r_deg >= 0,
            "corner-noise": self.corner_noise_px >= 0,
            "max-range": self.max_range_m > 0,
            "max-incidence": 0 < self.max_incidence_deg < 90,
            "odom-scale-error": self.odom_scale_error is None
            or abs(self.odom_scale_error) < 0.5,  # NaN fails too
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise SpecError(f"invalid simulate option(s): {', '.join('--' + b for b in bad)}")
        if self.compressed and self.detections:
            raise SpecError("--compressed and --detections exclude each other")
        if self.odom_slip is not None:
            Slip(*self.odom_slip)  # raises SpecError

    def slip(self) -> Slip | None:
        """The ``--odom-slip`` stretch, if any."""
        return None if self.odom_slip is None else Slip(*self.odom_slip)

    def to_dict(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "fps": self.fps,
            "speed_mps": self.speed_mps,
            "query_frames": self.query_frames,
            "storage": self.storage,
            "compressed": self.compressed,
            "detections": self.detections,
            "seed": self.seed,
            "noise_t_m": self.noise_t_m,
            "noise_r_deg": self.noise_r_deg,
            "corner_noise_px": self.corner_noise_px,
            "max_range_m": self.max_range_m,
            "max_incidence_deg": self.max_incidence_deg,
            "mount": {"height_m": self.mount.height_m, "forward_m": self.mount.forward_m},
            "realism": {k: float(v) for k, v in vars(self.realism).items()},
            "odom": self.odom,
            "odom_scale_error": self.odom_scale_error,
            "odom_slip": None if self.odom_slip is None else list(self.odom_slip),
        }


def _tags(poses: list[F64], opts: SimOptions) -> tuple[tuple[Tag, ...], int]:
    ids = list(opts.tag_ids) if opts.tag_ids is not None else list(range(len(poses)))
    if len(ids) != len(poses):
        raise SpecError(f"this scenario has {len(poses)} tags; --tag-ids gave {len(ids)}")
    for i in ids:
        tag_bits(i)  # raises SpecError for ids outside tag36h11
    anchor = ids[0] if opts.anchor_id is None else opts.anchor_id
    if anchor not in ids:
        raise SpecError(f"--anchor {anchor} is not one of the scenario's tags {ids}")
    unknown = sorted(set(opts.tag_sizes_m) - set(ids))
    if unknown:
        raise SpecError(f"--tag-sizes names tags {unknown} that are not in the scenario")
    tags = tuple(
        Tag(int(i), float(opts.tag_sizes_m.get(i, opts.tag_size_m)), P)
        for i, P in zip(ids, poses, strict=True)
    )
    return tags, int(anchor)


def _moving(
    name: str,
    poly: F64,
    closed: bool,
    tags: tuple[Tag, ...],
    walls: tuple[Wall, ...],
    anchor: int,
    opts: SimOptions,
    info: dict[str, Any],
) -> Scene:
    _, _, length = resample_path(poly, 2, closed)
    n = opts.frames or max(2, int(round(length / opts.speed_mps * opts.fps)))
    xy, yaw, _ = resample_path(poly, n, closed)
    info = {**info, "path_length_m": length, "frames": n}
    return Scene(
        name,
        opts.camera,
        tags,
        walls,
        anchor,
        scene_T_cam_planar(xy, yaw, opts.mount),
        stamps_ns(n, opts.fps),
        info=info,
    )


def circle(opts: SimOptions, name: str = "circle") -> list[Scene]:
    """24 tags on a ring of radius 2.3 m, each turned 45° from the centre towards the oncoming
    robot, which drives counter-clockwise on a circle of radius 1.5 m."""
    beta = np.radians(45.0)
    poses = []
    for i, a in enumerate(np.radians(np.arange(24) * 15.0)):
        rad, tan = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        centre = np.array([2.3 * rad[0], 2.3 * rad[1], 0.30 + 0.06 * (i % 2)])
        poses.append(upright_pose(centre, -np.cos(beta) * rad - np.sin(beta) * tan))
    tags, anchor = _tags(poses, opts)
    walls = box_walls(-4.0, -4.0, 4.0, 4.0, height_m=2.5)
    info = {"scenario": "circle", "path_radius_m": 1.5, "tag_ring_radius_m": 2.3}
    return [_moving(name, circle_poly(1.5), True, tags, walls, anchor, opts, info)]


def _room_tags(width: float, depth: float) -> list[F64]:
    # Counter-clockwise from the east wall (x = width): 4, 5, 4, 5 tags, heights 0.30-0.46 m.
    sides = [
        ((width, 0.0), (width, depth), (-1.0, 0.0), 4),
        ((width, depth), (0.0, depth), (0.0, -1.0), 5),
        ((0.0, depth), (0.0, 0.0), (1.0, 0.0), 4),
        ((0.0, 0.0), (width, 0.0), (0.0, 1.0), 5),
    ]
    poses: list[F64] = []
    for p0, p1, normal, k in sides:
        a, b = np.array(p0), np.array(p1)
        for j in range(k):
            c = a + (b - a) * (j + 0.5) / k
            poses.append(
                upright_pose(
                    np.array([c[0], c[1], 0.30 + 0.08 * (len(poses) % 3)]), np.array(normal)
                )
            )
    return poses


def room(opts: SimOptions) -> list[Scene]:
    """A 5 x 4 m room, 18 wall tags, a rounded-rectangle loop (``reference``, ~9.1 m; corners of
    radius 0.5 m entered and left along 0.2 m clothoids) and three parked test poses off the loop
    (``query_1..3``)."""
    tags, anchor = _tags(_room_tags(5.0, 4.0), opts)
    walls = box_walls(0.0, 0.0, 5.0, 4.0, height_m=2.5)
    poly = ease_curvature(rounded_rect(1.0, 1.0, 4.0, 3.0, 0.5), True, ROOM_CURVATURE_RAMP_M)
    info = {"scenario": "room", "room_m": [5.0, 4.0]}
    scenes = [_moving("reference", poly, True, tags, walls, anchor, opts, info)]
    xy, yaw, _ = resample_path(poly, 2000, True)
    for q, (frac, offset, turn) in enumerate(ROOM_QUERIES, start=1):
        k = int(frac * len(xy))
        left = np.array([-np.sin(yaw[k]), np.cos(yaw[k])])
        p, h = xy[k] + offset * left, yaw[k] + np.radians(turn)
        T = scene_T_cam_planar(p[None], np.array([h]), opts.mount)
        n = opts.query_frames
        qinfo = {
            **info,
            "query": q,
            "loop_fraction": frac,
            "offset_left_m": offset,
            "turn_deg": turn,
            "frames": n,
        }
        scenes.append(
            Scene(
                f"query_{q}",
                opts.camera,
                tags,
                walls,
                anchor,
                np.repeat(T, n, axis=0),
                stamps_ns(n, opts.fps, EPOCH_NS + q * QUERY_EPOCH_STEP_NS),
                parked=True,
                info=qinfo,
            )
        )
    return scenes


def corridor(opts: SimOptions) -> list[Scene]:
    """A 15 x 2 m corridor, 9 tags on boards alternating left/right every 1.4 m, turned 50° from
    the wall towards the oncoming robot; the robot drives 12 m along it with a slight weave, and
    sees one or two tags at a time (consecutive tags are co-visible for ~1 s)."""
    beta = np.radians(50.0)
    poses = []
    for i in range(9):
        side = 1.0 if i % 2 == 0 else -1.0
        normal = np.cos(beta) * np.array([0.0, -side]) + np.sin(beta) * np.array([-1.0, 0.0])
        poses.append(upright_pose(np.array([2.0 + 1.4 * i, 0.9 * side, 0.32]), normal))
    tags, anchor = _tags(poses, opts)
    walls = box_walls(-0.5, -1.0, 14.5, 1.0, height_m=2.5)
    x = np.linspace(0.0, 12.0, 1200)
    poly = np.stack([x, 0.04 * np.sin(2 * np.pi * x / 6.0)], -1)
    info = {"scenario": "corridor", "corridor_m": [15.0, 2.0]}
    return [_moving("corridor", poly, False, tags, walls, anchor, opts, info)]


def _corridor_tag(x: float, side: float, turn_deg: float = 50.0) -> F64:
    """A corridor board tag at ``x`` on the ``side`` (+1 left, -1 right) wall, turned
    ``turn_deg`` from the wall towards the oncoming robot."""
    beta = np.radians(turn_deg)
    normal = np.cos(beta) * np.array([0.0, -side]) + np.sin(beta) * np.array([-1.0, 0.0])
    return upright_pose(np.array([x, 0.9 * side, 0.32]), normal)


def corridor_gap(opts: SimOptions) -> list[Scene]:
    """Odometry across a gap: the corridor's boards (1.4 m apart, alternating sides) with a blank
    stretch of wall mid-corridor: 5 tags from x = 2 m, none from 7.6 m to GAP_NEXT_X_M, 5 more
    after it (turned GAP_TURN_DEG); the robot drives ~16 m with the corridor's weave. At 0.3 m/s
    no tag is in view for about 5 s (1.5 m; measured with the renderer and the default extract;
    BLANK_STRETCH_S) — what wheel odometry must bridge; the tags after the gap test that the
    map stays whole."""
    xs = [2.0 + 1.4 * i for i in range(5)] + [GAP_NEXT_X_M + 1.4 * i for i in range(5)]
    poses = [
        _corridor_tag(x, 1.0 if i % 2 == 0 else -1.0, 50.0 if i < 5 else GAP_TURN_DEG)
        for i, x in enumerate(xs)
    ]
    tags, anchor = _tags(poses, opts)
    end = xs[-1] - 1.5
    walls = box_walls(-0.5, -1.0, xs[-1] + 1.5, 1.0, height_m=2.5)
    x = np.linspace(0.0, end, int(end * 100))
    poly = np.stack([x, 0.04 * np.sin(2 * np.pi * x / 6.0)], -1)
    info = {"scenario": "corridor_gap", "corridor_m": [xs[-1] + 2.0, 2.0], "gap_m": [xs[4], xs[5]]}
    return [_moving("corridor_gap", poly, False, tags, walls, anchor, opts, info)]


def room_blank_turn(opts: SimOptions) -> list[Scene]:
    """Odometry through a turn at a blank wall: the room's loop (5 x 4 m, the same path), 14 tags
    on the east, north and south walls and none on the west one; the north wall's tags sit
    towards the west corner, the south wall's towards the east, so that in the north-west corner
    the camera turns towards the bare west wall and no tag is in view for about 2 s (measured
    with the renderer and the default extract; BLANK_STRETCH_S: the stretch)."""
    width, depth = 5.0, 4.0
    spots = [((width, depth * (j + 0.5) / 4), (-1.0, 0.0)) for j in range(4)]
    spots += [((x, depth), (0.0, -1.0)) for x in BLANK_TURN_NORTH_X_M]
    spots += [((x, 0.0), (0.0, 1.0)) for x in BLANK_TURN_SOUTH_X_M]
    poses = [
        upright_pose(np.array([x, y, 0.30 + 0.08 * (k % 3)]), np.array(n))
        for k, ((x, y), n) in enumerate(spots)
    ]
    tags, anchor = _tags(poses, opts)
    walls = box_walls(0.0, 0.0, width, depth, height_m=2.5)
    poly = ease_curvature(rounded_rect(1.0, 1.0, 4.0, 3.0, 0.5), True, ROOM_CURVATURE_RAMP_M)
    info = {"scenario": "room_blank_turn", "room_m": [width, depth], "blank_wall": "west (x = 0)"}
    return [_moving("room_blank_turn", poly, True, tags, walls, anchor, opts, info)]


def hall(opts: SimOptions) -> list[Scene]:
    """The sparse scene of issue 12: a 14 x 2.4 m hall, 28 tags flat on its walls (0.8 m apart on
    each wall from x = 2.2 m, staggered by 0.4 m across, 0.30/0.36 m high), so a forward-looking
    camera sees them obliquely (50-65 deg incidence) and one to three at a time (about a third
    of the frames that see a tag see one). The robot drives 12.2 m out 0.3 m right of the centre
    line, U-turns (radius 0.3 m, no tag in view) and drives 9 m back 0.3 m left of it."""
    length, width, lane, step = 14.0, 2.4, 0.3, 0.8
    poses = []
    for side, first in ((1.0, 2.6), (-1.0, 2.2)):  # left (+y) wall (the anchor first), right
        for i, x in enumerate(np.arange(first, 13.01, step)):
            poses.append(
                upright_pose(
                    np.array([x, side * width / 2, 0.30 + 0.06 * (i % 2)]), np.array([0.0, -side])
                )
            )
    tags, anchor = _tags(poses, opts)
    walls = box_walls(0.0, -width / 2, length, width / 2, height_m=2.5)
    x_turn = 12.5
    a = np.linspace(-np.pi / 2, np.pi / 2, 181)[1:-1]
    poly = np.vstack(
        [
            np.stack([np.linspace(0.3, x_turn, 1220), np.full(1220, -lane)], -1),
            np.stack([x_turn + lane * np.cos(a), lane * np.sin(a)], -1),
            np.stack([np.linspace(x_turn, 3.5, 900), np.full(900, lane)], -1),
        ]
    )
    poly = ease_curvature(poly, False, ROOM_CURVATURE_RAMP_M)
    info = {
        "scenario": "hall",
        "hall_m": [length, width],
        "lane_offset_m": lane,
        "tag_spacing_m": step,
    }
    return [_moving("hall", poly, False, tags, walls, anchor, opts, info)]


def build(scenario: str, opts: SimOptions) -> list[Scene]:
    """The scenes (recordings) of ``scenario``."""
    if scenario == "circle":
        return circle(opts)
    if scenario == "room":
        return room(opts)
    if scenario == "corridor":
        return corridor(opts)
    if scenario == "hall":
        return hall(opts)
    if scenario == "corridor_gap":
        return corridor_gap(opts)
    if scenario == "room_blank_turn":
        return room_blank_turn(opts)
    if scenario == "observations":
        scene = circle(opts, name="observations")[0]
        return [replace(scene, info={**scene.info, "scenario": "observations"})]
    raise SpecError(f"unknown scenario {scenario!r}; choose one of {', '.join(SCENARIOS)}")
