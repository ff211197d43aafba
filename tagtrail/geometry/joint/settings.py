"""The joint solve's settings: one model, set once under ``optimize.joint`` and used by
``optimize`` (the map) and ``trajectory`` (which takes the map's, through ``optimize.report``).

Five settings a user tunes; the rest of the solve is fixed here, each constant with its reason:
they were parameters once, tuned on the simulator and the LIMO and never changed since. This
module imports no other part of the solve: the artifact schemas name :class:`JointSettings`, and
every stage's cache key would otherwise follow the solver's code.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from tagtrail.geometry.robust import LossName

# The corners' robust loss: Huber at 1 px (in units of the corner noise at the median tag): a
# detection more than a pixel off counts linearly, as a mis-fitted corner or a partly occluded
# tag should.
CORNER_LOSS: LossName = "huber"
CORNER_F_SCALE_PX = 1.0
# Levenberg-Marquardt iterations: the solve converges in 5-20 from its starting poses; the cap
# only bounds a pathological start (and is reported when hit).
MAX_ITER = 50
# The corner noise is taken as given (corner_sigma_px), not rescaled to the residuals: with the
# corner re-fit the default 0.5 px is what the corners show, and estimating it lets a few bad
# frames loosen every frame's weight (geometry.joint.Corners.estimate_noise keeps the option).
ESTIMATE_NOISE = False
# The motion prior's angular acceleration density follows the linear one: 30 deg/s^2/sqrt(Hz)
# at 0.1 m/s^2/sqrt(Hz), in proportion: a robot's turn rate changes as readily as its speed
# does, over a third of a metre.
MOTION_ACC, MOTION_ANG_DEG = 0.1, 30.0
# The ground plane: the camera rises or sinks 1 cm and rolls or pitches 1 deg from its plane
# (floor unevenness, suspension) -- a LIMO on an office floor -- and its height wanders by 5 mm
# over a second of driving (5 mm/s/sqrt(Hz) of vertical velocity: a finished floor's 4 mm per
# metre of flatness, driven at the LIMO's 1 m/s).
GROUND_HEIGHT_SIGMA_M, GROUND_TILT_SIGMA_DEG, GROUND_LEVEL_SIGMA = 0.01, 1.0, 0.005
# The wheeled drive: 1 cm/s/sqrt(Hz) of sideways slip beyond the lever arm (1 cm over a second).
DRIVE_LATERAL_SIGMA = 0.01
# The wheel odometry: 1 cm of slip per sqrt(metre) driven, beyond the wheel scale and yaw errors
# the prior solves for (geometry.joint.odometry; the LIMO's wheels on an office floor).
ODOMETRY_SIGMA_M = 0.01


class JointSettings(BaseModel):
    """``optimize.joint``: the joint solve of tag and camera poses on the tags' corners."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, strict=True, allow_inf_nan=False, use_attribute_docstrings=True
    )

    corner_sigma_px: float = Field(0.5, ge=1e-3, le=100.0)
    """Corner noise (px, per coordinate) of a tag of 20 px sides; a smaller, farther or more
    oblique tag's grows as its sides shrink (geometry.joint.corner_sigma). Weighs the corners
    against the priors and scales the reported standard deviations."""
    motion: Annotated[float, Field(ge=1e-6, le=1000.0)] | Literal["none"] = 0.1
    """The constant-velocity motion prior between consecutive frames (geometry.joint.motion):
    its linear acceleration noise density (m/s^2/sqrt(Hz); smaller holds the camera path
    straighter; the angular density follows it in proportion: 30 deg/s^2/sqrt(Hz) at the
    default), or ``none``: frames on their own (then neither ground plane nor drive)."""
    max_gap_s: float = Field(0.5, gt=0.0, le=1e6)
    """Frames further apart than this are not linked by the priors (gaps stay gaps)."""
    ground: Literal["auto", "plane", "none"] = "auto"
    """Ground-plane prior (geometry.joint.ground): ``plane``: the camera rides at a fixed height
    and tilt above a plane (a ground robot), the plane solved with the rest; ``auto``
    (default): the same when the solution without it moves in a plane (a robot, a panning
    tripod), not for a hand-held camera, and not decided on a parked or few-second dataset
    (geometry.joint.decide); ``none``: free 6-dof motion."""
    drive: Literal["auto", "wheeled", "free"] = "auto"
    """Wheeled-drive prior on top of the ground plane (geometry.joint.drive): ``wheeled``: the
    robot moves along its heading, the camera sideways only by its lever arm as it turns (the
    lever arm and the camera's yaw on the robot solved with the rest); ``auto`` (default): the
    same when it costs the corners little (strain below 2), not for a base or camera that
    moves sideways (mecanum, omni wheels, a panning camera); ``free``: no such prior."""
    odometry: Literal["auto", "on", "off"] = "auto"
    """Wheel-odometry prior (geometry.joint.odometry; the dataset's ``extract.odometry``): ties
    consecutive frames by the robot base's motion the wheels measured, solving the time offset
    of its stamps, its scale and yaw errors and the camera's mount; frames with no tag in view
    get a pose from it (up to 10 s from a tag). ``auto`` (default): on when the dataset has
    usable odometry and it agrees with the tags (strain below 2); ``on``: whenever usable;
    ``off``: not used."""

    @field_validator("motion", mode="before")
    @classmethod
    def _motion_word(cls, v: object) -> object:
        """A word other than ``none`` or a number out of range: one plain line, not the
        union's errors."""
        word = isinstance(v, str) and v != "none"
        out = isinstance(v, int | float) and not isinstance(v, bool) and not 1e-6 <= v <= 1000.0
        if word or out:
            raise ValueError(
                f"a number from 1e-6 to 1000 (the acceleration noise density, "
                f"m/s^2/sqrt(Hz)) or none, not {v!r}"
            )
        return v

    @field_validator("odometry", mode="before")
    @classmethod
    def _odometry_word(cls, v: object) -> object:
        """YAML reads a bare ``on`` / ``off`` as true / false: those are the words."""
        return {True: "on", False: "off"}.get(v, v) if isinstance(v, bool) else v

    def motion_sigmas(self) -> tuple[float, float] | None:
        """The motion prior's ``(acc_sigma m/s^2/sqrt(Hz), ang_sigma rad/s^2/sqrt(Hz))``; None
        without it."""
        if self.motion == "none":
            return None
        return self.motion, float(np.radians(MOTION_ANG_DEG * (self.motion / MOTION_ACC)))


# Keys that were flat joint-solve parameters of ``optimize`` and ``trajectory``: where each is
# now (``{joint}``: where the settings are, for the stage that names the old key).
JOINT_OLD_KEYS = {
    "corner_sigma_px": "use {joint}.corner_sigma_px",
    "max_gap_s": "use {joint}.max_gap_s",
    "ground": "use {joint}.ground",
    "drive": "use {joint}.drive",
    "motion": "use {joint}.motion (none, or the acceleration noise density)",
    "motion_acc_sigma": "use {joint}.motion (its value is the acceleration noise density)",
    "motion_ang_sigma_deg": "the angular density follows {joint}.motion (30 deg/s^2/sqrt(Hz) "
    "at 0.1)",
    "corner_noise": "the corner noise is taken as given: {joint}.corner_sigma_px",
    "corner_weighting": "a tag's corner noise grows as its sides shrink, always "
    "({joint}.corner_sigma_px is a 20 px tag's)",
    "joint_loss": "the corners' loss is fixed (Huber at 1 px)",
    "ba_loss": "the corners' loss is fixed (Huber at 1 px)",
    "joint_f_scale_px": "the corners' loss is fixed (Huber at 1 px)",
    "ba_f_scale_px": "the corners' loss is fixed (Huber at 1 px)",
    "joint_max_iter": "the joint solve stops after 50 iterations, fixed",
    "ba_max_iter": "the joint solve stops after 50 iterations, fixed",
    "ground_height_sigma_m": "the ground plane's noise is fixed (1 cm, 1 deg, 5 mm/s/sqrt(Hz))",
    "ground_tilt_sigma_deg": "the ground plane's noise is fixed (1 cm, 1 deg, 5 mm/s/sqrt(Hz))",
    "drive_lateral_sigma": "the wheeled drive's noise is fixed (0.01 m/s/sqrt(Hz))",
}
