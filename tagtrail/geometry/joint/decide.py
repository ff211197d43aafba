"""The auto decisions of the ground-plane and wheeled-drive priors, taken only on data that can
support them.

``auto`` applies the ground plane where the solution solved without it moves in a plane
(:func:`~.ground.planarity` below ``PLANAR_BOUND``) and the wheeled drive on top of it where the
corners leave its steps unstrained (:func:`~.drive.strain` below ``WHEELED_BOUND``). Neither
question has an answer for a camera that hardly moves (a parked robot: any plane through one
pose fits it, any mount fits no steps) or for a few seconds of data: there ``auto`` is not
decided on the data (:func:`travel`), the caller's ``fallback`` (the reference map's decision)
or none is used, and the report says so in plain words.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.joint.drive import (
    WHEELED_BOUND,
    DrivePrior,
    WheeledDrive,
    drive_report,
    drive_terms,
    fit_mount,
    strain,
)
from tagtrail.geometry.joint.ground import (
    PLANAR_BOUND,
    GroundLevel,
    GroundPlane,
    GroundPrior,
    GroundReport,
    ground_report,
    planarity,
)
from tagtrail.geometry.joint.motion import MotionPrior
from tagtrail.geometry.joint.problem import JointResult, Prior, centres, steps
from tagtrail.geometry.rotations import geodesic_angle

# A dataset on which auto decides: the camera travels MIN_TRAVEL_M (its centres' extent) or
# turns MIN_TURN_DEG, over MIN_DURATION_S at least. The demo's parked queries (1 s, a few mm of
# noise) fall below; every moving recording (simulated scenes, the LIMO's) is far above.
MIN_TRAVEL_M = 0.10
MIN_TURN_DEG = 10.0
MIN_DURATION_S = 2.0

Resolve = Callable[[JointResult, Sequence[Prior]], JointResult]


@dataclass(frozen=True)
class Travel:
    """How much the camera moved: ``extent_m`` (the largest distance of a camera centre from
    their median), ``turn_deg`` (the largest angle of a camera from the median-picked one),
    ``duration_s``."""

    extent_m: float
    turn_deg: float
    duration_s: float

    @property
    def enough(self) -> bool:
        """Whether an auto decision can be taken on it (module docstring)."""
        moved = self.extent_m >= MIN_TRAVEL_M or self.turn_deg >= MIN_TURN_DEG
        return moved and self.duration_s >= MIN_DURATION_S

    def words(self) -> str:
        """The travel in plain words, for a log line."""
        what = (
            "parked"
            if self.extent_m < MIN_TRAVEL_M and self.turn_deg < MIN_TURN_DEG
            else "too short"
        )
        return (
            f"the camera moved {100 * self.extent_m:.1f} cm and turned {self.turn_deg:.1f} "
            f"deg in {self.duration_s:.1f} s ({what}; auto decides on at least "
            f"{100 * MIN_TRAVEL_M:.0f} cm or {MIN_TURN_DEG:.0f} deg over "
            f"{MIN_DURATION_S:.0f} s)"
        )


def travel(R_cam: F64, t_cam: F64, t_s: F64 | None) -> Travel:
    """The :class:`Travel` of cameras ``cam_T_world`` stamped ``t_s`` (s; None: unknown, taken
    as long enough)."""
    if not len(R_cam):
        return Travel(0.0, 0.0, 0.0)
    c = centres(R_cam, t_cam)
    ext = float(np.linalg.norm(c - np.median(c, axis=0), axis=1).max())
    mid = R_cam[len(R_cam) // 2]
    turn = float(np.degrees(geodesic_angle(R_cam, np.broadcast_to(mid, R_cam.shape)).max()))
    dur = float(t_s[-1] - t_s[0]) if t_s is not None and len(t_s) else float("inf")
    return Travel(ext, turn, dur)


def solve_grounded(
    res: JointResult,
    resolve: Resolve,
    ground: GroundPrior,
    mode: str,
    drive: DrivePrior | None = None,
    drive_mode: str = "auto",
    motion: MotionPrior | None = None,
    fallback: tuple[bool, bool] | None = None,
) -> tuple[JointResult, GroundReport]:
    """The ground-plane prior on a solution ``res`` solved without it (with ``cam_cov``):
    ``mode`` ``plane`` applies it, ``auto`` only when the motion is planar; with ``drive`` and
    the ``motion`` prior whose steps it constrains, the wheeled-drive prior is solved with it:
    ``drive_mode`` ``wheeled`` keeps it, ``auto`` only where the corners leave its steps
    unstrained (else the plane alone is solved for). Where the data cannot support an auto
    decision (:func:`travel`), ``fallback`` (ground applied, drive applied: the reference's
    decisions) or none is taken instead. ``resolve(start, priors)`` solves again from
    ``start`` with these priors added. Returns the solution and the :class:`GroundReport`."""
    assert res.cam_cov is not None
    plane, stat = planarity(res.R_cam, res.t_cam, res.cam_cov, ground)
    moved = travel(res.R_cam, res.t_cam, None if motion is None else motion.t_s)
    note = ""
    use_ground, use_drive = mode == "plane", drive_mode == "wheeled"
    if mode == "auto" or drive_mode == "auto":
        if moved.enough:
            use_ground = use_ground or stat < PLANAR_BOUND
        else:
            ref = fallback or (False, False)
            note = moved.words() + (
                ", so the reference's decision is taken"
                if fallback
                else ", too little to decide on"
            )
            use_ground = use_ground or (mode == "auto" and ref[0])
            use_drive = use_drive or (drive_mode == "auto" and ref[1])
    part = GroundPlane(ground, plane)
    level = (
        [GroundLevel(ground, motion.t_s, motion.max_gap_s)]
        if motion is not None and np.isfinite(ground.level_sigma)
        else []
    )
    drive_rep = None
    if use_ground and drive is not None and motion is not None:
        j = steps(motion.t_s, motion.max_gap_s)
        wheels = WheeledDrive(
            drive,
            motion.t_s,
            motion.max_gap_s,
            fit_mount(res.R_cam, res.t_cam, motion.t_s, j, plane),
        )
        driven = resolve(res, [part, *level, wheels])
        q, _, _ = drive_terms(
            driven.R_cam,
            driven.t_cam,
            motion.t_s,
            wheels.j,
            driven.unknowns["ground"],
            driven.unknowns["drive"],
            drive,
            unknowns=False,
        )
        fit = strain(q, drive, driven.variance_factor)
        wheeled = use_drive or (moved.enough and drive_mode == "auto" and bool(fit < WHEELED_BOUND))
        drive_rep = drive_report(
            q, wheels, driven.unknowns["ground"], driven.unknowns["drive"], drive_mode, wheeled, fit
        )
        if wheeled:
            res = driven
    if use_ground and (drive_rep is None or not drive_rep.applied):
        res = resolve(res, [part, *level])
    if use_ground:
        plane = res.unknowns["ground"]
    return res, ground_report(
        res.R_cam, res.t_cam, plane, ground, mode, use_ground, stat, drive_rep, note
    )
