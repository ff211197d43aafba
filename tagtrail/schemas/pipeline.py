"""Pydantic models of ``pipeline.yaml`` (datasets and stage parameters)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

_DATASET_NAME = re.compile(r"[A-Za-z0-9_.-]+")


def check_dataset_name(name: object) -> str:
    """A dataset name names a folder under ``outputs/``, never a path (SPEC): letters, digits,
    ``_``, ``-``, ``.``; not ``.`` or ``..``. Returns the name; raises ``ValueError``."""
    if not isinstance(name, str) or not _DATASET_NAME.fullmatch(name) or name in (".", ".."):
        raise ValueError(
            f"dataset name {name!r} is not allowed: use letters, digits, '_', '-' and '.' "
            "(not '.' or '..'); a dataset name names a folder under outputs/, never a path"
        )
    return name


class Topics(BaseModel):
    """Bag topics; ``None`` = found automatically when unambiguous."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    image: str | None = None
    camera_info: str | None = None
    detections: str | None = None


class DatasetConfig(BaseModel):
    """One recording. Paths are resolved against the pipeline file's folder at load time.

    ``source``: a rosbag2 folder (MCAP or sqlite3), a ROS 1 ``.bag``, an image folder, or an
    observations folder (``observations.csv`` of camera→tag poses, as ``tagtrail simulate
    observations`` writes). ``camera``: camera_info YAML (image folders; overrides the bag's).
    ``ground_truth``: folder with SPEC-layout ground truth (default ``<source>/ground_truth`` if
    present). ``inputs``: rewiring, e.g. ``{"trajectory.tag_map": "reference:optimize.tag_map"}``
    localizes this dataset directly against the reference map. ``params``: per-stage parameter
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
