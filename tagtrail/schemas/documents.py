"""Pydantic models of the stages' JSON artifacts: one model per document, validated when a stage
returns it and when the store loads it, so no consumer re-parses a dict by hand.

``extract.camera`` is the exception in what consumers see: stages receive the
:class:`~tagtrail.geometry.camera.CameraModel` itself (None for sources without a camera).
The serialised form of every document is ``model_dump(mode="json")`` (keys sorted on disk).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError

from tagtrail.errors import ArtifactError
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.joint.drive import DriveReport
from tagtrail.geometry.joint.settings import JointSettings


class Document(BaseModel):
    """Base of every JSON artifact: unknown keys refused, immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    def __getitem__(self, key: str) -> Any:
        """Read access by key, as for the JSON file (``doc["anchor_id"]``)."""
        if key not in type(self).model_fields:
            raise KeyError(key)
        return getattr(self, key)

    def __contains__(self, key: object) -> bool:
        return key in type(self).model_fields

    def get(self, key: str, default: Any = None) -> Any:
        return getattr(self, key) if key in type(self).model_fields else default


class CameraDoc(Document):
    """``extract.camera``: as ``sensor_msgs/CameraInfo`` (K row-major, D in ROS order)."""

    width: int
    height: int
    distortion_model: str
    K: list[float]
    D: list[float]

    def model(self) -> CameraModel:
        return CameraModel.from_dict(self.model_dump())

    @classmethod
    def of(cls, camera: CameraModel) -> CameraDoc:
        return cls.model_validate(camera.to_dict())


class MountDoc(Document):
    """``extract.mount``: the frames of the robot that carries the camera. ``odom_frame`` /
    ``base_frame``: the odometry's ``frame_id`` / ``child_frame_id``; ``camera_frame``: the
    CameraInfo's (else the detections' or images') ``header.frame_id``; ``base_T_camera``: the
    camera's pose in the base frame, ``[x, y, z, qx, qy, qz, qw]`` (m), composed from the
    recording's ``/tf_static`` (``source: tf_static``), or null when no chain links the two
    frames (``source`` null: solve for it, or give it). ``topic``: the odometry topic read
    (null: none); ``covariance``: what its pose covariance is worth -- ``varying`` (it changes
    along the recording), ``constant`` (one value throughout: a placeholder, like the LIMO's),
    ``unusable`` (all zero or not finite: the variances are NaN), null without odometry."""

    odom_frame: str | None = None
    base_frame: str | None = None
    camera_frame: str | None = None
    base_T_camera: Annotated[list[float], Field(min_length=7, max_length=7)] | None = None
    source: Literal["tf_static"] | None = None
    topic: str | None = None
    covariance: Literal["varying", "constant", "unusable"] | None = None


class DroppedTag(Document):
    tag_id: int
    n_obs: int


class WeakLink(Document):
    """A bridge of the tag graph seen together in fewer than 3 frames."""

    tag_i: int
    tag_j: int
    n_frames: int


class RivalPair(Document):
    """A tag pair whose second-best solution combination is supported nearly as well."""

    tag_i: int
    tag_j: int
    support_ratio: float


class TagGraph(Document):
    """``edges.graph``: the anchor (world) tag, the mapped tags, what was dropped and why."""

    anchor_id: int
    tags: list[int]
    dropped: list[DroppedTag]
    n_components: int
    weak_links: list[WeakLink]
    second_solution_edges: int = 0
    """Co-observations whose edge uses a tag's second IPPE solution (``edges.branches``)."""
    rival_pairs: list[RivalPair] = []
    """Pairs with a close second hypothesis (edges rows with ``hypothesis`` 1)."""
    ambiguous_kept: int = 0
    """Ambiguous observations kept (down-weighted) because without them the graph splits."""


class GroundSummary(Document):
    """The ground-plane prior (``optimize.report.bundle.ground``, geometry.joint.ground): the mode,
    whether it was applied, the planarity figure that decided ``auto`` (median normalised
    chi^2 per degree of freedom of the solution without it; planar below 2), the plane's
    normal in the world, the camera's tilt to it (deg from its y axis), the RMS height (m) and
    tilt (deg) of the frames off it, the frames beyond the robust loss's scale, and the
    wheeled-drive prior on top of it."""

    mode: Literal["auto", "plane"]
    applied: bool
    planarity: float
    normal: list[float]
    camera_tilt_deg: float
    height_rms_m: float
    tilt_rms_deg: float
    frames_off: int
    drive: DriveReport | None = None
    """The wheeled-drive prior on top of it (geometry.joint.drive.DriveReport: the model is the
    document)."""
    note: str = ""
    """Why ``auto`` was not decided on this dataset (a parked or few-second one), in words."""
    offset_m: float | None = None
    """The plane's offset ``n . c`` of the camera centres (m; None in reports before it)."""
    normal_camera: list[float] | None = None
    """The normal seen from the camera (unit; None in reports before it)."""

    def known(self) -> KnownGround | None:
        """The ``ground.json`` of this block: its plane and, when the wheeled-drive prior held
        it, the mount; None when the prior was not applied (or an older report)."""
        if not self.applied or self.offset_m is None or self.normal_camera is None:
            return None
        d = self.drive if self.drive is not None and self.drive.applied else None
        fwd = None if d is None else d.forward_camera
        return KnownGround(
            normal=self.normal,
            offset_m=self.offset_m,
            normal_camera=self.normal_camera,
            forward_camera=None if fwd is None else list(fwd),
            lever_m=None if fwd is None or d is None else d.lever_m,
        )


class OdometrySummary(Document):
    """The wheel-odometry prior (``optimize.report.bundle.odometry``, geometry.joint.odometry):
    the mode, whether it was applied and why (plain words), the topic, the time offset it
    solved (ms; the odometry's stamps later than the frames' by it), the distance scale, turn
    scale, yaw per metre (deg/m) and yaw drift (deg/s) it found, the camera's mount (lever arm
    ahead of the base m, yaw from the robot's forward axis deg, where it came from), the strain
    that decided ``auto`` (its robust chi^2 per degree of freedom in the solution's variance
    factor; agreeing below 2), the fraction of steps down-weighted as slip (beyond the robust
    loss's scale), the steps it tied and the frames with no tag in view it posed, and notes
    (a warning line: the odometry unusable, a recorded mount the motion disagrees with). NaN:
    not found (the prior off)."""

    mode: Literal["auto", "on", "off"]
    applied: bool
    why: str
    topic: str
    offset_ms: float
    scale: float
    yaw_scale: float
    yaw_per_m_deg: float
    yaw_drift_dps: float
    lever_m: float
    camera_yaw_deg: float
    mount_source: str
    strain: float
    down_weighted: float
    steps: int
    frames_odometry_only: int
    notes: list[str] = []


class BundleSummary(Document):
    """The joint solve's figures (``optimize.report.bundle``): frames posed (of them with a single
    tag, and held by the motion prior), frames started from a tag's second IPPE solution, tags
    the pose graph left out and the trajectory linked to the map, the
    whitened cost and its variance factor (cost per degree of freedom, 1 when the corner noise is
    as assumed), the corner noise it used (px, median; estimated from the residuals by default),
    corner reprojection RMS / p95 (px)."""

    frames: int
    single_tag_frames: int
    observations: int
    motion_prior_frames: int
    ippe_second_solution: int
    linked_tags: list[int]
    rival_pairs_flipped: list[list[int]] = []
    """Tag pairs whose rival hypothesis the frames' continuity preferred (``edges.rival_pairs``)."""
    iterations: int
    converged: bool
    cost: float
    variance_factor: float
    corner_sigma_px: float
    rms_px: float
    p95_px: float
    ground: GroundSummary | None = None
    odometry: OdometrySummary | None = None


def _unit3(v: list[float]) -> list[float]:
    """A finite 3-vector of non-zero length, made unit."""
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise ValueError(f"not a finite 3-vector: {v}")
    n = math.sqrt(sum(x * x for x in v))
    if n < 1e-9:
        raise ValueError("a zero vector")
    return [x / n for x in v]


Unit3 = Annotated[list[float], AfterValidator(_unit3)]


class KnownGround(Document):
    """``ground.json`` (``optimize``'s export, SPEC-ADDITIONS): the ground plane of the camera
    centres and the camera's mount on the robot that the mapping run's joint solve found —
    what ``stream localize --smooth`` holds from a run's first frame instead of fitting them
    to its own history first. The plane: its normal in the map's world (unit, up), its offset
    ``n . c`` (m) and the normal seen from the camera; the mount (null when the wheeled-drive
    prior was not applied): the robot's forward axis in the camera frame and the camera's
    distance ahead of the turning centre (m)."""

    normal: Unit3
    offset_m: float = Field(allow_inf_nan=False)
    normal_camera: Unit3
    forward_camera: Unit3 | None = None
    lever_m: float | None = Field(None, allow_inf_nan=False)


class SurveyTag(Document):
    """A known tag's residual after the survey fit (rotation None: position-only)."""

    tag_id: int
    res_pos_m: float
    res_rot_deg: float | None


class SurveySummary(Document):
    """``optimize.report.survey``: the fit that put the map in the surveyed world and the
    residuals at the known tags."""

    source: str
    format: str
    model: str
    scale: float
    rotation_deg: float
    translation_m: list[float]
    tags: list[int]
    missing: list[int]
    res_pos_rms_m: float
    res_pos_max_m: float
    res_rot_rms_deg: float | None
    per_tag: list[SurveyTag]


class PlacedComponent(Document):
    """A part of the tag graph not linked to the anchor, solved on its own and placed in the
    surveyed world by the known tags it holds."""

    anchor_id: int
    tags: list[int]
    survey: SurveySummary | None


class OptimizeReport(Document):
    """``optimize.report``: the pose graph solve (Eq. 3.4-3.7) and the optional refinement (of
    the anchor's component), and the other components a surveyed world placed."""

    anchor_id: int
    loss: str
    f_scale: float
    cost: float
    nfev: int
    status: int
    rms_t_m: float
    rms_r_deg: float
    method: Literal["joint", "pairwise"]
    edges_rebuilt: int = 0
    """Edges rebuilt from the IPPE solutions the map agrees with (``optimize.branch_check``)."""
    bundle: BundleSummary | None
    survey: SurveySummary | None = None
    components: list[PlacedComponent] = []
    joint: JointSettings | None = None
    """The joint solve's settings the map was made with (``optimize.joint``): what
    ``trajectory`` solves with (its ``map_report`` input)."""


class ErrorStats(Document):
    """Statistics of errors (None when there are none)."""

    mean: float | None
    median: float | None
    rmse: float | None
    p95: float | None
    max: float | None
    min: float | None


class ErrorBlock(Document):
    n: int
    coverage: float
    position_m: ErrorStats
    angle_deg: ErrorStats


class GaugeFree(Document):
    """The errors after the best rigid fit of the map to ground truth."""

    rotation_deg: float
    translation_m: float
    trajectory: ErrorBlock
    tags: ErrorBlock


class Evaluation(Document):
    """``eval.evaluation``: errors against ground truth (``evaluation.json``)."""

    anchor_id: int | None
    gt_anchor_id: int | None
    trajectory: ErrorBlock
    trajectory_raw: ErrorBlock
    tags: ErrorBlock
    gauge_free: GaugeFree | None


class AlignmentBlock(Document):
    """``align.alignment``, the SPEC ``summary.json`` "alignment" block (``translation`` in the
    plane's (u, v) or the world's (x, y, z), m)."""

    model: str
    scale: float
    rotation_deg: float
    translation: list[float]
    inliers: int
    common_tags: int
    rms_m: float | None


class RelocStats(Document):
    mean: float | None
    median: float | None
    p90: float | None
    p95: float | None
    max: float | None
    rmse: float | None


class Summary(Document):
    """``report.summary``, SPEC ``summary.json``."""

    mode: Literal["trajectory", "point"]
    plane: str
    n: int
    distance_m: RelocStats
    abs_heading_error_deg: RelocStats
    alignment: AlignmentBlock
    # which association chose the reference point (trajectory mode: progress | nearest; point
    # mode: the nearest point of the polyline) and which heading phi compares with (point
    # mode: the nearest segment's; trajectory mode: the centred difference at the sample)
    association: Literal["progress", "nearest", "polyline"] = "nearest"
    ref_heading: Literal["segment", "sample"] = "sample"
    cross_track_m: RelocStats | None = None  # signed, > 0 left of the path seen from n
    abs_cross_track_m: RelocStats | None = None
    lost: int = 0  # rows with no reference point within report.lost_m, or re-acquired


DOCUMENTS: dict[str, type[Document]] = {
    "extract.camera": CameraDoc,
    "extract.mount": MountDoc,
    "edges.graph": TagGraph,
    "optimize.report": OptimizeReport,
    "eval.evaluation": Evaluation,
    "align.alignment": AlignmentBlock,
    "report.summary": Summary,
}


def dump(name: str, value: Any) -> dict[str, Any]:
    """The JSON form of artifact ``name`` (``stage.output``): a model, a dict (validated), or,
    for ``extract.camera``, a ``CameraModel`` or None (``{}``)."""
    if name == "extract.camera" and (value is None or isinstance(value, CameraModel)):
        return {} if value is None else CameraDoc.of(value).model_dump(mode="json")
    model = DOCUMENTS.get(name)
    if isinstance(value, BaseModel):
        if model is not None and not isinstance(value, model):
            raise TypeError(
                f"artifact {name} must be a {model.__name__}, not {type(value).__name__}"
            )
        return value.model_dump(mode="json")
    if not isinstance(value, dict):
        raise TypeError(
            f"artifact {name} is a {type(value).__name__}; a stage returns "
            "DataFrames, documents or dicts"
        )
    return value if model is None else model.model_validate(value).model_dump(mode="json")


def load(name: str, data: Any) -> Any:
    """Artifact ``name`` from its JSON form: its model (``extract.camera``: a ``CameraModel`` or
    None), or the plain dict of an undeclared document."""
    model = DOCUMENTS.get(name)
    if model is None:
        return data
    if name == "extract.camera" and data == {}:
        return None
    try:
        doc = model.model_validate(data)
    except ValidationError as err:
        raise ArtifactError(
            f"artifact {name} does not fit its model: "
            f"{err.errors()[0]['loc']} {err.errors()[0]['msg']}"
        ) from err
    return doc.model() if isinstance(doc, CameraDoc) else doc
