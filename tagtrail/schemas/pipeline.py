"""Pydantic models of ``pipeline.yaml`` (datasets, stage parameters, a surveyed world, tag sizes
from its files)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationInfo,
    field_validator,
    model_validator,
)

from tagtrail.geometry.se3 import R_from_quat_xyzw, quat_xyzw_from_R
from tagtrail.geometry.survey import Survey, make_survey, parse_survey, parse_tag_sizes
from tagtrail.schemas.ranges import (
    Coordinate,
    QuatComponent,
    TagId,
    TagSize,
    check_expansion,
)

_DATASET_NAME = re.compile(r"[A-Za-z0-9_.-]+")


MAX_NAME = 100  # characters: a name plus tagtrail's prefixes and suffixes stays below NAME_MAX
RESERVED_NAMES = ("last_run.json",)  # tagtrail's own files beside the datasets' folders


def check_dataset_name(name: object) -> str:
    """A dataset name names a folder under ``outputs/``, never a path (SPEC): letters, digits,
    ``_``, ``-``, ``.``; not ``.`` or ``..``; at most 100 characters; not a name tagtrail
    uses for its own files (``last_run.json``, ``.tagtrail…``). Returns the name; raises
    ``ValueError``."""
    shown = repr(name) if not isinstance(name, str) or len(name) <= 120 else repr(name[:60] + "…")
    if not isinstance(name, str) or not _DATASET_NAME.fullmatch(name) or name in (".", ".."):
        raise ValueError(
            f"dataset name {shown} is not allowed: use letters, digits, '_', '-' and '.' "
            "(not '.' or '..'); a dataset name names a folder under outputs/, never a path"
        )
    if len(name) > MAX_NAME:
        raise ValueError(
            f"dataset name {shown} is not allowed: {len(name)} characters, at most "
            f"{MAX_NAME} (it names folders and files)"
        )
    if name in RESERVED_NAMES or name.startswith(".tagtrail"):
        raise ValueError(
            f"dataset name {shown} is not allowed: tagtrail names its own files so "
            "(artifacts/runs/last_run.json, .tagtrail-…); choose another"
        )
    return name


class Topics(BaseModel):
    """Bag topics; ``None`` = found automatically when unambiguous.

    ``odometry``: the wheel odometry (``nav_msgs/msg/Odometry``) that ``extract`` reads; None:
    the bag's one Odometry topic, ``/odom`` when there are several (the LIMO's, or its
    ``/wheel/odom`` remap when that is the only one); ``""`` or ``none``: do not read odometry.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    image: str | None = None
    camera_info: str | None = None
    detections: str | None = None
    odometry: str | None = None

    def odometry_off(self) -> bool:
        """The dataset turns odometry off (``odometry: ""`` or ``none``)."""
        return self.odometry is not None and self.odometry.strip().lower() in ("", "none")


class DatasetConfig(BaseModel):
    """One recording. Paths are resolved against the pipeline file's folder at load time.

    ``source``: a rosbag2 folder (MCAP or sqlite3), a ROS 1 ``.bag``, an image folder, or an
    observations folder (``observations.csv`` of camera→tag poses, as ``tagtrail simulate
    observations`` writes). ``camera``: camera_info YAML (image folders; overrides the bag's).
    ``ground_truth``: folder with SPEC-layout ground truth (default ``<source>/ground_truth`` if
    present). ``inputs``: rewiring, e.g. ``{"trajectory.tag_map": "reference:optimize.tag_map",
    "trajectory.map_report": "reference:optimize.report"}`` localizes this dataset directly
    against the reference map, under the map's joint-solve settings. ``params``: per-stage parameter
    overrides for this dataset only (merged over the pipeline's ``stages:``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    source: Path
    topics: Topics = Field(default_factory=Topics)
    camera: Path | None = None
    ground_truth: Path | None = None
    inputs: dict[str, str] = Field(default_factory=dict)
    params: dict[str, dict[str, Any]] = Field(default_factory=dict)


class PipelineConfig(BaseModel):
    """The whole file: datasets, the name of the reference dataset, and per-stage parameters."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    datasets: dict[str, DatasetConfig]
    reference: str = "reference"
    stages: dict[str, dict[str, Any]] = Field(default_factory=dict)

    @field_validator("datasets")
    @classmethod
    def _names(cls, datasets: dict[str, DatasetConfig]) -> dict[str, DatasetConfig]:
        for name in datasets:
            check_dataset_name(name)
        return datasets


class KnownTag(BaseModel):
    """A known tag pose (survey frame, SPEC tag frame): ``position`` (m), ``orientation``
    quaternion (x, y, z, w; omitted = position only), ``size`` (m, optional)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    position: tuple[Coordinate, Coordinate, Coordinate]
    orientation: tuple[QuatComponent, QuatComponent, QuatComponent, QuatComponent] | None = None
    size: TagSize | None = None

    @field_validator("orientation")
    @classmethod
    def _not_zero(cls, q: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if q is not None and float(np.linalg.norm(q)) < 1e-6:
            raise ValueError("a zero quaternion is no orientation")
        return q


class SurveyConfig(BaseModel):
    """A surveyed world (``optimize.survey``): the map and trajectory are expressed in the frame
    of known tag poses instead of the anchor tag's (``geometry.survey``).

    ``file``: known poses from TagSLAM's ``tagslam.yaml``, a WPILib/PhotonVision field layout
    JSON or a tagtrail ``tag_map.yaml`` (recognised by content; a relative path is taken from the
    pipeline file's folder); ``tags``: known poses inline, ``{<id>: {position: [x, y, z],
    orientation: [qx, qy, qz, qw], size: m}}`` (over the file's); ``use``: only these ids;
    ``position_only``: use only the positions (tape-measured tags); ``model``: ``rigid``
    (default) or ``similarity`` (also a scale: the map's metres are the survey's after it).
    The file is read when the parameters are validated: its known poses are part of them
    (``known``), so editing the file changes the cache key."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    file: str | None = None
    tags: dict[TagId, KnownTag] = Field(default_factory=dict)
    use: tuple[TagId, ...] | None = None
    position_only: bool = False
    model: Literal["rigid", "similarity"] = "rigid"
    format: str = ""
    known: dict[TagId, KnownTag] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _load(self, info: ValidationInfo) -> SurveyConfig:
        """Fill ``known`` (and ``format``) from ``file`` and ``tags``; one-line errors naming
        the file (a relative one is taken from the pipeline file's folder: :func:`_resolve`)."""
        if self.known:  # already loaded (a copy, or a dump validated again)
            return self
        known: dict[int, KnownTag] = {}
        fmt = "inline"
        if self.file is not None:
            fmt, known = _read_known(_resolve(self.file, info))
        known.update(self.tags)
        if self.use is not None:
            absent = sorted(set(self.use) - set(known))
            if absent:
                raise ValueError(
                    f"survey.use names tags {absent} that no known pose gives "
                    f"(known: {sorted(known)})"
                )
            known = {k: v for k, v in known.items() if k in self.use}
        if self.position_only:
            known = {k: v.model_copy(update={"orientation": None}) for k, v in known.items()}
        if not known:
            raise ValueError("survey: no known tag pose (give file: or tags:)")
        object.__setattr__(self, "known", dict(sorted(known.items())))
        object.__setattr__(self, "format", fmt)
        return self

    def survey(self) -> Survey:
        """The known poses as a :class:`~tagtrail.geometry.survey.Survey`."""
        return make_survey(
            [
                (
                    k,
                    v.position,
                    None
                    if v.orientation is None
                    else R_from_quat_xyzw(
                        np.asarray(v.orientation) / np.linalg.norm(v.orientation)
                    ),
                    v.size,
                )
                for k, v in self.known.items()
            ]
        )


def _resolve(file: str, info: ValidationInfo | None) -> Path:
    """A file named by a parameter: a relative path is taken from the validation context's
    ``root`` (the pipeline file's folder, as the datasets' sources are), else the working
    directory."""
    where = Path(file)
    root = (info.context or {}).get("root") if info is not None else None
    if root is not None and not where.is_absolute():
        where = Path(root) / where
    return where


def _read_doc(path: Path, kind: str, param: str) -> Any:
    """The decoded document of a YAML or JSON (``.json``) file; one-line ``ValueError``s
    naming the file, its ``kind`` and the ``param`` that names it."""
    if not path.is_file():
        raise ValueError(
            f"{path}: {kind} file not found ({param}; a relative path is taken "
            "from the pipeline file's folder)"
        )
    try:
        text = path.read_text(encoding="utf-8")
        doc = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, yaml.YAMLError) as err:
        raise ValueError(
            f"{path}: cannot read the {kind} file: {str(err).splitlines()[0]}"
        ) from err
    except RecursionError as err:
        raise ValueError(f"{path}: cannot read the {kind} file: nested too deeply") from err
    try:
        return check_expansion(doc)
    except ValueError as err:
        raise ValueError(f"{path}: {kind} file refused: {err}") from err


def _read_known(path: Path) -> tuple[str, dict[int, KnownTag]]:
    """``(format, known poses)`` of a known-poses file (:func:`geometry.survey.parse_survey`)."""
    doc = _read_doc(path, "known-poses", "survey.file")
    try:
        fmt, sv = parse_survey(doc)
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: {err}") from err
    known = {}
    for k, i in enumerate(sv.ids.tolist()):
        q = None if not sv.full[k] else tuple(float(v) for v in quat_xyzw_from_R(sv.R[k]))
        size = float(sv.size[k]) if np.isfinite(sv.size[k]) else None
        try:
            known[int(i)] = KnownTag(
                position=tuple(float(v) for v in sv.position[k]), orientation=q, size=size
            )
        except ValueError as err:
            raise ValueError(f"{path}: {_first_error(err, f'tag {i}')}") from err
    return fmt, known


class TagSizesFile(BaseModel):
    """Tag sizes from a known-poses file (``pnp.tag_sizes_from: tagslam.yaml``): TagSLAM's
    ``tagslam.yaml`` (each tag's ``size`` or its body's ``default_tag_size``; ``default``: the
    ``default_body``'s, which TagSLAM gives every tag it discovers) or a tagtrail
    ``tag_map.yaml`` (``size``); a WPILib field layout gives none. Written as the file's name (a
    relative path is taken from the pipeline file's folder); the sizes are read when the
    parameters are validated and are part of them, so editing a size in the file changes the
    cache key (and editing anything else in it does not)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    file: str
    format: str = ""
    sizes: dict[TagId, TagSize] = Field(default_factory=dict)
    default: TagSize | None = None

    @model_validator(mode="before")
    @classmethod
    def _name(cls, data: Any) -> Any:
        """``tag_sizes_from: FILE`` is ``{file: FILE}``."""
        return {"file": data} if isinstance(data, str) else data

    @model_validator(mode="after")
    def _load(self, info: ValidationInfo) -> TagSizesFile:
        """Fill ``format``, ``sizes`` and ``default`` from ``file`` (one-line errors naming it)."""
        if self.format:  # already loaded (a copy, or a dump validated again)
            return self
        path = _resolve(self.file, info)
        doc = _read_doc(path, "tag-sizes", "pnp.tag_sizes_from")
        try:
            fmt, sizes = parse_tag_sizes(doc)
            per_id = _SIZES.validate_python(dict(sorted(sizes.per_id.items())))
            default = None if sizes.default is None else _SIZE.validate_python(sizes.default)
        except (ValueError, TypeError) as err:  # a pydantic ValidationError is a ValueError
            raise ValueError(f"{path}: {_first_error(err, 'tag size')}") from err
        object.__setattr__(self, "format", fmt)
        object.__setattr__(self, "sizes", per_id)
        object.__setattr__(self, "default", default)
        return self


_SIZES: TypeAdapter[dict[int, float]] = TypeAdapter(dict[TagId, TagSize])
_SIZE: TypeAdapter[float] = TypeAdapter(TagSize)


def _first_error(err: Exception, what: str) -> str:
    """One short line for a file's value out of range (the first of pydantic's errors)."""
    errors = getattr(err, "errors", None)
    if errors is None:
        return str(err)
    e = errors()[0]
    where = ".".join(str(p) for p in e["loc"])
    return f"{what} {where + ' ' if where else ''}{e['msg'].lower()} (got {e['input']!r:.40})"
