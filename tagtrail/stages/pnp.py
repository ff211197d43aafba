"""Stage ``pnp``: tag corners → camera→tag poses ``cam_T_tag``, both IPPE solutions.

Tag frame (SPEC): origin at the tag centre, x right, y up, z out of the face; the detector's
corners 0..3 sit at (−s/2, −s/2), (s/2, −s/2), (s/2, s/2), (−s/2, s/2). OpenCV's
``SOLVEPNP_IPPE_SQUARE`` ignores the object points' values and assumes its canonical square
(−s/2, s/2), (s/2, s/2), (s/2, −s/2), (−s/2, −s/2) — the SPEC corners 3, 2, 1, 0 — so the
corners are passed in that order and the pose comes out in the SPEC frame directly.

Corners are undistorted to normalized coordinates with the camera model (all distortion models),
then solved with an identity camera matrix for a unit square; IPPE is scale-covariant, so the
translation is scaled by each tag's size. ``reproj_px`` = RMS over the 4 corners of the pixel
distance between the measured corners and the corners projected (with distortion) from the pose;
solutions are ordered best first; ``ambiguity`` = reproj_px / alt_reproj_px (near 1: ambiguous).
Observations given by the source (``extract.observations``) pass through with NaN errors.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from pydantic import Field, field_validator

from tagtrail.errors import SourceError
from tagtrail.geometry import se3
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.ippe import ambiguity, solve_ippe
from tagtrail.schemas.artifacts import ALT_POSE_COLS as ALT_COLS
from tagtrail.schemas.artifacts import CORNER_COLS, POSE_COLS, columns
from tagtrail.schemas.pipeline import TagSizesFile
from tagtrail.schemas.ranges import TagId, TagSize
from tagtrail.stages.base import StageParams

log = logging.getLogger("tagtrail.pnp")

INPUTS = {
    "detections": "extract.detections",
    "camera": "extract.camera",
    "extracted": "extract.observations",
}
OUTPUTS = ("observations",)
COLUMNS = columns("pnp.observations")


class Params(StageParams):
    """Tag edge length (black square, metres), with per-id overrides, from a known-poses file
    too."""

    tag_size: float = Field(0.16, ge=1e-3, le=10.0)
    """The size of tags that neither ``tag_sizes`` nor ``tag_sizes_from`` gives."""
    tag_sizes: dict[TagId, TagSize] = Field(default_factory=dict)
    """Per-id sizes, over the file's."""
    tag_sizes_from: TagSizesFile | None = None
    """A ``tagslam.yaml`` or ``tag_map.yaml`` whose sizes are used (its per-tag sizes, then
    its default for the other tags: TagSLAM's ``default_body``'s ``default_tag_size``);
    schemas.pipeline.TagSizesFile."""

    @field_validator("tag_sizes")
    @classmethod
    def _positive(cls, v: dict[int, float]) -> dict[int, float]:
        bad = {k: s for k, s in v.items() if not s > 0}
        if bad:
            raise ValueError(f"tag sizes must be > 0 m, got {bad}")
        return v

    def sizes(self, tag_ids: NDArray[Any]) -> NDArray[np.float64]:
        """Edge length per tag id, (n,) m: ``tag_sizes``, else the file's size of the id, else
        the file's default, else ``tag_size``."""
        file = self.tag_sizes_from
        sizes = {**(file.sizes if file is not None else {}), **self.tag_sizes}
        fallback = file.default if file is not None and file.default is not None else self.tag_size
        ids, inv = np.unique(np.asarray(tag_ids, dtype=np.int64), return_inverse=True)
        per_id = np.array([sizes.get(int(t), fallback) for t in ids], np.float64)
        return per_id[inv.reshape(-1)]


def run(
    detections: pd.DataFrame,
    camera: CameraModel | None,
    extracted: pd.DataFrame,
    params: Params,
) -> dict[str, pd.DataFrame]:
    """Poses of every detection plus the source's own observations; see the module docstring."""
    parts = []
    if len(detections):
        if camera is None:
            raise SourceError(
                "extract.camera is empty: the source has no camera intrinsics for its detections"
            )
        parts.append(_solve_table(detections, camera, params))
    if len(extracted):
        parts.append(_passthrough(extracted, params))
    if not parts:
        return {"observations": _typed(pd.DataFrame({c: np.zeros(0) for c in COLUMNS}))}
    out = pd.concat(parts, ignore_index=True) if len(parts) > 1 else parts[0]
    out = out.sort_values(["frame_idx", "tag_id"], kind="stable").reset_index(drop=True)
    return {"observations": _typed(out)}


def _solve_table(det: pd.DataFrame, camera: CameraModel, params: Params) -> pd.DataFrame:
    corners = det[CORNER_COLS].to_numpy(np.float64).reshape(-1, 4, 2)
    tag_id = det["tag_id"].to_numpy(np.int32)
    sizes = params.sizes(tag_id)
    T, err = solve_ippe(corners, sizes, camera)
    good = np.isfinite(err[:, 0])
    if not good.all():
        log.warning(
            "pnp: %d of %d detections gave no pose (degenerate corners)",
            int((~good).sum()),
            len(good),
        )
    cols: dict[str, Any] = {
        "t_ns": det["t_ns"].to_numpy(np.int64),
        "frame_idx": det["frame_idx"].to_numpy(np.int32),
        "tag_id": tag_id,
        "size_m": sizes,
    }
    for prefix, k in (("", 0), ("alt_", 1)):
        xyz, q = _xyz_quat(T[:, k])
        for c, v in zip(POSE_COLS, [*xyz.T, *q.T], strict=True):
            cols[prefix + c] = v
        cols[prefix + "reproj_px"] = err[:, k]
    cols["ambiguity"] = ambiguity(err[:, 0], err[:, 1])
    return pd.DataFrame(cols)[COLUMNS][good].reset_index(drop=True)


def _xyz_quat(T: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(n, 4, 4) possibly NaN → xyz (n, 3), q_xyzw (n, 4), NaN rows kept NaN."""
    xyz = T[:, :3, 3].copy()
    q = np.full((len(T), 4), np.nan)
    ok = np.isfinite(T).all(axis=(1, 2))
    if ok.any():
        q[ok] = se3.quat_xyzw_from_R(T[ok, :3, :3])
    return xyz, q


def _passthrough(obs: pd.DataFrame, params: Params) -> pd.DataFrame:
    out = obs[["t_ns", "frame_idx", "tag_id", *POSE_COLS]].reset_index(drop=True).copy()
    out.insert(3, "size_m", params.sizes(out["tag_id"].to_numpy()))
    for c in ["reproj_px", *ALT_COLS, "alt_reproj_px", "ambiguity"]:
        out[c] = np.nan
    return out[COLUMNS]


def _typed(df: pd.DataFrame) -> pd.DataFrame:
    out = df[COLUMNS].copy()
    out["t_ns"] = out["t_ns"].astype(np.int64)
    out["frame_idx"] = out["frame_idx"].astype(np.int32)
    out["tag_id"] = out["tag_id"].astype(np.int32)
    for c in COLUMNS[3:]:
        out[c] = out[c].astype(np.float64)
    return out
