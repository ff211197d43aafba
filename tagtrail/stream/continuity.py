"""Live poses with continuity: the offline joint model's priors as a fixed-lag smoother, and
wheel-odometry dead reckoning between tag fixes.

:class:`Smoother` keeps the last frames (``window_s``, at most ``max_frames``, fewer while a
solve overruns ``budget_ms``) with their tag corners and re-solves them per new frame with
:func:`tagtrail.geometry.joint.solve_joint` against the fixed map — the corners under the
offline model's weights and loss, the constant-velocity motion prior (its velocity in the
camera's own frame: a steady arc costs nothing) and, once the camera has travelled far enough to
tell its plane, the ground-plane prior with that plane held fixed (fitted to the smoothed
history, its outlier poses left out), the wheeled-drive prior with the camera's mount held
fixed (fitted on that plane; its lever arm only once the history has turned ``MIN_TURN_RAD``;
kept while the history's steps leave it unstrained, as ``drive: auto`` offline) and, with
odometry, the wheel-odometry prior with its unknowns held (:class:`LiveOdometry`) — warm
started from the last solution (the new frame from its own pose, or from the motion's
extrapolation when its own disagrees: an IPPE flip), at most ``max_iter`` iterations. The
answer is the newest frame's pose and its covariance (the smoother's filtered estimate).

:class:`DeadReckoning` carries the last fix forward by the base's odometry (``nav_msgs/Odometry``
whose stamps are publication times, put back on the driver's fixed-rate clock by
:class:`~tagtrail.geometry.joint.odometry.StampGrid`: the state they describe is ``latency_s``
older), the camera ``camera_forward_m`` ahead of the base's turning centre, turning about the
plane's normal.
"""

from __future__ import annotations

import json
import logging
import math
import time
from bisect import bisect_left, bisect_right
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from operator import itemgetter
from typing import Any

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.fusion import tag_corners
from tagtrail.geometry.joint.drive import (
    WHEELED_BOUND,
    Mount,
    drive_terms,
    fit_mount,
    robust_weights,
    strain,
)
from tagtrail.geometry.joint.ground import (
    PLANAR_BOUND,
    GroundLevel,
    GroundPrior,
    Plane,
    fit_plane,
    ground_terms,
    planarity,
    plane_spread,
)
from tagtrail.geometry.joint.motion import MotionPrior
from tagtrail.geometry.joint.newest import Rows, prior_rows, solve_newest
from tagtrail.geometry.joint.odometry import (
    MAX_DEAD_RECKONING_S,
    ODOM_F_SCALE,
    ODOM_LOSS,
    Odometry,
    OdometryPrior,
    OdometryState,
    Pose2,
    StampGrid,
    carried_on,
    covered_steps,
    fit_yaw,
    planar_step,
    step_model,
    step_sigmas,
    whiten,
)
from tagtrail.geometry.joint.problem import (
    CornerObservations,
    Corners,
    Terms,
    corner_sigma,
    steps,
)
from tagtrail.geometry.joint.settings import (
    CORNER_F_SCALE_PX,
    CORNER_LOSS,
    ODOMETRY_SIGMA_M,
    JointSettings,
)
from tagtrail.geometry.joint.setup import DRIVE, GROUND
from tagtrail.geometry.joint.solver import solve_joint
from tagtrail.geometry.robust import rho
from tagtrail.geometry.rotations import log_so3
from tagtrail.geometry.se3 import R_of_rotvec, quat_xyzw_of
from tagtrail.schemas.documents import KnownGround
from tagtrail.stream import codec
from tagtrail.stream.stats import DropError

log = logging.getLogger("tagtrail.stream")

BUDGET_SOLVES = 5  # the solves (at least 3) whose median time the budget judges
HISTORY = 600  # smoothed poses kept for the plane and mount fits (20 s at 30 Hz)
MIN_TURN_RAD = 0.5  # the yaw the history must have turned before the mount's lever arm is fitted
# The ground prior's level term (the height's change frame to frame) is held once the history's
# A frame within this of the stamp its step was taken ahead for (Smoother._ahead) takes it,
# the terms moved to the frame's own start on their linear model. What that leaves out is the
# motion prior's interval: 0.15 ms off in 33 moved poses by up to 0.13 mm on a 0.3 m/s circle,
# 2 us by under 2 um. A camera stamped on a fixed period (ns-rounded: 1 ns off every few
# frames) takes them; one stamped by a jittery host clock computes them on arrival.
AHEAD_TOL_NS = 2_000
# After this many frames in a row off the stamp taken ahead for, the step is no longer taken
# ahead but every AHEAD_RETRY-th frame (a host-stamped camera: ~0.75 ms of CPU a frame for
# nothing, on the pose's path when the next frame comes before the after-work has run).
AHEAD_MISSES, AHEAD_RETRY = 10, 30
# spread across the travel is this many times its scatter off the plane
# (geometry.joint.ground.plane_spread): a straight drive gives 1-2 and leaves the normal free to
# roll about the line (harmless while the camera keeps to it; the hall's first 9 m fitted one
# 34 deg off, and held level through its U-turn that put the camera 5 cm low); a weaving drive
# gives 30-1000 in its first second.
MIN_PLANE_SPREAD = 100.0
# A held ground plane (SmootherSettings.ground: a mapping run's) is dropped when the history's
# median height off it or median tilt to it is beyond these: three times the ground prior's
# sigmas (1 cm, 1 deg); another robot's camera, or one remounted, sits centimetres off.
HELD_HEIGHT_M, HELD_TILT_DEG = 0.03, 3.0
# ... and its mount is not held when its lever arm is this far from the one given (--camera-
# forward): the rendered circle's mapping run solved -1.28 m for 0.084 (a pure arc cannot tell
# the lever arm from the camera's yaw) and, held, made the live 0.34 -> 0.49 mm.
HELD_LEVER_M = 0.02


@dataclass(frozen=True)
class HeldGround:
    """The ground plane and the camera's mount on the robot that a mapping run found
    (``ground.json``, :class:`~tagtrail.schemas.documents.KnownGround`): the smoother holds
    them from its first frame, where it would otherwise wait for ``plane_after_m`` of travel to
    fit them to its own history (the room's first 2 s: 0.65 mm lateral and 0.81 mm height
    error against 0.21 / 0.23 offline). ``mount`` None: fitted to the history on the plane."""

    plane: Plane
    mount: Mount | None = None

    @classmethod
    def of(cls, doc: KnownGround) -> HeldGround:
        """From a ``ground.json`` document."""
        plane = Plane(np.array(doc.normal), doc.offset_m, np.array(doc.normal_camera))
        if doc.forward_camera is None or doc.lever_m is None:
            return cls(plane)
        return cls(plane, Mount(np.array(doc.forward_camera), doc.lever_m))


@dataclass(frozen=True)
class SmootherSettings:
    """The live smoother: the window (s, frames), iterations per frame, the gate (m) beyond which
    a frame's own pose is not taken as its start, the travel (m) after which the ground plane is
    fitted, and the joint model's settings (``optimize.joint``)."""

    window_s: float = 2.0
    max_frames: int = 60
    budget_ms: float = 15.0
    """When the median of the last ``BUDGET_SOLVES`` solves takes longer, the window's frames
    halve (down to 5) for the next ones; under half of it, the window grows back by a frame: a
    loaded machine keeps its rate, a lone slow solve does not shrink the window."""
    max_iter: int = 2
    step_tol: float = 1e-3
    """The filter's step stops early once a Gauss-Newton step moves the frame less than this
    (m and rad, each component): from the motion's extrapolation one step is most often enough
    (81-100 % of the frames of five seeded recordings; their poses within 31 um of two steps'
    at p99, 89 um at most, each RMS error within 1.2 um), the second's ~0.15 ms off the pose's
    path. 0: always ``max_iter``."""
    start_gate_m: float = 0.05
    plane_after_m: float = 1.0
    step_first: bool = True
    """The newest frame's pose by the filter's step on the last solve (~1 ms), the window
    re-solved after it is out (:meth:`Smoother.settle`); False: the window re-solved first
    (the same pose for a linear problem; the step's reference)."""
    step_ahead: bool = True
    """The next frame's step taken as far as it can be before the frame arrives, once the
    window is re-solved (:meth:`Smoother._ahead`: the priors' terms but the odometry's, ~0.6
    ms off the pose's path); False: all on arrival (the same pose for a frame at the
    expected stamp)."""
    lever_m: float | None = None
    """The camera's distance ahead of the base's turning centre when the mount is known
    (``--camera-forward``, the profile's): the drive prior's lever arm, held from the start;
    None: fitted to the history once it has turned ``MIN_TURN_RAD`` (0 until then), which a
    weaving drive along a corridor never does: there the held 0 pulls the camera sideways."""
    joint: JointSettings = field(default_factory=JointSettings)
    ground: HeldGround | None = None
    """A mapping run's plane and mount (``stream localize --ground``), held from the first
    frame while the history agrees with them (:func:`held_off`); None: fitted to the history
    once the camera has travelled ``plane_after_m``."""


@dataclass(frozen=True)
class FixedGround:
    """The ground-plane prior with its plane held fixed (a :class:`~tagtrail.geometry.joint.
    Prior` without unknowns): a short window cannot tell the plane, the history can."""

    prior: GroundPrior
    plane: Plane

    name = "ground_fixed"
    n_params = 0
    start = None
    uses: tuple[str, ...] = ()

    def terms(self, R_cam: F64, t_cam: F64, values: Any) -> Terms:
        """:class:`GroundPlane`'s terms at the fixed plane, without its unknowns."""
        return ground_terms(R_cam, t_cam, self.plane, self.prior, unknowns=False)

    def update(self, value: Any, step: F64, values: Any) -> Any:
        return None


@dataclass(frozen=True)
class FixedDrive:
    """The wheeled-drive prior with the plane and the camera's mount held fixed (fitted to the
    history, like :class:`FixedGround`'s plane): the steps between the window's frames
    stamped ``t_s`` within ``max_gap_s`` move along the robot's heading."""

    plane: Plane
    mount: Mount
    t_s: F64
    max_gap_s: float

    name = "drive_fixed"
    n_params = 0
    start = None
    uses: tuple[str, ...] = ()

    def terms(self, R_cam: F64, t_cam: F64, values: Any) -> Terms:
        j = steps(self.t_s, self.max_gap_s)
        q, Jc, _ = drive_terms(
            R_cam, t_cam, self.t_s, j, self.plane, self.mount, DRIVE, unknowns=False
        )
        val, w = robust_weights(q, DRIVE)
        sw = np.sqrt(w)
        return Terms(
            float(val.sum()),
            (q * sw)[:, None],
            j,
            (Jc * sw[:, None, None])[:, :, None],
            None,
            len(j),
        )

    def update(self, value: Any, step: F64, values: Any) -> Any:
        return None


@dataclass
class _Frame:
    t_ns: int
    tag: I64  # map indices
    corners_px: F64  # (k, 4, 2)
    R: F64  # cam_T_world
    t: F64
    # the corners undistorted by ``camera`` and their noise (px), once a frame (the window's
    # every frame undistorted again for each re-solve: ~1 ms)
    camera: CameraModel | None = None
    norm: F64 | None = None
    sigma: F64 | None = None

    def weighed(self, camera: CameraModel, sigma_px: float) -> tuple[F64, F64]:
        """``(norm (k, 4, 2), sigma (k,))`` of the frame's corners through ``camera``."""
        if self.camera is not camera or self.norm is None or self.sigma is None:
            self.norm = camera.undistort(self.corners_px.reshape(-1, 4, 2))
            self.sigma = corner_sigma(self.corners_px, sigma_px)
            self.camera = camera
        return self.norm, self.sigma


Outputs = Iterator[tuple[str, bytes]]  # a node's keyed payloads, encoded as they are published
_ON_ARRIVAL = object()  # an extra prior that takes nothing ahead (Smoother._ahead)
PriorOf = Callable[[F64, list[int]], Any]
"""A further prior of the window: ``(t_s (F,), t_ns)`` of its frames -> a
:class:`~tagtrail.geometry.joint.Prior` (or None): :class:`LiveOdometry` (which
:class:`LivePoses` adds), or a student's own. One with a ``refresh()`` method has it called
as each window's re-solve is prepared (after the pose is out), for its slower updates; one
with ``ahead(a, b, start)`` and ``ahead_rows(taken, t_ns, d)`` takes the next frame's step's
term as far as it can before the frame (:meth:`Smoother._ahead`), the rest on arrival."""


@dataclass(frozen=True)
class _Window:
    """What a window's re-solve needs, taken when it is prepared (:meth:`Smoother._prepare`):
    picklable, so that it can be computed in the background process (:func:`_resolve`)."""

    R_tag: F64
    t_tag: F64
    R0: F64
    t0: F64
    ob: CornerObservations
    corners: Corners
    priors: list[Any]
    settings: SmootherSettings
    clock: Callable[[], float]
    t_ns: int  # the newest frame's stamp
    travel: float  # the camera's travel and frames seen before it (:meth:`Smoother._note`)
    seen: int
    fitted: bool  # the history fitted before (the fits then every 30 frames)
    hist: tuple[F64, F64, F64] | None  # the history (R, t, t_s) when a fit may be due
    held: HeldGround | None  # the mapping run's plane and mount, while the history agrees


@dataclass(frozen=True)
class _Solved:
    """A window's re-solve, computed: the solver's answer, its CPU time (ms), and the ground
    plane and mount fitted when the history asks for it (``fit``: None when not due)."""

    res: Any
    took_ms: float
    fit: _Fit | None


RESOLVE = "tagtrail.stream.continuity:_resolve"  # for a Background process


def _resolve(w: _Window) -> _Solved:
    """Compute a window's re-solve (a pure function of ``w``: here or in the background)."""
    start = w.clock()
    res = solve_joint(
        w.R_tag,
        w.t_tag,
        w.R0,
        w.t0,
        w.ob,
        np.zeros(len(w.R_tag), bool),
        w.corners,
        w.priors,
        max_iter=w.settings.max_iter,
        covariance="last",
    )
    took_ms = (w.clock() - start) * 1e3
    R, t = res.R_cam[-1], res.t_cam[-1]
    travel, fit = w.travel, None
    if w.hist is not None:
        Rs, ts, t_s = w.hist
        if len(Rs):
            travel += _moved((Rs[-1], ts[-1]), R, t)
        n = min(HISTORY, len(Rs) + 1)
        if _fit_due(w.settings, travel, n, w.seen, w.fitted, w.held):
            Rs = np.concatenate([Rs, R[None]])[-HISTORY:]
            ts = np.concatenate([ts, t[None]])[-HISTORY:]
            t_s = np.concatenate([t_s, [w.t_ns * 1e-9]])[-HISTORY:]
            fit = _fit(w.settings, Rs, ts, t_s, w.held, travel)
    return _Solved(res, took_ms, fit)


class _Job:
    """The window's re-solve after a pose went out: its frames and :class:`_Window`, handed
    to the background process (:class:`~tagtrail.stream.background.Background`, job ``seq``);
    :meth:`take` is its result, or computes it when that is not back."""

    def __init__(self, frames: list[_Frame], window: _Window) -> None:
        self.frames, self.window = frames, window
        self.seq: int | None = None

    def take(self, background: Any) -> _Solved:
        if background is not None:
            ok, out = background.result(self.seq)
            if ok:
                return out  # type: ignore[no-any-return]
        return _resolve(self.window)


class Smoother:
    """Fixed-lag smoother of one camera against a fixed map (module docstring); ``extra``:
    further priors of each window (:data:`PriorOf`)."""

    def __init__(
        self,
        world_T_tag: F64,
        size_m: F64,
        settings: SmootherSettings | None = None,
        extra: Sequence[PriorOf] = (),
        clock: Callable[[], float] = time.thread_time,
    ) -> None:
        self.s = settings or SmootherSettings()
        self.extra = tuple(extra)
        self.clock = clock
        self.n_max = self.s.max_frames  # the window's frames now (the time budget's)
        self._took_ms: deque[float] = deque(maxlen=BUDGET_SOLVES)
        self.R_tag = np.ascontiguousarray(world_T_tag[:, :3, :3])
        self.t_tag = np.ascontiguousarray(world_T_tag[:, :3, 3])
        self.pts = tag_corners(np.asarray(size_m, np.float64))
        self.frames: deque[_Frame] = deque()
        self.history: deque[tuple[F64, F64]] = deque(maxlen=HISTORY)  # smoothed (R, t)
        self.plane: Plane | None = None
        self.level = False  # the plane's normal told by the history: its level term held
        self.fitted = False  # the history fitted once (then every 30 frames)
        self.mount: Mount | None = None
        held = self.s.ground if self.s.joint.ground != "none" else None
        lever = self.s.lever_m
        if (
            held is not None
            and held.mount is not None
            and lever is not None
            and abs(held.mount.lever_m - lever) > HELD_LEVER_M
        ):
            log.warning(
                "localize: the mapping run's camera mount (--ground) is not held: its lever arm "
                "%.3f m is not the %.3f m given (--camera-forward, the profile's); its drive "
                "could not tell it (a pure arc: the lever arm and the camera's yaw trade against "
                "each other) or it is another robot's. Its ground plane is held",
                held.mount.lever_m,
                lever,
            )
            held = HeldGround(held.plane)
        self.held = held
        if self.held is not None:  # a mapping run's: held from the first frame
            self.plane, self.level = self.held.plane, True
            if self.s.joint.drive != "free":
                self.mount = self.held.mount
        self.dropped = ""  # why the held plane was dropped (the history is off it)
        self.t_hist: deque[float] = deque(maxlen=HISTORY)
        self._travel = 0.0
        self._seen = 0
        self.iters = 0
        # the re-solve after a frame answered by the step: its camera until it is prepared
        # (once the pose is out: :meth:`pending`), then the job
        self._pending: CameraModel | None = None
        self._job: _Job | None = None
        self._extrapolated: tuple[int, F64, F64, tuple[F64, F64] | None] | None = None
        self.background: Any = None  # a Background process for the re-solves (None: here)
        # the last solve: its newest frame's stamp, its last two frames' covariance, the
        # corners' loss scale (noise units), the variance factor (>= 1)
        self._last: tuple[int, F64, float, float] | None = None
        # the next frame's step taken ahead (:meth:`_ahead`): its expected stamp, its start,
        # the terms of the priors but the extra ones there, the last solve it is for, and
        # what each extra prior took ahead (its ``ahead``'s, else _ON_ARRIVAL)
        self._next: tuple[int, F64, F64, Rows, Any, tuple[Any, ...]] | None = None
        self.ahead_used = 0  # frames whose step took it
        self._ahead_missed = 0  # frames in a row that did not (AHEAD_MISSES)
        self.ahead_taken = 0  # steps taken ahead

    def reset(self) -> None:
        self.frames.clear()
        self._last = self._next = None

    def _extrapolate(self, t_ns: int) -> tuple[F64, F64] | None:
        """The pose at ``t_ns`` by a constant twist from the last two frames (the motion
        prior's model; None: < 2)."""
        if len(self.frames) < 2:
            return None
        a, b = self.frames[-2], self.frames[-1]
        memo = self._extrapolated  # wants_start's, for add of the same frame
        if memo is not None and memo[0] == t_ns and memo[1] is a.R and memo[2] is b.R:
            return memo[3]  # (the poses it came from are held: their ids cannot be reused)
        out = self._extrapolated_from(a, b, t_ns)
        self._extrapolated = (t_ns, a.R, b.R, out)
        return out

    def _extrapolated_from(self, a: _Frame, b: _Frame, t_ns: int) -> tuple[F64, F64] | None:
        h, g = (b.t_ns - a.t_ns) * 1e-9, (t_ns - b.t_ns) * 1e-9
        if h <= 0 or g > self.s.joint.max_gap_s:
            return None
        Rab = b.R @ a.R.T  # cam_R_world: b = Rab a (left increment)
        dR = R_of_rotvec(log_so3(Rab[None])[0] * (g / h))
        ca, cb = -a.R.T @ a.t, -b.R.T @ b.t
        c = cb + b.R.T @ (a.R @ (cb - ca)) * (g / h)  # a's step, seen from b
        R = dR @ b.R
        return R, -R @ c

    def add(
        self, t_ns: int, tag: I64, corners_px: F64, start: F64 | None, camera: CameraModel
    ) -> tuple[F64, F64] | None:
        """Add a frame (map tag indices ``tag (k,)``, distorted corners ``(k, 4, 2)`` px, its own
        pose ``start`` = world_T_cam (4, 4) or None): the newest frame's ``world_T_cam (4, 4)``
        and covariance ``(6, 6)`` of ``[position ; rotation]`` (world axes, ROS's order). None
        when the frame has no start and nothing to extrapolate from.

        The pose comes from the filter's step on the last solve's two newest frames
        (:func:`~tagtrail.geometry.joint.newest.solve_newest`) when there is one, and the
        window's re-solve waits for :meth:`settle` (the node calls it once the pose is out;
        the next ``add`` does it first); else (the first frames, after a gap) the window is
        solved at once."""
        self.settle()
        if self.frames and (
            t_ns <= self.frames[-1].t_ns
            or (t_ns - self.frames[-1].t_ns) * 1e-9 > self.s.joint.max_gap_s
        ):
            self.reset()  # a gap (or stamps back in time): start over
        guess = self._extrapolate(t_ns)
        own = None
        if start is not None and np.isfinite(start).all():
            Rw = start[:3, :3].T
            own = (Rw, -Rw @ start[:3, 3])
        init: tuple[F64, F64] | None = own if own is not None else guess
        if guess is not None and own is not None:
            cg, co = -guess[0].T @ guess[1], -own[0].T @ own[1]
            init = own if np.linalg.norm(cg - co) <= self.s.start_gate_m else guess
        if init is None:
            return None
        frame = _Frame(t_ns, np.asarray(tag, np.int64), corners_px, *init)
        quick = self._newest(frame, camera, guess)
        self.frames.append(frame)
        t_cut = t_ns - int(self.s.window_s * 1e9)
        while len(self.frames) > self.n_max or self.frames[0].t_ns < t_cut:
            self.frames.popleft()
        if quick is not None:
            self._pending = camera
            return quick
        job = self._prepare(camera)
        return self._commit(job.frames, _resolve(job.window))

    def wants_start(self, t_ns: int) -> bool:
        """Whether :meth:`add` of a frame at ``t_ns`` needs the frame's own pose: not when the
        filter's step will start from the motion's extrapolation (the per-frame multi-tag PnP
        is then ~0.5 ms for nothing)."""
        self.settle()  # what add does first: then the last solve is the one to step from
        return not (
            self._steppable()
            and t_ns > self.frames[-1].t_ns
            and self._extrapolate(t_ns) is not None
        )

    def _steppable(self) -> bool:
        """Whether the last solve is the window's, to take the filter's step from."""
        last = self._last
        return (
            self.s.step_first
            and last is not None
            and len(self.frames) >= 2
            and last[0] == self.frames[-1].t_ns
        )

    def settle(self) -> None:
        """Re-solve the window of the frame :meth:`add` answered by the filter's step (nothing
        when none waits; the background's result when it is back, :meth:`dispatch`): its
        frames, the plane, the mount and the next step's prior."""
        job, self._job = self._prepared(), None
        if job is not None:
            self._commit(job.frames, job.take(self.background))

    def dispatch(self) -> bool:
        """Prepare the waiting re-solve and hand it to :attr:`background` (when there is
        one), or take its result once it is back: the node's after-work (``Node.after``, a
        couple of ms after a message's outputs, once the nodes downstream have had their
        turn), so a frame's pose is followed by its window's hand-over, and the result is
        taken between messages instead of before the next frame's step. Whether the
        background still has it (the node asks again a couple of ms later: without that,
        the result waited for an odometry message, and a fifth of the frames took it first
        thing). :meth:`settle` takes what is left: the result when it is back, else it
        computes it."""
        job = self._prepared()
        if job is None or self.background is None or self.background.dead:
            return False
        if job.seq is None:
            if self.background.idle():  # (else its start-up, or a job the next frame took)
                job.seq = self.background.submit(job.window)
        elif self.background.ready(job.seq):
            self.settle()
            return False
        return True

    def _prepared(self) -> _Job | None:
        if self._pending is not None:
            self._job, self._pending = self._prepare(self._pending), None
        return self._job

    def _history(self) -> tuple[F64, F64, F64]:
        """The history as arrays: ``R (n, 3, 3)``, ``t (n, 3)``, ``t_s (n,)``."""
        if not self.history:
            return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0)
        return (
            np.stack([h[0] for h in self.history]),
            np.stack([h[1] for h in self.history]),
            np.asarray(self.t_hist, np.float64),
        )

    def _prepare(self, camera: CameraModel) -> _Job:
        """The window's re-solve as a :class:`_Job`: the frames, corners and priors taken now,
        the history only when a fit may be due (:meth:`_note`)."""
        fr = list(self.frames)
        for make in self.extra:  # (off the pose's path: a frame's step only evaluates them)
            refresh = getattr(make, "refresh", None)
            if refresh is not None:
                refresh()
        used, ob, corners = self._observations(fr, camera)
        seen, fitted = self._seen + 1, self.fitted
        window = _Window(
            self.R_tag[used],
            self.t_tag[used],
            np.stack([f.R for f in fr]),
            np.stack([f.t for f in fr]),
            ob,
            corners,
            self._priors(fr),
            self.s,
            self.clock,
            fr[-1].t_ns,
            self._travel,
            seen,
            fitted,
            self._history() if not fitted or seen % 30 == 0 else None,
            self.held,
        )
        return _Job(fr, window)

    def _commit(self, fr: list[_Frame], done: _Solved) -> tuple[F64, F64]:
        """Take a computed re-solve of frames ``fr`` (:class:`_Solved`): their poses, the
        history, the fits, the next step's prior and the time budget
        (:class:`SmootherSettings`); the newest frame's ``world_T_cam`` and covariance."""
        res = done.res
        self._took_ms.append(done.took_ms)
        took_ms = float(np.median(self._took_ms))  # a lone slow solve (a hiccup) does not count
        if took_ms > self.s.budget_ms and len(self._took_ms) >= 3:
            self.n_max = max(5, self.n_max // 2)
            self._took_ms.clear()  # judge the smaller window on its own solves
        elif took_ms < self.s.budget_ms / 2:
            self.n_max = min(self.s.max_frames, self.n_max + 1)
        self.iters = res.iters
        for i, f in enumerate(fr):
            f.R, f.t = res.R_cam[i], res.t_cam[i]
        R, t = res.R_cam[-1], res.t_cam[-1]
        self._note(fr[-1].t_ns, R, t, done)
        vf = res.variance_factor
        self._last = (
            (fr[-1].t_ns, res.tail_cov, CORNER_F_SCALE_PX / res.sigma_px, max(vf, 1.0))
            if res.tail_cov is not None and np.isfinite(vf) and np.isfinite(res.tail_cov).all()
            else None
        )
        self._ahead()
        cov = np.full((6, 6), np.nan)
        if res.cam_cov is not None:
            cov = _world_cov(R, res.cam_cov[-1])
        return _world_T_cam(R, t), cov

    def _ahead(self) -> None:
        """Take the next frame's step ahead, as far as it can be before the frame: at the
        stamp one frame interval on, the start the motion extrapolates there, the terms of
        the joint model's priors (~0.6 ms off the pose's path) and what the extra ones take
        ahead (the odometry: its Jacobians, ~0.4 ms; its reading, whose messages keep
        coming, waits for the frame). A frame whose stamp is within ``AHEAD_TOL_NS`` of it
        takes them (:meth:`_newest`); exactly there its pose is the one computed on
        arrival."""
        self._next = None
        if not self.s.step_ahead or not self._steppable() or len(self.frames) < 2:
            return
        if self._ahead_missed >= AHEAD_MISSES and self._seen % AHEAD_RETRY:
            return
        a, b = self.frames[-2], self.frames[-1]
        t_ns = 2 * b.t_ns - a.t_ns
        start = self._extrapolated_from(a, b, t_ns)
        if start is None:
            return
        nxt = _Frame(t_ns, np.zeros(0, np.int64), np.zeros((0, 4, 2)), *start)
        priors = self._priors([a, b, nxt], extra=False)
        rows = prior_rows(np.stack([a.R, b.R, start[0]]), np.stack([a.t, b.t, start[1]]), priors)
        self._next = (t_ns, start[0], start[1], rows, self._last, self._extras_ahead(a, b, start))
        self.ahead_taken += 1

    def _observations(
        self, fr: Sequence[_Frame], camera: CameraModel
    ) -> tuple[I64, CornerObservations, Corners]:
        """The map tags seen in frames ``fr``, their corner observations and weighing."""
        tag_all = np.concatenate([f.tag for f in fr])
        used, tag_local = np.unique(tag_all, return_inverse=True)
        frame = np.repeat(np.arange(len(fr)), [len(f.tag) for f in fr])
        w = [f.weighed(camera, self.s.joint.corner_sigma_px) for f in fr]
        norm = w[0][0] if len(w) == 1 else np.concatenate([n for n, _ in w])
        sigma = w[0][1] if len(w) == 1 else np.concatenate([g for _, g in w])
        ob = CornerObservations(frame, tag_local, self.pts[tag_all], norm)
        corners = Corners(camera.focal_px, sigma, CORNER_LOSS, CORNER_F_SCALE_PX, False)
        return used, ob, corners

    def _priors(self, fr: Sequence[_Frame], own: bool = True, extra: bool = True) -> list[Any]:
        """The priors over frames ``fr`` (module docstring): the joint model's (``own``) and
        :attr:`extra`'s (``extra``)."""
        js = self.s.joint
        priors: list[Any] = []
        sig = js.motion_sigmas() if own else None
        t_s = np.array([(f.t_ns - fr[0].t_ns) * 1e-9 for f in fr])
        if sig is not None and len(fr) >= 3:
            priors.append(MotionPrior(t_s, *sig, js.max_gap_s, frame="camera"))
        if own and self.plane is not None and js.ground != "none":
            priors.append(FixedGround(GROUND, self.plane))
            if self.level and np.isfinite(GROUND.level_sigma):
                priors.append(GroundLevel(GROUND, t_s, js.max_gap_s, self.plane))
            if self.mount is not None and js.drive != "free":
                priors.append(FixedDrive(self.plane, self.mount, t_s, js.max_gap_s))
        for make in self.extra if extra else ():
            prior = make(t_s, [f.t_ns for f in fr])
            if prior is not None:
                priors.append(prior)
        return priors

    def _newest(
        self, frame: _Frame, camera: CameraModel, guess: tuple[F64, F64] | None
    ) -> tuple[F64, F64] | None:
        """The filter's step for ``frame`` on the last solve (None: no solve to step from),
        from the motion's extrapolation ``guess`` when there is one: there the priors, taken
        once (:func:`~tagtrail.geometry.joint.newest.solve_newest`), are at their expected
        residuals (from the frame's own pose, mm off, the motion prior's robust loss would
        discount itself: +11 % on a detections circle)."""
        last = self._last
        if last is None or not self._steppable():
            return None
        start = guess if guess is not None else (frame.R, frame.t)
        fr = [self.frames[-2], self.frames[-1]]
        used, ob, corners = self._observations([frame], camera)
        nxt = self._next
        hit = False
        if nxt is not None and nxt[4] is last and guess is not None:
            hit = abs(frame.t_ns - nxt[0]) <= AHEAD_TOL_NS
            self._ahead_missed = 0 if hit else self._ahead_missed + 1
        d = np.zeros(6)  # the start from the one taken ahead
        rows: Rows | None = None
        if hit and nxt is not None:
            rows, ahead = nxt[3], nxt[5]
            if not (np.array_equal(start[0], nxt[1]) and np.array_equal(start[1], nxt[2])):
                # the terms taken ahead, moved to this start on their linear model
                dR = start[0] @ nxt[1].T
                d = np.concatenate([log_so3(dR[None])[0], start[1] - dR @ nxt[2]])
                rows = (rows[0] + rows[1] @ d, rows[1], rows[2])
            self.ahead_used += 1
            priors: list[Any] = []
        else:
            priors = self._priors([*fr, frame], extra=False)
            ahead = self._extras_ahead(fr[0], fr[1], start)
        extra, more = self._extra_on_arrival([*fr, frame], ahead, frame.t_ns, d)
        if more:
            have = rows if rows is not None else (np.zeros(0), np.zeros((0, 6)), np.zeros((0, 12)))
            r, A, B = (np.concatenate([x, *(m[i] for m in more)]) for i, x in enumerate(have))
            rows = (r, A, B)
        priors += extra
        res = solve_newest(
            np.stack([*(f.R for f in fr), start[0]]),
            np.stack([*(f.t for f in fr), start[1]]),
            last[1],
            self.R_tag[used],
            self.t_tag[used],
            ob,
            corners,
            last[2],
            priors,
            self.s.max_iter,
            rows,
            self.s.step_tol,
        )
        if res is None or not (np.isfinite(res.R).all() and np.isfinite(res.t).all()):
            return None
        frame.R, frame.t = res.R, res.t
        return _world_T_cam(res.R, res.t), _world_cov(res.R, res.cov * last[3])

    def _extras_ahead(self, a: _Frame, b: _Frame, start: tuple[F64, F64]) -> tuple[Any, ...]:
        """What each extra prior takes of a step from frames ``a, b`` to a new frame at
        ``start`` before the new frame's own data (its ``ahead``; else ``_ON_ARRIVAL``)."""
        return tuple(
            make.ahead(a, b, start) if hasattr(make, "ahead") else _ON_ARRIVAL
            for make in self.extra
        )

    def _extra_on_arrival(
        self, fr: Sequence[_Frame], ahead: tuple[Any, ...], t_ns: int, d: F64
    ) -> tuple[list[Any], list[Rows]]:
        """The extra priors' part of the step into the frame at ``t_ns`` (the last of ``fr``)
        from what each took before it (``ahead``, :meth:`_extras_ahead`; ``d``: the frame's
        start from the one it was taken at): the rows of those that took something (their
        ``ahead_rows``, with the frame's own data: the odometry's reading), the priors of
        the others (evaluated in the step)."""
        priors: list[Any] = []
        more: list[Rows] = []
        for make, ah in zip(self.extra, ahead, strict=True):
            if ah is _ON_ARRIVAL:
                t_s = np.array([(f.t_ns - fr[0].t_ns) * 1e-9 for f in fr])
                prior = make(t_s, [f.t_ns for f in fr])
                if prior is not None:
                    priors.append(prior)
            elif ah is not None:
                taker: Any = make  # (one with ahead and ahead_rows: PriorOf)
                got = taker.ahead_rows(ah, t_ns, d)
                if got is not None:
                    more.append(got)
        return priors, more

    def _note(self, t_ns: int, R: F64, t: F64, done: _Solved | None = None) -> None:
        """Keep the smoothed pose; once the camera has travelled far enough, fit the ground
        plane to the history (robustly: a lone frame's outlier pose does not tilt it) and, on
        it, the camera's mount on a wheeled robot (every 30 frames). ``drive: auto`` keeps the
        drive prior while the history's steps leave it unstrained
        (:func:`~tagtrail.geometry.joint.drive.strain`, as offline). ``done``: a re-solve
        that computed the fits already (:meth:`_prepare`)."""
        if self.history:
            self._travel += _moved(self.history[-1], R, t)
        self.history.append((R, t))
        self.t_hist.append(t_ns * 1e-9)
        self._seen += 1
        if done is not None:
            fit = done.fit
        elif _fit_due(self.s, self._travel, len(self.history), self._seen, self.fitted, self.held):
            fit = _fit(self.s, *self._history(), self.held, self._travel)
        else:
            fit = None
        if fit is not None:
            if fit.dropped and self.held is not None:
                self.held, self.dropped = None, fit.dropped
                log.warning(
                    "localize: the mapping run's ground plane (--ground) dropped: %s; the "
                    "plane and mount are fitted to this run's own poses instead",
                    fit.dropped,
                )
            # a held plane dropped before the history could tell one: wait for the travel
            self.fitted = fit.plane is not None or not fit.dropped
            self.plane, self.level = fit.plane, fit.told
            if fit.set_mount:
                self.mount = fit.mount


@dataclass(frozen=True)
class _Fit:
    """The history's fits (:func:`_fit`): the ground ``plane``, whether it ``told`` the
    plane's normal (:data:`MIN_PLANE_SPREAD`; the level term is held only then), the
    ``mount`` (None: not a wheeled robot's) and whether it is to be set (not with ``ground:
    none`` or ``drive: free``). No plane: the history leaves any plane (``ground: auto``: the
    offline planarity test on the smoothed poses; a hand-held camera)."""

    plane: Plane | None
    told: bool
    mount: Mount | None
    set_mount: bool
    dropped: str = ""  # the held plane's (SmootherSettings.ground) disagreement, in words


def _fit_due(
    s: SmootherSettings,
    travel: float,
    n_hist: int,
    seen: int,
    fitted: bool,
    held: HeldGround | None = None,
) -> bool:
    """Whether the history asks for the plane's (and mount's) fit (:meth:`Smoother._note`);
    a held plane is checked against it from its tenth pose, travelled or not."""
    if (travel < s.plane_after_m and held is None) or n_hist < 10:
        return False
    return not (fitted and seen % 30)  # (the history stops at HISTORY poses)


def held_off(plane: Plane, Rs: F64, ts: F64) -> str:
    """Why the poses ``cam_T_world`` ``(Rs, ts)`` are not on ``plane`` (a mapping run's): the
    median height off it or tilt to it beyond :data:`HELD_HEIGHT_M` / :data:`HELD_TILT_DEG`;
    '' when they are."""
    h = float(np.median(np.abs(np.einsum("fji,fj->fi", Rs, -ts) @ plane.n - plane.d)))
    u = plane.u / np.linalg.norm(plane.u)
    cos = np.clip(np.einsum("fij,j->fi", Rs, plane.n) @ u, -1.0, 1.0)
    tilt = float(np.degrees(np.median(np.arccos(cos))))
    if h > HELD_HEIGHT_M or tilt > HELD_TILT_DEG:
        return (
            f"this run's camera sits {100 * h:.1f} cm off it and is tilted {tilt:.1f} deg to "
            f"it (median; at most {100 * HELD_HEIGHT_M:.0f} cm, {HELD_TILT_DEG:.0f} deg): "
            "another robot, or the camera remounted"
        )
    return ""


def _fit(
    s: SmootherSettings,
    Rs: F64,
    ts: F64,
    t_hist: F64,
    held: HeldGround | None = None,
    travel: float = math.inf,
) -> _Fit:
    """The plane and the mount fitted to the history ``Rs, ts`` at times ``t_hist`` (s) once
    the camera has travelled (``travel``) ``plane_after_m`` — or ``held``'s plane (and mount) while
    the history agrees with it (:func:`held_off`): a mapping run's whole drive tells them
    better than this run's last 20 s (the corridor's seed 3: 1.49 mm held, 1.59 with this
    run's own once its weaving told the plane's normal)."""
    t_s = np.asarray(t_hist, np.float64) - t_hist[0]
    keep = robust_plane_frames(Rs, ts)
    Rs, ts, t_s = Rs[keep], ts[keep], t_s[keep]
    js = s.joint
    dropped = "" if held is None else held_off(held.plane, Rs, ts)
    own: tuple[Plane, bool] | None = None  # the history's plane, whether it tells the normal
    if (held is None or dropped) and travel >= s.plane_after_m:
        if js.ground == "auto":  # as offline: the planarity test, its plane fitted on the way
            fitted, stat = planarity(Rs, ts, np.zeros((len(Rs), 6, 6)), GROUND)
            if stat < PLANAR_BOUND:  # (else not a ground robot's)
                own = fitted, plane_spread(Rs, ts, GROUND) >= MIN_PLANE_SPREAD
        else:
            own = fit_plane(Rs, ts, GROUND), plane_spread(Rs, ts, GROUND) >= MIN_PLANE_SPREAD
    if held is not None and not dropped:
        plane, told = held.plane, True
        if held.mount is not None or js.drive == "free":
            return _Fit(plane, told, held.mount, js.drive != "free")
        if travel < s.plane_after_m:  # the mount fitted to this run's first metre, as without
            return _Fit(plane, told, None, False)
    elif own is None:
        return _Fit(None, False, None, True, dropped)  # none yet, or not a ground robot's
    else:
        plane, told = own
    if js.ground == "none" or js.drive == "free":
        return _Fit(plane, told, None, False, dropped)
    j = steps(t_s, js.max_gap_s)
    mount = fit_mount(Rs, ts, t_s, j, plane, MIN_TURN_RAD, s.lever_m)
    q = drive_terms(Rs, ts, t_s, j, plane, mount, DRIVE, unknowns=False)[0]
    wheeled = js.drive == "wheeled" or strain(q, DRIVE, 1.0) <= WHEELED_BOUND
    return _Fit(plane, told, mount if wheeled else None, True, dropped)


def _moved(prev: tuple[F64, F64], R: F64, t: F64) -> float:
    """The camera centre's move from ``prev`` = (R, t) to (R, t) (cam_T_world), m."""
    Rp, tp = prev
    return float(np.linalg.norm(-R.T @ t + Rp.T @ tp))


def _world_T_cam(R: F64, t: F64) -> F64:
    """``world_T_cam (4, 4)`` of ``cam_T_world`` ``(R, t)``."""
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ t
    return T


def _world_cov(R: F64, cam_cov: F64) -> F64:
    """The covariance ``(6, 6)`` of ``[position ; rotation]`` in the world (ROS's order) from
    that of ``cam_T_world``'s ``[w ; v]`` (``R``: its rotation)."""
    J = np.zeros((6, 6))  # [w ; v] of cam_T_world -> [dc ; dtheta] in the world
    J[:3, 3:] = -R.T
    J[3:, :3] = -R.T
    return J @ cam_cov @ J.T


def robust_plane_frames(R: F64, t: F64, rounds: int = 3) -> np.ndarray:
    """Which frames ``(F,)`` bool a plane fit keeps: those within 3 robust standard deviations
    (at least 2 cm) of the plane fitted to the ones kept before (from all)."""
    keep = np.ones(len(R), bool)
    c = -np.einsum("fji,fj->fi", R, t)
    for _ in range(rounds):
        p = fit_plane(R[keep], t[keep], GROUND)
        h = c @ p.n - p.d
        mad = float(np.median(np.abs(h[keep] - np.median(h[keep]))))
        new = np.abs(h - np.median(h[keep])) <= max(3 * 1.4826 * mad, 0.02)
        if new.sum() < 10 or (new == keep).all():
            break
        keep = new
    return keep


@dataclass
class DeadReckoning:
    """The last fix carried forward by wheel odometry (module docstring): odometry samples
    ``(t_ns of the state, x, y, yaw)`` of the base in its odom frame (z up)."""

    latency_s: float = 0.005
    camera_forward_m: float = 0.0
    max_age_s: float = MAX_DEAD_RECKONING_S  # the offline bound (10 s from the last tag)
    odo: deque[tuple[int, float, float, float]] = field(default_factory=lambda: deque(maxlen=500))
    fix: tuple[int, F64] | None = None  # (t_ns, world_T_cam)
    up: F64 | None = None  # the plane's normal pointing up (world)
    grid: StampGrid = field(default_factory=StampGrid)
    errors: tuple[float, float, float, float] = (1.0, 1.0, 0.0, 0.0)
    """The odometry's errors read against the smoothed history (:class:`LiveOdometry`: its
    scale, turn scale, yaw per metre, drift rad/s), taken off each step: two wheels 3 % apart
    carried 2 s through a figure eight's turns drifted 5 cm."""
    _run: tuple[int, int, float, float, float] | None = None  # (fix, last sample, x, y, yaw)

    def add_odometry(self, stamp_ns: int, x: float, y: float, yaw: float) -> int:
        """One odometry message (stamp = publication time, its jitter taken off on the
        driver's grid); the state's time (ns)."""
        t = self.grid.add(stamp_ns) - int(self.latency_s * 1e9)
        if self.odo and t <= self.odo[-1][0]:
            return t
        self.odo.append((t, x, y, yaw))
        return t

    def _at(self, t_ns: int) -> tuple[float, float, float] | None:
        """The odometry pose at ``t_ns`` (linear in x, y, yaw; None outside the samples)."""
        o = self.odo
        if not o or t_ns > o[-1][0] or t_ns < o[0][0]:
            return None
        j = bisect_left(o, t_ns, key=itemgetter(0))  # (not a list of the 500 stamps a call: ~20 us)
        if o[j][0] == t_ns or j == 0:
            return o[j][1:]
        a, b = o[j - 1], o[j]
        f = (t_ns - a[0]) / (b[0] - a[0])
        dyaw = math.atan2(math.sin(b[3] - a[3]), math.cos(b[3] - a[3]))
        return a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]), a[3] + f * dyaw

    def _step(
        self, a: Pose2, b: Pose2, h: float, run: tuple[float, ...]
    ) -> tuple[float, float, float]:
        """``run`` (x, y, yaw of the base since the fix) on by the odometry's step from its
        pose ``a`` to ``b`` (``h`` s), its :attr:`errors` taken off (the offline prior's
        model: distance ``scale`` times the true, yaw ``turn`` times the true turn plus
        ``per_m`` per metre read and ``drift`` per second)."""
        scale, turn, per_m, drift = self.errors
        ox, oy, oth = planar_step(a, b)
        dx, dy, dth = ox / scale, oy / scale, (oth - per_m * ox - drift * h) / turn
        c, s = math.cos(run[2]), math.sin(run[2])
        return run[0] + c * dx - s * dy, run[1] + s * dx + c * dy, run[2] + dth

    def reading(
        self, t0_ns: int, t_ns: int, since_ns: int, extend_ns: int
    ) -> tuple[float, float, float] | None:
        """What the odometry read from ``t0_ns`` to ``t_ns``: ``(dx, dy, dyaw)`` in the base's
        frame at ``t0_ns``, its errors in -- the window's prior's reading of a step
        (:class:`LiveOdometry`: the samples from the last at or before ``since_ns`` on, at
        least two, carried on at the last step's rate up to ``extend_ns`` past the last);
        None where they do not cover both times. In scalars: a frame's step takes it on
        arrival (building the prior took ~0.2 ms)."""
        o = self.odo
        first = max(bisect_right(o, since_ns, key=itemgetter(0)) - 1, 0)
        if len(o) - first < 2 or not o[first][0] <= t0_ns <= t_ns:
            return None
        last = o[-1]
        if t_ns <= last[0]:
            b = self._at(t_ns)
        elif t_ns - last[0] <= extend_ns:
            prev = o[-2]
            b = carried_on(prev[1:], last[1:], (t_ns - last[0]) / (last[0] - prev[0]))
        else:
            return None
        if b is None:
            return None
        if t0_ns <= last[0]:
            a = self._at(t0_ns)
        else:  # both past the last sample: on the line to the carried-on pose, as interpolated
            g = (t0_ns - last[0]) / (t_ns - last[0])
            x, y, yaw = last[1:]
            a = x + g * (b[0] - x), y + g * (b[1] - y), yaw + g * (b[2] - yaw)
        return None if a is None else planar_step(a, b)

    def _motion(self, t_fix: int, t_ns: int) -> tuple[float, float, float] | None:
        """The base's motion from ``t_fix`` to ``t_ns`` in its frame at ``t_fix``: the
        odometry's steps between its samples, each corrected (:meth:`_step`), kept up to the
        last sample for the next message (through a blackout, one step a message)."""
        o = self.odo
        if not o or t_fix < o[0][0] or t_ns > o[-1][0] or t_ns < t_fix:
            return None
        run = self._run
        if run is None or run[0] != t_fix or run[1] > t_ns:
            run = (t_fix, t_fix, 0.0, 0.0, 0.0)
        t0, pose = run[1], run[2:]
        a = self._at(t0)
        if a is None:
            return None
        for j in range(bisect_right(o, t0, key=itemgetter(0)), len(o)):
            if o[j][0] > t_ns:
                break
            pose = self._step(a, o[j][1:], (o[j][0] - t0) * 1e-9, pose)
            t0, a = o[j][0], o[j][1:]
        self._run = (t_fix, t0, *pose)
        b = self._at(t_ns)
        if b is None:
            return None
        return self._step(a, b, (t_ns - t0) * 1e-9, pose) if t_ns > t0 else pose

    def pose(self, t_ns: int) -> F64 | None:
        """world_T_cam (4, 4) at ``t_ns`` from the last fix and the odometry since (None: no
        fix, no odometry covering both times, or the fix older than ``max_age_s``)."""
        if self.fix is None:
            return None
        t_fix, T = self.fix
        if not 0 <= (t_ns - t_fix) * 1e-9 <= self.max_age_s:
            return None
        moved = self._motion(t_fix, t_ns)
        if moved is None:
            return None
        dx, dy, dyaw = moved  # the base's motion in its own frame at the fix
        R = T[:3, :3]
        up = self.up if self.up is not None else -R[:, 1]
        up = up / np.linalg.norm(up)
        fwd = R[:, 2] - (R[:, 2] @ up) * up
        fwd = fwd / max(float(np.linalg.norm(fwd)), 1e-12)
        left = np.cross(up, fwd)
        d = self.camera_forward_m
        Rz = R_of_rotvec(up * dyaw)
        base = T[:3, 3] - d * fwd + dx * fwd + dy * left
        out = np.eye(4)
        out[:3, :3] = Rz @ R
        out[:3, 3] = base + d * (Rz @ fwd)
        return out


@dataclass(frozen=True)
class FixedOdometry:
    """The wheel-odometry prior with its unknowns (mount, time offset, scales, drift) held
    fixed: the odometry's motion of the base between the window's frames."""

    prior: OdometryPrior

    name = "odometry_fixed"
    n_params = 0
    start = None
    uses: tuple[str, ...] = ()

    def terms(self, R_cam: F64, t_cam: F64, values: Any) -> Terms:
        pr, st, j = self.prior, self.prior.start, self.prior.j
        u, meas = pr.plane.u, pr.measured(st.offset_s)
        Ra, ta, Rb, tb = R_cam[j], t_cam[j], R_cam[j + 1], t_cam[j + 1]
        q, Jc = pr.camera_terms(Ra, ta, Rb, tb, u, st, meas)
        val, w = pr.weights(q)
        sw = np.sqrt(w)
        return Terms(
            float(val.sum()),
            q * sw[:, None],
            self.prior.j,
            Jc * sw[:, None, None, None],
            None,
            3 * len(self.prior.j),
        )

    def update(self, value: Any, step: F64, values: Any) -> Any:
        return None


class LiveOdometry:
    """The offline odometry prior (:mod:`tagtrail.geometry.joint.odometry`) in the smoother's
    window (a :data:`PriorOf`), its unknowns held: the time offset 0 (:class:`DeadReckoning`
    takes the latency off the stamps), the wheel scale (the median of the steps' ratios) and
    the yaw errors (turn scale, yaw per metre, drift: :func:`~tagtrail.geometry.joint.odometry.
    fit_yaw`, held near none by the offline priors) read against the smoothed history,
    refreshed every ``REFRESH`` frames, within ``SCALE_BOUNDS``, by :meth:`refresh` as a window
    is prepared, through the camera's mount (the drive prior's, fitted on the history's plane;
    else the camera looking along the floor ``camera_forward_m`` ahead of the base). Two wheels
    2-4 % apart read 0.1-0.2 rad per metre: held at 0, that made a room's loop 1.05-1.09 mm
    instead of 0.68-0.74 on 3 of 7 simulated runs, worse than no odometry. A window cannot
    solve the offline prior's seven unknowns (nor a straight drive the lever arm); held, the
    tags correct what the odometry gets wrong, and its robust loss drops slip."""

    REFRESH = 30
    SCALE_BOUNDS = (0.8, 1.25)
    # The newest frame's odometry arrives after it (50 Hz, 2-8 ms late: up to 28 ms uncovered):
    # carried on at its last step's rate (Odometry.extended; 0.4 mm off at 1 m/s^2) the step gets
    # its odometry term. Not further: a slower stream's older rate would mislead more.
    EXTEND_S = 0.04

    def __init__(self, smoother: Smoother, dead: DeadReckoning) -> None:
        self.smoother, self.dead = smoother, dead
        self.scales = (1.0, 1.0)
        self.yaw = (0.0, 0.0)  # the yaw the wheels read per metre (rad/m) and per second
        self._at = -self.REFRESH

    def _plane(self) -> Plane | None:
        """The smoother's plane once the camera has travelled ``plane_after_m``: the odometry
        joins when its unknowns can be read against that much history (a mapping run's plane,
        held from the first frame, let it join with them unread: the rendered circle 0.34 ->
        0.50 mm)."""
        sm = self.smoother
        return sm.plane if sm._travel >= sm.s.plane_after_m else None

    def _odometry(self, t0_ns: int, since_ns: int | None = None) -> Odometry | None:
        """The odometry received (``since_ns``: only from the last sample at or before it on,
        what a window starting then needs), its times (s) from ``t0_ns``; None before 2
        messages."""
        o: Sequence[tuple[int, float, float, float]] = self.dead.odo
        if since_ns is not None:
            tail = []
            for sample in reversed(o):  # the newest first: a window's few, not the 10 s kept
                tail.append(sample)
                if sample[0] <= since_ns:
                    break
            o = tail[::-1]
        if len(o) < 2:
            return None
        a = np.array(o, np.float64)
        t = ((np.array([s[0] for s in o], np.int64) - t0_ns) * 1e-9).astype(np.float64)
        return Odometry(t, a[:, 1], a[:, 2], np.unwrap(a[:, 3]))

    def refresh(self) -> None:
        """Read the scales again when ``REFRESH`` frames have been added since (1-2 ms over
        the history, once a second: in a frame's step it was a thirtieth of the frames' p99)."""
        sm = self.smoother
        plane = self._plane()
        if sm._seen - self._at < self.REFRESH or len(sm.history) < 30 or plane is None:
            return
        self._at = sm._seen
        Rs = np.stack([h[0] for h in sm.history])
        ts = np.stack([h[1] for h in sm.history])
        t_ns = (np.asarray(sm.t_hist) * 1e9).astype(np.int64)
        odo = self._odometry(int(t_ns[0]))
        if odo is None:
            return
        t = (t_ns - t_ns[0]) * 1e-9
        ok = odo.covers(t[:-1]) & odo.covers(t[1:]) & (np.diff(t) <= sm.s.joint.max_gap_s)
        o = odo.relative(t[:-1][ok], t[1:][ok])
        c = -np.einsum("fji,fj->fi", Rs, ts)
        d = np.linalg.norm(np.diff(c, axis=0)[ok], axis=1)
        E = Rs[:-1][ok] @ np.swapaxes(Rs[1:][ok], 1, 2)
        yaw = np.einsum("pi,pi->p", log_so3(E), Rs[:-1][ok] @ plane.n)
        lo, hi = self.SCALE_BOUNDS
        moved = d > 2e-3
        scale = (
            float(np.median(np.hypot(o[moved, 0], o[moved, 1]) / d[moved]))
            if moved.sum() >= 20
            else 1.0
        )
        turn, per_m, drift = fit_yaw(yaw, o[:, 0], np.diff(t)[ok], o[:, 2])
        self.scales = (
            scale if lo <= scale <= hi else 1.0,
            turn if lo <= turn <= hi else 1.0,
        )
        self.yaw = (per_m, drift) if lo <= turn <= hi else (0.0, 0.0)
        self.dead.errors = (*self.scales, *self.yaw)

    def __call__(self, t_s: F64, t_ns: list[int]) -> FixedOdometry | None:
        sm, plane = self.smoother, self._plane()
        if plane is None:
            return None
        odo = self._odometry(t_ns[0], t_ns[0])
        if odo is None:
            return None
        odo = odo.extended(float(t_s[-1]), self.EXTEND_S)
        j = covered_steps(t_s, odo, sm.s.joint.max_gap_s, 0.0)
        if not len(j):
            return None
        state = self._state(plane)
        return FixedOdometry(OdometryPrior(odo, t_s, j, ODOMETRY_SIGMA_M, state, plane))

    def _state(self, plane: Plane) -> OdometryState:
        """The unknowns held: the mount (the smoother's, else the camera looking along the
        floor ``camera_forward_m`` ahead of the base), the scales and yaw errors read."""
        mount = self.smoother.mount
        if mount is None:
            u = plane.u / np.linalg.norm(plane.u)
            fwd = np.array([0.0, 0.0, 1.0]) - u[2] * u  # the optical axis along the floor
            mount = Mount(fwd / np.linalg.norm(fwd), self.dead.camera_forward_m)
        return OdometryState(
            mount,
            scale=self.scales[0],
            yaw_scale=self.scales[1],
            yaw_per_m=self.yaw[0],
            yaw_drift_rps=self.yaw[1],
        )

    def ahead(self, a: _Frame, b: _Frame, start: tuple[F64, F64]) -> _OdometryAhead | None:
        """The next frame's odometry term as far as it goes before the frame (``Smoother.
        _ahead``): what the odometry should read from frame ``b`` to the next at its start
        ``start`` (``cam_T_world``) and its Jacobians; the reading itself waits for the frame
        (:meth:`ahead_rows`). None without a plane (then no term, as :meth:`__call__`)."""
        plane = self._plane()
        if plane is None:
            return None
        st = self._state(plane)
        m, J = step_model(b.R[None], b.t[None], start[0][None], start[1][None], plane.u, st)
        return _OdometryAhead(a.t_ns, b.t_ns, m[0], J[0], st.yaw_drift_rps)

    def ahead_rows(self, ah: _OdometryAhead, t_ns: int, d: F64) -> Rows | None:
        """The odometry's term on the step into the frame at ``t_ns``, taken ahead (``ah``, at
        a start ``d`` (``[w ; v]``) from the frame's: moved on its linear model), as
        :func:`~tagtrail.geometry.joint.newest.prior_rows` gives :meth:`__call__`'s: the same
        reading, whitening and robust weight. None when the odometry does not cover it."""
        h_ns = t_ns - ah.t0_ns
        if not 0 < h_ns * 1e-9 <= self.smoother.s.joint.max_gap_s:
            return None
        got = self.dead.reading(ah.t0_ns, t_ns, ah.since_ns, int(self.EXTEND_S * 1e9))
        if got is None:
            return None
        o = np.array([got])
        sig_t, sig_r = step_sigmas(o, ODOMETRY_SIGMA_M)
        m = ah.m + ah.J[:, 1] @ d
        drift = np.array([ah.drift_rps * (h_ns * 1e-9)])
        q = whiten(m[None], o, drift, sig_t, sig_r)[0]
        w = rho(ODOM_LOSS, float(q @ q) / ODOM_F_SCALE**2)[1]
        k = math.sqrt(float(w)) / np.array([sig_t[0], sig_t[0], sig_r[0]])
        B = np.zeros((3, 12))
        B[:, 6:] = ah.J[:, 0] * k[:, None]  # the frame before (the two before: a, b)
        return q * math.sqrt(float(w)), ah.J[:, 1] * k[:, None], B


@dataclass(frozen=True)
class _OdometryAhead:
    """:meth:`LiveOdometry.ahead`'s: the stamps of the step's frames (``since_ns``: the
    window's first, from which the prior takes its samples), the readings modelled at the
    start ``m (3,)`` and their Jacobians ``J (3, 2, 6)`` on the frame before and the new."""

    since_ns: int
    t0_ns: int
    m: F64
    J: F64
    drift_rps: float


class LivePoses:
    """The localize node's outputs with continuity (module docstring): per camera frame the
    smoothed pose; per odometry message after a fix the dead-reckoned one. Each as
    ``PoseStamped`` on ``pose_key`` and ``PoseWithCovarianceStamped`` on
    ``<prefix>/pose_with_covariance``, with the age of the last tag fix (s) on
    ``<prefix>/fix_age_s`` (``Float64``) and in ``<prefix>/state`` (JSON)."""

    def __init__(
        self,
        smoother: Smoother,
        dead: DeadReckoning,
        pose_key: str,
        prefix: str,
        frame_id: str,
    ) -> None:
        self.smoother, self.dead = smoother, dead
        smoother.extra = (*smoother.extra, LiveOdometry(smoother, dead))
        self.pose_key = pose_key
        self.cov_key = f"{prefix}/pose_with_covariance"
        self.age_key = f"{prefix}/fix_age_s"
        self.state_key = f"{prefix}/state"
        self._pose = codec.PoseStampedEncoder(frame_id)
        self._cov = codec.PoseWithCovarianceEncoder(frame_id)
        self.t_out = -1  # the last stamp published (ns): poses leave in time order
        self.fix_cov = np.full((6, 6), np.nan)
        # poses: of a frame, dead-reckoned, a frame's fix carried to a later pose's stamp
        self.counts = {"tags": 0, "odometry": 0, "carried": 0}

    def keys(self) -> dict[str, str]:
        """Output key → message type."""
        return {
            self.pose_key: codec.POSE_STAMPED,
            self.cov_key: codec.POSE_TYPES["pose_with_covariance"],
            self.age_key: "std_msgs/msg/Float64",
            self.state_key: "json",
        }

    def on_frame(
        self,
        t_ns: int,
        own: F64 | None,
        obs: tuple[I64, F64] | None,
        camera: CameraModel | None,
    ) -> Outputs:
        """A camera frame: its own pose ``own`` (or None) and its mapped tags' corners."""
        if obs is None or not len(obs[0]) or camera is None:
            raise DropError("no_pose", "no mapped tag in the frame")
        got = self.smoother.add(t_ns, obs[0], obs[1], own, camera)
        if got is None or not np.isfinite(got[0]).all():
            raise DropError("no_pose", "no start for the frame")
        T, cov = got
        self.dead.fix = (t_ns, T)
        self.fix_cov = cov
        self._sync_up()
        self.counts["tags"] += 1
        if t_ns > self.t_out:
            return self._out(t_ns, T, cov, 0.0, "tags")
        # poses dead-reckoned to later times left while the frame was on its way (a camera
        # stamped at exposure, its frame 10-30 ms behind the odometry): the new fix carried to
        # the last of them, for the same stamp (never dropped: the fix is news)
        t = self.t_out
        carried = self.dead.pose(t)
        if carried is None:
            return iter(())
        self.counts["carried"] += 1
        return self._out(t, carried, self._carried_cov(carried, t), (t - t_ns) * 1e-9, "tags", True)

    def settle(self) -> None:
        """The smoother's window re-solved after a pose is out (:meth:`Smoother.settle`)."""
        self.smoother.settle()
        self._sync_up()

    def dispatch(self) -> bool:
        """The window's re-solve handed to the background once the pose is out, its result
        taken once back; whether it is still out (:meth:`Smoother.dispatch`)."""
        out = self.smoother.dispatch()
        self._sync_up()
        return out

    def _sync_up(self) -> None:
        """The dead reckoning turns about the smoother's plane once it has one."""
        if self.smoother.plane is not None:
            self.dead.up = self.smoother.plane.n  # fit_plane's n points up (against camera y)

    def wants_start(self, t_ns: int) -> bool:
        """Whether :meth:`on_frame` at ``t_ns`` needs the frame's own pose
        (:meth:`Smoother.wants_start`)."""
        return self.smoother.wants_start(t_ns)

    def on_odometry(self, data: bytes) -> Outputs:
        """One ``nav_msgs/Odometry``: the pose dead-reckoned from the last fix (nothing before
        a fix, or when it is older than the dead reckoning's bound)."""
        try:
            p = codec.decode_pose(data, "odometry")
        except codec.CodecError as err:
            raise DropError("malformed", str(err)) from err
        vals = (p.x, p.y, p.qx, p.qy, p.qz, p.qw)
        if not all(math.isfinite(v) for v in vals):
            raise DropError("non_finite", "odometry pose is not finite")
        yaw = math.atan2(2 * (p.qw * p.qz + p.qx * p.qy), 1 - 2 * (p.qy**2 + p.qz**2))
        t = self.dead.add_odometry(p.sec * 1_000_000_000 + p.nanosec, p.x, p.y, yaw)
        if self.dead.fix is None or t <= self.t_out:
            return iter(())
        T = self.dead.pose(t)
        if T is None:
            return iter(())
        self.counts["odometry"] += 1
        return self._out(t, T, self._carried_cov(T, t), (t - self.dead.fix[0]) * 1e-9, "odometry")

    def _carried_cov(self, T: F64, t_ns: int) -> F64:
        """The covariance of the last fix carried to pose ``T`` at ``t_ns`` by the odometry,
        grown by its own error: 3 % of the distance and 0.3 deg/s (the LIMO's)."""
        assert self.dead.fix is not None
        t_fix, T_fix = self.dead.fix
        cov = self.fix_cov.copy()
        dist = float(np.linalg.norm(T[:3, 3] - T_fix[:3, 3]))
        cov[:3, :3] += np.eye(3) * (0.03 * dist + 1e-4) ** 2
        cov[3:, 3:] += np.eye(3) * (math.radians(0.3) * (t_ns - t_fix) * 1e-9) ** 2
        return cov

    def _out(
        self, t_ns: int, T: F64, cov: F64, age: float, source: str, again: bool = False
    ) -> Outputs:
        """The outputs of a pose (none for a stamp before the last one's, nor the same stamp
        but ``again``: a new fix carried to it), encoded as they are published: the
        ``PoseStamped`` the next node takes leaves first."""
        if t_ns < self.t_out or (t_ns == self.t_out and not again):
            return iter(())
        self.t_out = t_ns
        return self._encoded(
            t_ns, T, cov, age, source, len(self.smoother.frames), self.smoother.iters
        )

    def _encoded(
        self, t_ns: int, T: F64, cov: F64, age: float, source: str, frames: int, iters: int
    ) -> Outputs:
        sec, nsec = divmod(t_ns, 1_000_000_000)
        pq = [*T[:3, 3].tolist(), *quat_xyzw_of(T[:3, :3])]
        yield self.pose_key, self._pose(sec, nsec, *pq)
        yield self.cov_key, self._cov(sec, nsec, pq, np.nan_to_num(cov, nan=-1.0).ravel().tolist())
        yield self.age_key, codec.encode_float64(age)
        state = {
            "stamp_sec": sec,
            "stamp_nanosec": nsec,
            "fix_age_s": age,
            "source": source,
            "position_std_m": _std(cov[:3, :3]),
            "rotation_std_deg": _std(cov[3:, 3:], math.degrees(1.0)),
            "window_frames": frames,
            "iterations": iters,
        }
        yield self.state_key, json.dumps(state).encode()


def _std(c: F64, unit: float = 1.0) -> float | None:
    """RMS over the axes of the standard deviations of covariance ``c (3, 3)``, times ``unit``
    (None: unknown)."""
    v = float(np.trace(c) / 3)
    return math.sqrt(v) * unit if math.isfinite(v) and v >= 0 else None
