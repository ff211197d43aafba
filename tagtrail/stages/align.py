"""Stage ``align``: bring a query dataset into the reference world with the common tags (§3.2.1).

The query's and the reference's tag maps share some tag ids; a similarity (or rigid) transform
of their in-plane positions is fitted with RANSAC + least squares (Eqs. 3.9–3.10), or a 3-D
Sim(3)/SE(3) one (``model: sim3|se3``). A planar transform acts in the plane only: in-plane
coordinates are scaled, rotated and shifted, the normal coordinate is kept, orientations are
rotated about the plane normal (headings gain the planar angle). ``align: auto`` aligns when
there are enough common tags and otherwise keeps the query frame, with a warning.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field

from tagtrail.errors import DataError
from tagtrail.geometry import se3
from tagtrail.geometry.arrays import F64
from tagtrail.geometry.reference_path import Plane, reference_plane
from tagtrail.geometry.registration import MODELS, Alignment, ransac_align, world_transform
from tagtrail.schemas.artifacts import poses
from tagtrail.schemas.documents import AlignmentBlock
from tagtrail.schemas.ranges import Scale
from tagtrail.stages.base import StageParams

log = logging.getLogger(__name__)

INPUTS = {
    "tag_map": "optimize.tag_map",
    "ref_tag_map": "reference:optimize.tag_map",
    "trajectory": "smooth.trajectory",
    "ref_trajectory": "reference:smooth.trajectory",
}
OUTPUTS = ("alignment", "trajectory")
SCOPE = "query"


class Params(StageParams):
    """``align``: auto | none | tags; ``model``: similarity | rigid (planar), sim3 | se3 (3-D)."""

    align: Literal["auto", "none", "tags"] = "auto"
    """Bring the query into the reference world with their common tags: ``tags`` (always),
    ``none`` (keep the query's frame), ``auto`` (when there are enough common tags, else a
    warning)."""
    model: Literal["similarity", "rigid", "se3", "sim3"] = "similarity"
    """The transform fitted: ``similarity`` / ``rigid`` in the plane (with / without scale),
    ``sim3`` / ``se3`` in 3-D."""
    plane: Literal["auto", "xz", "xy", "yz"] = "auto"
    """Plane of the planar models (SPEC Conventions; ``auto``: fitted to the reference cameras)."""
    ransac_threshold_m: float = Field(0.10, gt=0, le=100.0)
    """RANSAC inlier threshold (m) on a common tag's position after the fit."""
    ransac_iterations: int = Field(300, ge=1, le=1_000_000)
    """RANSAC iterations."""
    seed: int = Field(0, ge=0, le=2**32 - 1)
    """Seed of RANSAC's random samples (a fixed seed: the same fit every run)."""
    allow_scale: bool = False  # accept a fitted scale outside scale_range
    """Accept a fitted scale outside ``scale_range`` (else the stage fails: a scale far from 1
    usually means a wrong tag size)."""
    scale_range: tuple[Scale, Scale] = (0.9, 1.1)
    """Fitted scales accepted without ``allow_scale`` (min, max)."""


def common_tags(tag_map: pd.DataFrame, ref_tag_map: pd.DataFrame) -> tuple[F64, F64, list[int]]:
    """World positions ``(n, 3)`` of the tags both maps hold (query, reference) and their ids."""
    q = tag_map.drop_duplicates("tag_id").set_index("tag_id")
    r = ref_tag_map.drop_duplicates("tag_id").set_index("tag_id")
    ids = sorted(set(q.index.astype(int)) & set(r.index.astype(int)))
    cols = ["x_m", "y_m", "z_m"]
    return q.loc[ids, cols].to_numpy(np.float64), r.loc[ids, cols].to_numpy(np.float64), ids


def transform_trajectory(traj: pd.DataFrame, A: F64, R: F64) -> pd.DataFrame:
    """The trajectory with positions mapped by ``A (4, 4)`` and rotations by ``R (3, 3)``."""
    out = traj.copy()
    if len(out) == 0:
        return out
    P, Rc = poses(traj)
    out[["x_m", "y_m", "z_m"]] = P @ A[:3, :3].T + A[:3, 3]
    out[["qx", "qy", "qz", "qw"]] = se3.quat_xyzw_from_R(R @ Rc)
    return out


def alignment_block(model: str, al: Alignment | None, n_common: int, dim: int) -> AlignmentBlock:
    """SPEC ``summary.json`` "alignment" block (``translation`` in plane (u, v) or world, m)."""
    if al is None:
        return AlignmentBlock(
            model="none",
            scale=1.0,
            rotation_deg=0.0,
            translation=[0.0] * dim,
            inliers=0,
            common_tags=n_common,
            rms_m=None,
        )
    return AlignmentBlock(
        model=model,
        scale=al.scale,
        rotation_deg=al.rotation_deg,
        translation=[float(v) for v in al.t],
        inliers=int(al.inliers.sum()),
        common_tags=n_common,
        rms_m=al.rms_m,
    )


def estimate(
    tag_map: pd.DataFrame, ref_tag_map: pd.DataFrame, plane: Plane | None, params: Params
) -> tuple[Alignment | None, int]:
    """The query→reference alignment (None when not aligning) and the number of common tags."""
    dim, _ = MODELS[params.model]
    q, r, ids = common_tags(tag_map, ref_tag_map)
    if params.align == "none":
        return None, len(ids)
    if len(ids) < dim:
        msg = (
            f"only {len(ids)} common tag(s) between the query and the reference maps "
            f"({params.model} alignment needs {dim})"
        )
        if params.align == "tags":
            raise DataError(f"{msg}: check that both recordings saw the same tags, or align=none")
        log.warning("align: %s; keeping the query's own frame (align=none)", msg)
        return None, len(ids)
    if dim == 2:
        if plane is None:
            raise DataError(f"{params.model} alignment needs a plane")
        q, r = plane.to_uv(q), plane.to_uv(r)
    al = ransac_align(
        q, r, params.model, params.ransac_threshold_m, params.ransac_iterations, params.seed
    )
    return al.check_scale(*params.scale_range, allow=params.allow_scale), len(ids)


def run(
    tag_map: pd.DataFrame,
    ref_tag_map: pd.DataFrame,
    trajectory: pd.DataFrame,
    ref_trajectory: pd.DataFrame,
    params: Params,
) -> dict[str, Any]:
    """Align the query ``trajectory`` to the reference world (Eqs. 3.9–3.10).

    Returns ``alignment`` (SPEC "alignment" block) and ``trajectory`` (the query's world_T_cam in
    the reference world; other columns kept).
    """
    dim, _ = MODELS[params.model]
    plane = None
    if dim == 2 and params.align != "none":
        plane = reference_plane(params.plane, *poses(ref_trajectory))
    al, n_common = estimate(tag_map, ref_tag_map, plane, params)
    if al is None:
        return {
            "alignment": alignment_block(params.model, None, n_common, dim),
            "trajectory": trajectory.copy(),
        }
    A, R = world_transform(al, plane)
    return {
        "alignment": alignment_block(params.model, al, n_common, dim),
        "trajectory": transform_trajectory(trajectory, A, R),
    }
