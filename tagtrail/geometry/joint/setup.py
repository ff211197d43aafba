"""The joint solve of one dataset from its settings: written once, for ``optimize`` (the map and
the cameras) and ``trajectory`` (the cameras against a fixed map).

:func:`corner_problem` builds the observations (frames in time order), the corner model and the
motion prior; :func:`solve_on_corners` starts every frame at the IPPE solution its neighbours
agree with (:func:`~.start.initial_cameras`), solves, then takes the ground-plane and
wheeled-drive decisions (:func:`~.decide.solve_grounded`). Frames whose stamps are only a file
order (``timed`` False) get no prior and are linked to no other frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.joint.decide import solve_grounded
from tagtrail.geometry.joint.drive import DrivePrior
from tagtrail.geometry.joint.ground import GroundPrior, GroundReport
from tagtrail.geometry.joint.motion import MotionPrior
from tagtrail.geometry.joint.problem import (
    CornerObservations,
    CornerRows,
    Corners,
    JointResult,
    Prior,
    corner_sigma,
)
from tagtrail.geometry.joint.settings import (
    CORNER_F_SCALE_PX,
    CORNER_LOSS,
    DRIVE_LATERAL_SIGMA,
    ESTIMATE_NOISE,
    GROUND_HEIGHT_SIGMA_M,
    GROUND_TILT_SIGMA_DEG,
    MAX_ITER,
    JointSettings,
)
from tagtrail.geometry.joint.solver import solve_joint
from tagtrail.geometry.joint.start import initial_cameras

GROUND = GroundPrior.of(GROUND_HEIGHT_SIGMA_M, GROUND_TILT_SIGMA_DEG)
DRIVE = DrivePrior(DRIVE_LATERAL_SIGMA)


@dataclass(frozen=True)
class CornerProblem:
    """One dataset's joint problem: the observations ``ob`` (frames in time order), each
    frame's stamp ``t_ns (F,)`` and ``t_s (F,)`` (s from the first), both IPPE solutions of
    each observation ``cam_T_tag (O, 2, 4, 4)``, the corner model, the motion prior (None: off,
    or stamps that are a file order) and the gap beyond which frames are not linked (s)."""

    ob: CornerObservations
    t_ns: I64
    t_s: F64
    cam_T_tag: F64
    corners: Corners
    motion: MotionPrior | None
    max_gap_s: float


def corner_problem(
    rows: CornerRows,
    tag: I64,
    camera: CameraModel,
    settings: JointSettings,
    timed: bool,
    priors: bool = True,
) -> CornerProblem:
    """The :class:`CornerProblem` of ``rows``, ``tag`` their tags' indices in the map;
    ``timed``: the stamps are capture times; ``priors`` False: each frame on its own corners
    (no prior), the frames' continuity still choosing their start."""
    corners_px = rows.corners_px
    ob, stamps = rows.observations(tag, camera)
    t_s = (stamps - stamps[0]) * 1e-9
    corners = Corners(
        camera.focal_px,
        corner_sigma(corners_px, settings.corner_sigma_px),
        CORNER_LOSS,
        CORNER_F_SCALE_PX,
        ESTIMATE_NOISE,
    )
    sig = settings.motion_sigmas() if timed and priors else None
    motion = None if sig is None else MotionPrior(t_s, *sig, settings.max_gap_s)
    return CornerProblem(
        ob, stamps, t_s, rows.cam_T_tag, corners, motion, settings.max_gap_s if timed else 0.0
    )


@dataclass(frozen=True)
class Solved:
    """A joint solution, the start each frame took (``choice (F,)``: observation index * 2 +
    IPPE solution) and the ground-plane prior's report (None when it was not considered: no
    motion prior, or ``ground: none``)."""

    res: JointResult
    choice: I64
    ground: GroundReport | None


def solve_on_corners(
    pb: CornerProblem,
    W: F64,
    free: np.ndarray,
    settings: JointSettings,
    *,
    max_iter: int = MAX_ITER,
    covariance: bool = True,
    decide: bool = True,
    fallback: tuple[bool, bool] | None = None,
) -> Solved:
    """Solve ``pb`` from the map ``W (T, 4, 4)`` (``world_T_tag``; ``free (T,)`` the tags
    solved with the cameras), each frame started at the IPPE solution its neighbours agree
    with; ``decide``: then the ground-plane and wheeled-drive priors as ``settings`` say
    (``fallback``: the reference's decisions, for data too short or too still to decide on)."""
    cams, choice, _ = initial_cameras(
        W[pb.ob.tag],
        pb.cam_T_tag,
        pb.ob,
        pb.t_s,
        px_per_unit=pb.corners.px_per_unit,
        max_gap_s=pb.max_gap_s,
    )
    base: list[Prior] = [] if pb.motion is None else [pb.motion]

    def again(start: JointResult, extra: Sequence[Prior]) -> JointResult:
        return solve_joint(
            start.R_tag,
            start.t_tag,
            start.R_cam,
            start.t_cam,
            pb.ob,
            free,
            pb.corners,
            [*base, *extra],
            max_iter=max_iter,
            covariance=covariance,
        )

    res = solve_joint(
        W[:, :3, :3],
        W[:, :3, 3],
        cams[:, :3, :3],
        cams[:, :3, 3],
        pb.ob,
        free,
        pb.corners,
        base,
        max_iter=max_iter,
        covariance=covariance,
    )
    ground = None
    if decide and settings.ground != "none" and pb.motion is not None:
        res, ground = solve_grounded(
            res,
            again,
            GROUND,
            settings.ground,
            None if settings.drive == "free" else DRIVE,
            settings.drive,
            pb.motion,
            fallback,
        )
    return Solved(res, choice, ground)
