"""The joint solve: tag poses and camera poses on the tags' corners, held together by priors.

- :mod:`.problem` -- what is observed (:class:`CornerObservations`), how corners are weighed
  (:class:`Corners`), what a prior gives the solver (:class:`Terms`, :class:`Prior`), the
  :class:`JointResult`;
- :mod:`.motion`, :mod:`.ground`, :mod:`.drive`, :mod:`.odometry` -- the priors (constant
  velocity, ground plane, wheeled drive, wheel odometry), each with its residuals, Jacobians,
  own unknowns and report;
- :mod:`.solver` -- :func:`solve_joint`, Levenberg-Marquardt over the corners and a list of
  priors;
- :mod:`.decide` -- the ground plane's and wheeled drive's ``auto`` decisions
  (:func:`solve_grounded`), taken only on data that can support them;
- :mod:`.start` -- the starting poses (:func:`initial_cameras`, :func:`link_tags`);
- :mod:`.evidence` -- how far the priors moved each frame from its own corners
  (:func:`frame_evidence`; :func:`evidence_rows`, its ``diagnostics.csv`` rows);
- :mod:`.settings` -- :class:`JointSettings`, what a user sets, and the fixed constants;
- :mod:`.setup` -- one dataset's problem from its settings and its solve
  (:func:`corner_problem`, :func:`solve_on_corners`), for ``optimize`` and ``trajectory``;
- :mod:`.track` -- the cameras against a fixed map (:func:`solve_track`, for ``trajectory``;
  :func:`posed_rms_px`, the corner error of poses found frame by frame);
- :mod:`.mapping` -- the map's joint solve from the pose graph (:func:`refine_map`: tags linked
  through the trajectory, the report block; :func:`choose_hypotheses`: rival hypotheses decided).
"""

from __future__ import annotations

from tagtrail.geometry.joint.decide import Travel, solve_grounded, travel
from tagtrail.geometry.joint.drive import DrivePrior, DriveReport, Mount, WheeledDrive
from tagtrail.geometry.joint.evidence import (
    SHIFT_SIGMA_BOUND,
    FrameEvidence,
    evidence_rows,
    frame_evidence,
)
from tagtrail.geometry.joint.ground import GroundPlane, GroundPrior, GroundReport, Plane
from tagtrail.geometry.joint.mapping import MapRefinement, choose_hypotheses, refine_map
from tagtrail.geometry.joint.motion import MotionPrior
from tagtrail.geometry.joint.odometry import (
    Odometry,
    OdometryData,
    OdometryPrior,
    OdometryReport,
    OdometryState,
)
from tagtrail.geometry.joint.problem import (
    CornerObservations,
    CornerRows,
    Corners,
    JointResult,
    Prior,
    Terms,
    corner_observations,
    corner_sigma,
    frame_rms_px,
    observation_rms_px,
)
from tagtrail.geometry.joint.settings import JointSettings
from tagtrail.geometry.joint.setup import (
    CornerProblem,
    Solved,
    bridge,
    corner_problem,
    odometry_input,
    solve_on_corners,
)
from tagtrail.geometry.joint.solver import solve_joint
from tagtrail.geometry.joint.start import initial_cameras, link_tags

__all__ = [
    "SHIFT_SIGMA_BOUND",
    "CornerObservations",
    "CornerProblem",
    "CornerRows",
    "Corners",
    "DrivePrior",
    "DriveReport",
    "FrameEvidence",
    "GroundPlane",
    "GroundPrior",
    "GroundReport",
    "JointResult",
    "JointSettings",
    "MapRefinement",
    "MotionPrior",
    "Mount",
    "Odometry",
    "OdometryData",
    "OdometryPrior",
    "OdometryReport",
    "OdometryState",
    "Plane",
    "Prior",
    "Solved",
    "Terms",
    "Travel",
    "WheeledDrive",
    "choose_hypotheses",
    "bridge",
    "corner_observations",
    "corner_problem",
    "corner_sigma",
    "evidence_rows",
    "frame_evidence",
    "frame_rms_px",
    "initial_cameras",
    "link_tags",
    "observation_rms_px",
    "odometry_input",
    "refine_map",
    "solve_grounded",
    "solve_joint",
    "solve_on_corners",
    "travel",
]
