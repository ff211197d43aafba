"""A surveyed world: known poses of some tags, and the map expressed in their frame.

Labs measure where some tags are (tape-measured tags, TagSLAM's ``tagslam.yaml`` known poses, an
FRC field layout). A :class:`Survey` holds them in the SPEC tag frame (x right, y up, z out of
the face): per tag a position and optionally an orientation ("position-only" otherwise).
:func:`fit_survey` finds ``survey_T_map`` (rigid, or a similarity when asked) by Umeyama (1991)
over matched points: each known tag's centre, plus, for a full pose, its four corners at
(±h, ±h, 0) with ``h`` = half its size — so a single fully known tag fixes the world, an
orientation weighs as the tag's own extent does, and position-only tags need three or more,
not on one line. Its residuals at the known tags say how well the map agrees with the survey.

The file layouts are parsed here from their decoded documents (no file I/O): TagSLAM
(``bodies:`` of static bodies, each ``pose`` and its ``tags`` with poses in the body's frame,
rotations as rotation vectors), WPILib / PhotonVision field layout JSON (``tags: [{ID, pose:
{translation, rotation: {quaternion: {W, X, Y, Z}}}}]``, the tag's +X out of its face, Z up),
and tagtrail's ``tag_map.yaml`` (SPEC). :func:`parse_survey` tells them apart by content;
:func:`parse_tag_sizes` reads the tag sizes the same files give (for pnp).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from tagtrail.geometry.arrays import F64
from tagtrail.geometry.registration import umeyama
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import R_from_quat_xyzw, R_from_rotvec, rotation_angle

# WPILib's tag frame (+X out of the face, +Y to the viewer's right... as seen facing the tag, Z
# up) -> SPEC's (x right, y up, z out): columns = SPEC's axes in WPILib's frame.
WPILIB_R_SPEC = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
ORIENTATION_ARM_M = 0.1  # half-size used for a full pose whose tag size nobody gives


@dataclass(frozen=True)
class Survey:
    """Known tags: ``ids (K,)``, ``position (K, 3)`` (m, survey frame), ``R (K, 3, 3)``
    (survey_T_tag rotation, SPEC tag frame; NaN = position only), ``size (K,)`` (m; NaN:
    not given)."""

    ids: np.ndarray
    position: F64
    R: F64
    size: F64

    @property
    def full(self) -> np.ndarray:
        """Tags whose orientation is known too."""
        return np.asarray(np.isfinite(self.R).all(axis=(1, 2)))

    def subset(self, ids: list[int] | tuple[int, ...]) -> Survey:
        """The named tags only (the order of ``ids`` sorted)."""
        k = np.isin(self.ids, np.asarray(ids, dtype=np.int64))
        return Survey(self.ids[k], self.position[k], self.R[k], self.size[k])


def make_survey(entries: list[tuple[int, Any, Any, Any]]) -> Survey:
    """A :class:`Survey` from ``(id, position (3,), R (3, 3) or None, size or None)`` rows;
    ``ValueError`` on a repeated id or a non-finite value."""
    ids = [int(e[0]) for e in entries]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"tag {dup[0]} is given twice")
    order = np.argsort(ids, kind="stable")
    pos = np.array([np.asarray(entries[k][1], float).reshape(3) for k in order]).reshape(-1, 3)
    R = np.full((len(ids), 3, 3), np.nan)
    size = np.full(len(ids), np.nan)
    for row, k in enumerate(order):
        if entries[k][2] is not None:
            R[row] = np.asarray(entries[k][2], float)
        if entries[k][3] is not None:
            size[row] = float(entries[k][3])
    if not np.isfinite(pos).all():
        raise ValueError("a known position is not finite")
    return Survey(np.asarray(ids, dtype=np.int64)[order], pos, R, size)


# --- the file layouts (decoded documents) ------------------------------------------------------


def _xyz(d: Any, what: str) -> F64:
    if isinstance(d, dict) and all(k in d for k in "xyz"):
        return np.array([float(d["x"]), float(d["y"]), float(d["z"])])
    if isinstance(d, (list, tuple)) and len(d) == 3:
        return np.array([float(v) for v in d])
    raise ValueError(f"{what}: expected {{x, y, z}}")


def _quat(d: Any, what: str) -> F64:
    if isinstance(d, dict) and all(k in d for k in "xyzw"):
        q = np.array([float(d[k]) for k in "xyzw"])
    elif isinstance(d, (list, tuple)) and len(d) == 4:
        q = np.array([float(v) for v in d])
    else:
        raise ValueError(f"{what}: expected a quaternion {{x, y, z, w}}")
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"{what}: the quaternion has no length")
    return q / n


def _pose(d: Any, what: str, rotvec: bool) -> F64:
    """4x4 from ``{position, rotation (rotation vector) | orientation (quaternion)}``."""
    if not isinstance(d, dict) or "position" not in d:
        raise ValueError(f"{what}: expected a pose with position")
    T = np.eye(4)
    T[:3, 3] = _xyz(d["position"], f"{what}.position")
    if rotvec:
        T[:3, :3] = R_from_rotvec(_xyz(d.get("rotation", [0, 0, 0]), f"{what}.rotation"))
    elif d.get("orientation") is not None:
        T[:3, :3] = R_from_quat_xyzw(_quat(d["orientation"], f"{what}.orientation"))
    else:
        T[:3, :3] = np.nan  # position only
    return T


def from_tagslam(doc: dict[str, Any]) -> Survey:
    """TagSLAM's ``tagslam.yaml``: every tag with a ``pose`` on a static body with a ``pose``
    (world_T_tag = world_T_body @ body_T_tag), size = the tag's ``size`` or the body's
    ``default_tag_size``."""
    entries: list[tuple[int, Any, Any, Any]] = []
    bodies = doc.get("bodies")
    if not isinstance(bodies, list):
        raise ValueError("bodies: expected a list of bodies")
    for item in bodies:
        if not isinstance(item, dict) or len(item) != 1:
            raise ValueError("bodies: each entry is '- <name>: {...}'")
        name, body = next(iter(item.items()))
        if not isinstance(body, dict) or not body.get("is_static") or "pose" not in body:
            continue
        world_T_body = _pose(body["pose"], f"bodies.{name}.pose", rotvec=True)
        for k, tag in enumerate(body.get("tags") or []):
            if not isinstance(tag, dict) or "id" not in tag:
                raise ValueError(f"bodies.{name}.tags[{k}]: expected {{id, size, pose}}")
            if "pose" not in tag:
                continue
            T = world_T_body @ _pose(tag["pose"], f"bodies.{name}.tags[{k}].pose", rotvec=True)
            size = tag.get("size", body.get("default_tag_size"))
            entries.append((int(tag["id"]), T[:3, 3], T[:3, :3], size))
    if not entries:
        raise ValueError("no tag with a pose on a static body with a pose")
    return make_survey(entries)


def from_wpilib(doc: dict[str, Any]) -> Survey:
    """A WPILib / PhotonVision field layout: ``tags: [{ID, pose: {translation: {x, y, z},
    rotation: {quaternion: {W, X, Y, Z}}}}]`` (metres; the tag's +X out of its face)."""
    entries: list[tuple[int, Any, Any, Any]] = []
    for k, tag in enumerate(doc.get("tags") or []):
        try:
            pose = tag["pose"]
            q = pose["rotation"]["quaternion"]
            q_xyzw = _quat([q["X"], q["Y"], q["Z"], q["W"]], f"tags[{k}].pose.rotation")
            pos = _xyz(pose["translation"], f"tags[{k}].pose.translation")
            entries.append((int(tag["ID"]), pos, R_from_quat_xyzw(q_xyzw) @ WPILIB_R_SPEC, None))
        except (KeyError, TypeError) as err:
            raise ValueError(
                f"tags[{k}]: expected {{ID, pose: {{translation, rotation: "
                f"{{quaternion}}}}}} (missing {err})"
            ) from err
    if not entries:
        raise ValueError("tags: no tag")
    return make_survey(entries)


def _tag_id(key: Any) -> int:
    text = str(key)
    tail = text.rsplit(":", 1)[-1]
    if not tail.lstrip("-").isdigit():
        raise ValueError(f"tag {text!r}: expected tag36h11:<id> or an id")
    return int(tail)


def from_tag_map(doc: dict[str, Any]) -> Survey:
    """tagtrail's ``tag_map.yaml`` (SPEC: ``tags: {"tag36h11:<id>": {position, orientation,
    size}}``) or the inline form ``{<id>: {position, orientation?, size?}}``; an entry without
    ``orientation`` is position-only."""
    tags = doc.get("tags", doc)
    if not isinstance(tags, dict) or not tags:
        raise ValueError("tags: expected a mapping of tag -> {position, orientation}")
    entries: list[tuple[int, Any, Any, Any]] = []
    for key, item in tags.items():
        T = _pose(item, f"tags.{key}", rotvec=False)
        rot = None if np.isnan(T[0, 0]) else T[:3, :3]
        size = item.get("size", item.get("size_m")) if isinstance(item, dict) else None
        entries.append((_tag_id(key), T[:3, 3], rot, size))
    return make_survey(entries)


def file_format(doc: Any) -> str:
    """The layout of a decoded known-poses document, by content: ``bodies`` → ``tagslam``,
    ``tags`` as a list → ``wpilib`` (field layout), ``tags`` as a mapping → ``tag_map``.
    ``ValueError`` (one line) otherwise."""
    if isinstance(doc, dict) and "bodies" in doc:
        return "tagslam"
    if isinstance(doc, dict) and isinstance(doc.get("tags"), list):
        return "wpilib"
    if isinstance(doc, dict) and isinstance(doc.get("tags"), dict):
        return "tag_map"
    raise ValueError(
        "not a known-poses file (expected TagSLAM's tagslam.yaml with bodies:, a "
        "WPILib/PhotonVision field layout JSON with tags: [...], or a tagtrail "
        "tag_map.yaml)"
    )


def parse_survey(doc: Any) -> tuple[str, Survey]:
    """``(format, survey)`` of a decoded document (:func:`file_format`)."""
    fmt = file_format(doc)
    parse = {"tagslam": from_tagslam, "wpilib": from_wpilib, "tag_map": from_tag_map}[fmt]
    return fmt, parse(doc)


# --- tag sizes from the same files -------------------------------------------------------------


@dataclass(frozen=True)
class TagSizes:
    """Tag edge lengths (m) a known-poses file gives: ``per_id``, and ``default`` for every
    other tag (TagSLAM: the ``default_body``'s ``default_tag_size``, which it gives the tags it
    discovers; None when the file has none)."""

    per_id: dict[int, float]
    default: float | None


def _size(value: Any, what: str) -> float:
    try:
        size = float(value)
    except (TypeError, ValueError):
        size = float("nan")
    if not (np.isfinite(size) and size > 0):
        raise ValueError(f"{what}: expected a size > 0 m, got {value!r}")
    return size


def _tagslam_sizes(doc: dict[str, Any]) -> TagSizes:
    """Every tag of every body (static or not: a rig's tags are seen too) with its ``size`` or
    its body's ``default_tag_size``; the default from ``default_body``."""
    per_id: dict[int, float] = {}
    default = None
    bodies = doc.get("bodies")
    if not isinstance(bodies, list):
        raise ValueError("bodies: expected a list of bodies")
    for item in bodies:
        if not isinstance(item, dict) or len(item) != 1:
            raise ValueError("bodies: each entry is '- <name>: {...}'")
        name, body = next(iter(item.items()))
        if not isinstance(body, dict):
            continue
        body_size = body.get("default_tag_size")
        if body_size is not None:
            body_size = _size(body_size, f"bodies.{name}.default_tag_size")
            if name == doc.get("default_body"):
                default = body_size
        for k, tag in enumerate(body.get("tags") or []):
            if not isinstance(tag, dict) or "id" not in tag:
                raise ValueError(f"bodies.{name}.tags[{k}]: expected {{id, size, pose}}")
            size = tag.get("size", body_size)
            if size is None:
                continue
            i = int(tag["id"])
            if i in per_id:
                raise ValueError(f"tag {i} is given twice")
            per_id[i] = _size(size, f"bodies.{name}.tags[{k}].size")
    return TagSizes(per_id, default)


def parse_tag_sizes(doc: Any) -> tuple[str, TagSizes]:
    """``(format, sizes)`` of a decoded known-poses document (:func:`file_format`): TagSLAM's
    tag ``size`` / body ``default_tag_size``, a tag map's ``size``. ``ValueError`` when it
    gives none (a WPILib field layout has no size field)."""
    fmt = file_format(doc)
    if fmt == "wpilib":
        raise ValueError(
            "a WPILib/PhotonVision field layout gives no tag sizes (set "
            "pnp.tag_size or pnp.tag_sizes)"
        )
    if fmt == "tagslam":
        sizes = _tagslam_sizes(doc)
    else:
        sv = from_tag_map(doc)
        sizes = TagSizes(
            {
                int(i): _size(float(s), f"tag {int(i)}: size")
                for i, s in zip(sv.ids, sv.size, strict=True)
                if not np.isnan(s)
            },
            None,
        )
    if not sizes.per_id and sizes.default is None:
        raise ValueError(
            f"no tag size given (a {fmt} file sizes tags with "
            f"{'size: or default_tag_size:' if fmt == 'tagslam' else 'size:'})"
        )
    return fmt, sizes


# --- the fit -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class SurveyFit:
    """``survey_T_map`` = ``scale`` · ``R`` · p + ``t``; per known tag that is mapped: ``ids``,
    position residual ``res_pos_m`` and orientation residual ``res_rot_deg`` (NaN: position
    only) after the fit; ``missing``: known tags not in the map."""

    scale: float
    R: F64
    t: F64
    ids: np.ndarray
    res_pos_m: F64
    res_rot_deg: F64
    missing: list[int]

    def apply(self, map_T_x: F64) -> F64:
        """Poses ``(N, 4, 4)`` in the map frame → the survey frame (rotation unscaled)."""
        out = np.array(map_T_x, dtype=np.float64, copy=True)
        out[:, :3, :3] = self.R @ out[:, :3, :3]
        out[:, :3, 3] = self.scale * out[:, :3, 3] @ self.R.T + self.t
        return out

    def line(self, where: str) -> str:
        """The fit in plain words (for the log); ``where``: the survey's source and model."""
        fig = self.report()
        rot = fig["res_rot_rms_deg"]
        return (
            f"surveyed world ({where}) from known tags {fig['tags']}: residuals "
            f"{1e3 * fig['res_pos_rms_m']:.1f} mm rms (max {1e3 * fig['res_pos_max_m']:.1f} mm)"
            + ("" if rot is None else f", {rot:.2f} deg rms")
            + (f"; known tags not in the map: {self.missing}" if self.missing else "")
        )

    def report(self) -> dict[str, Any]:
        """The fit and its residuals at the known tags as plain values (``optimize.report``'s
        ``survey`` block, less where the survey came from)."""
        rot = np.nan_to_num(self.res_rot_deg, nan=0.0)
        full = np.isfinite(self.res_rot_deg)
        return {
            "scale": self.scale,
            "rotation_deg": float(np.degrees(rotation_angle(self.R))),
            "translation_m": [float(v) for v in self.t],
            "tags": self.ids.astype(int).tolist(),
            "missing": self.missing,
            "res_pos_rms_m": float(np.sqrt(np.mean(self.res_pos_m**2))),
            "res_pos_max_m": float(self.res_pos_m.max()),
            "res_rot_rms_deg": float(np.sqrt(np.mean(rot[full] ** 2))) if full.any() else None,
            "per_tag": [
                {
                    "tag_id": int(i),
                    "res_pos_m": float(p),
                    "res_rot_deg": float(r) if np.isfinite(r) else None,
                }
                for i, p, r in zip(self.ids, self.res_pos_m, self.res_rot_deg, strict=True)
            ],
        }


def _points(T: F64, full: np.ndarray, half: F64) -> tuple[F64, np.ndarray]:
    """Centres of ``T (K, 4, 4)`` plus corners at (±h, ±h, 0) of the ``full`` ones:
    ``(M, 3)`` points and the row of each."""
    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float64)
    pts, row = [T[:, :3, 3]], [np.arange(len(T))]
    k = np.flatnonzero(full)
    if len(k):
        local = corners[None] * half[k, None, None]
        pts.append(
            (np.einsum("kij,kcj->kci", T[k, :3, :3], local) + T[k, None, :3, 3]).reshape(-1, 3)
        )
        row.append(np.repeat(k, 4))
    return np.concatenate(pts), np.concatenate(row)


def fit_survey(
    map_ids: np.ndarray,
    map_T_tag: F64,
    survey: Survey,
    similarity: bool = False,
    map_size: F64 | None = None,
) -> SurveyFit:
    """``survey_T_map`` from the mapped tags ``map_ids (N,)`` at ``map_T_tag (N, 4, 4)`` (sizes
    ``map_size (N,)`` m, for the corner arm when the survey gives none) and the known ``survey``
    (module docstring). ``ValueError`` when the known tags in the map do not fix the world: none
    mapped, or position-only tags fewer than 3 or on one line (a similarity needs 3 such
    positions even with full poses: a single tag's scale is only its printed size)."""
    ids = np.asarray(map_ids, dtype=np.int64)
    common = np.intersect1d(ids, survey.ids)
    missing = np.setdiff1d(survey.ids, ids).astype(int).tolist()
    if not len(common):
        raise ValueError(
            f"none of the known tags {survey.ids.tolist()} is in the map (mapped: {ids.tolist()})"
        )
    known = survey.subset(common.tolist())
    est = np.asarray(map_T_tag, dtype=np.float64)[np.searchsorted(ids, common)]
    half = known.size.copy()
    if map_size is not None:
        est_size = np.asarray(map_size, dtype=np.float64)[np.searchsorted(ids, common)]
        half = np.where(np.isfinite(half), half, est_size)
    half = 0.5 * np.where(np.isfinite(half) & (half > 0), half, 2 * ORIENTATION_ARM_M)
    full = known.full
    centres = known.position - known.position.mean(axis=0)
    spread = np.linalg.svd(centres, compute_uv=False) if len(common) > 1 else np.zeros(3)
    planar = len(common) >= 3 and spread[1] > 1e-3 * max(spread[0], 1e-9)
    if similarity and not planar:
        raise ValueError(
            f"a similarity needs 3 or more known tags not on one line in the map "
            f"(have {common.tolist()}); use model: rigid"
        )
    if not full.any() and not planar:
        raise ValueError(
            f"position-only known tags {common.tolist()} do not fix the world: "
            "give 3 or more not on one line, or one tag's full pose"
        )
    T_known = np.tile(np.eye(4), (len(common), 1, 1))
    T_known[:, :3, 3] = known.position
    T_known[full, :3, :3] = known.R[full]
    src, _ = _points(est, full, half)
    dst, _ = _points(T_known, full, half)
    s, R, t = umeyama(src, dst, with_scale=similarity)
    fit = SurveyFit(float(s), R, t, common, np.zeros(0), np.zeros(0), missing)
    moved = fit.apply(est)
    res_pos = np.linalg.norm(moved[:, :3, 3] - known.position, axis=1)
    res_rot = np.full(len(common), np.nan)
    if full.any():
        res_rot[full] = np.degrees(geodesic_angle(moved[full, :3, :3], known.R[full]))
    return SurveyFit(float(s), R, t, common, res_pos, res_rot, missing)
