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
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.joint.decide import solve_grounded, travel
from tagtrail.geometry.joint.drive import DrivePrior, Mount
from tagtrail.geometry.joint.ground import GroundPlane, GroundPrior, GroundReport, fit_plane
from tagtrail.geometry.joint.motion import MotionPrior
from tagtrail.geometry.joint.odometry import (
    MAX_DEAD_RECKONING_S,
    MOUNT_LEVER_SIGMA_M,
    MOUNT_YAW_SIGMA_RAD,
    ODOM_BOUND,
    OdometryData,
    OdometryPrior,
    OdometryReport,
    OdometryState,
    camera_motion,
    camera_yaw_deg,
    covered_steps,
    dead_reckon,
    fit_state,
    mount_from_base_T_camera,
    odometry_from_table,
)
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
    GROUND_LEVEL_SIGMA,
    GROUND_TILT_SIGMA_DEG,
    MAX_ITER,
    ODOMETRY_SIGMA_M,
    JointSettings,
)
from tagtrail.geometry.joint.solver import solve_joint
from tagtrail.geometry.joint.start import initial_cameras

GROUND = GroundPrior.of(GROUND_HEIGHT_SIGMA_M, GROUND_TILT_SIGMA_DEG, GROUND_LEVEL_SIGMA)
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


ODOM_POSE = ("x_m", "y_m", "z_m", "qx", "qy", "qz", "qw")
ODOM_VAR = ("var_x_m2", "var_y_m2", "var_yaw_rad2")


def odometry_input(table: Any, mount: Any, frames_t_ns: I64 | None) -> OdometryData | None:
    """The :class:`~.odometry.OdometryData` of ``extract.odometry`` rows (``table``: columns
    ``t_ns``, ``x_m .. qw``, ``var_*``; None or empty: no odometry, None) and ``extract.mount``
    (a document or mapping with ``base_T_camera`` ``[x, y, z, qx, qy, qz, qw]`` or null,
    ``source``, and ``topic`` when it names one; None: no mount recorded); ``frames_t_ns``: the
    stamps of the camera's frames with no tag observation."""
    if table is None or len(table) == 0:
        return None

    def get(key: str) -> Any:
        if mount is None:
            return None
        return mount.get(key) if isinstance(mount, dict) else getattr(mount, key, None)

    var = (
        np.stack([np.asarray(table[c], np.float64) for c in ODOM_VAR], axis=1)
        if all(c in table for c in ODOM_VAR)
        else None
    )
    b_T_c = get("base_T_camera")
    return OdometryData(
        np.asarray(table["t_ns"], np.int64),
        np.stack([np.asarray(table[c], np.float64) for c in ODOM_POSE], axis=1),
        var,
        None if b_T_c is None else np.asarray(b_T_c, np.float64),
        str(get("source") or "recorded"),
        str(get("topic") or "extract.odometry"),
        frames_t_ns,
    )


def _tied(t_ns: I64, extra: I64, max_gap_s: float) -> I64:
    """Of the untagged frames ``extra``, those a chain of frames each within ``max_gap_s`` of
    the next (the motion prior's links; the odometry's steps are among them) ties to a frame
    with a tag (``t_ns``): a run of untagged frames linked only among themselves is free in the
    plane (the covariance's Cholesky failed on one)."""
    if not len(extra):
        return extra
    t = np.concatenate([t_ns, extra])
    order = np.argsort(t, kind="stable")
    dt = np.diff(t[order]) * 1e-9
    run = np.cumsum(np.r_[True, ~((dt > 0) & (dt <= max_gap_s))])  # linked runs, sorted order
    tagged = np.zeros(run[-1] + 1, bool)
    tagged[run[order < len(t_ns)]] = True
    keep = np.empty(len(t), bool)
    keep[order] = tagged[run]
    return extra[keep[len(t_ns) :]]


def bridge(data: OdometryData | None, settings: JointSettings, t0_ns: int) -> dict[str, Any]:
    """``link_tags``' odometry arguments (:func:`~.start.link_tags`): the wheels' dead reckoning
    from ``data`` (stamps from ``t0_ns``) and its reach, when the settings use odometry; else
    none (tags are linked across ``max_gap_s`` only, as without odometry)."""
    if data is None or settings.odometry == "off":
        return {}
    motion = camera_motion(data, t0_ns)
    return {} if motion is None else {"odometry": motion, "reach_s": MAX_DEAD_RECKONING_S}


@dataclass(frozen=True)
class Solved:
    """A joint solution, the start each frame took (``choice (F,)``: observation index * 2 +
    IPPE solution, of the frames with a tag), the ground-plane prior's report (None when it was
    not considered: no motion prior, or ``ground: none``), the problem solved (``pb``: the one
    given, or with the odometry's frames without a tag added), the odometry prior's report
    (None: no odometry given) and the prior itself as solved with (None: not applied)."""

    res: JointResult
    choice: I64
    ground: GroundReport | None
    pb: CornerProblem
    odometry: OdometryReport | None = None
    odometry_part: OdometryPrior | None = None


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
    odometry: OdometryData | None = None,
) -> Solved:
    """Solve ``pb`` from the map ``W (T, 4, 4)`` (``world_T_tag``; ``free (T,)`` the tags
    solved with the cameras), each frame started at the IPPE solution its neighbours agree
    with; ``decide``: then the ground-plane and wheeled-drive priors as ``settings`` say
    (``fallback``: the reference's decisions, for data too short or too still to decide on),
    then the wheel-odometry prior with ``odometry`` (:func:`with_odometry`)."""
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
    if odometry is None or not decide:
        return Solved(res, choice, ground, pb)
    pb2, res2, rep, part, ground2 = with_odometry(
        pb,
        res,
        ground,
        free,
        settings,
        odometry,
        max_iter=max_iter,
        covariance=covariance,
        fallback=fallback,
    )
    return Solved(res2, choice, ground2, pb2, rep, part)


def with_odometry(
    pb: CornerProblem,
    res: JointResult,
    ground: GroundReport | None,
    free: np.ndarray,
    settings: JointSettings,
    data: OdometryData,
    *,
    max_iter: int = MAX_ITER,
    covariance: bool = True,
    fallback: tuple[bool, bool] | None = None,
) -> tuple[CornerProblem, JointResult, OdometryReport, OdometryPrior | None, GroundReport | None]:
    """The wheel-odometry prior on a solution ``res`` of ``pb`` (the ground plane and drive as
    decided: ``ground``): the odometry checked (:func:`~.odometry.odometry_from_table`), its
    unknowns fitted to the solution's cameras, the frames without a tag it covers added (within
    ``MAX_DEAD_RECKONING_S`` of a frame with one, started by dead reckoning), and all solved
    again with it; ``auto`` keeps that where the corners leave it unstrained (its robust chi^2
    per degree of freedom, in the solution's variance factor, below ``ODOM_BOUND``) on data
    that moved enough to tell. Returns the problem and solution kept, the report and the prior
    (None: not applied)."""
    mode, topic = settings.odometry, data.topic

    def off(
        why: str, **kw: object
    ) -> tuple[
        CornerProblem, JointResult, OdometryReport, OdometryPrior | None, GroundReport | None
    ]:
        rep = OdometryReport(mode, False, why, topic, **kw)  # type: ignore[arg-type]
        return pb, res, rep, None, ground

    if mode == "off":
        return off("off in the settings (optimize.joint.odometry)")
    if pb.motion is None or not len(pb.t_ns):
        return off("no motion prior (the stamps are a file order, or motion: none)")
    odo, why = odometry_from_table(data.t_ns, data.pose, data.var, int(pb.t_ns[0]), topic)
    if odo is None:
        return off(why, notes=(f"{topic}: {why}: odometry prior off",))
    if not odo.covers(pb.t_s).any():
        return off("its stamps do not overlap the frames'")
    moved = travel(res.R_cam, res.t_cam, pb.t_s)
    if mode == "auto" and not moved.enough:
        return off(moved.words() + ", too little to decide on")
    grounded = ground is not None and ground.applied
    plane = res.unknowns["ground"] if grounded else fit_plane(res.R_cam, res.t_cam, GROUND)
    wheeled = grounded and ground is not None and ground.drive is not None and ground.drive.applied
    given = None
    if data.base_T_camera is not None:
        given = mount_from_base_T_camera(np.asarray(data.base_T_camera), plane.u)
    start_mount = given if given is not None else (res.unknowns["drive"] if wheeled else None)
    state = fit_state(
        res.R_cam, res.t_cam, pb.t_s, odo, plane, start_mount, pb.max_gap_s, ODOMETRY_SIGMA_M
    )
    # the frames without a tag the odometry covers, within reach of a frame with one and linked
    # to one (_tied)
    extra = np.zeros(0, np.int64)
    if data.frames_t_ns is not None and len(data.frames_t_ns):
        ft = np.setdiff1d(np.asarray(data.frames_t_ns, np.int64), pb.t_ns)
        fs = (ft - pb.t_ns[0]) * 1e-9
        i, last = np.searchsorted(pb.t_s, fs), len(pb.t_s) - 1
        before, after = pb.t_s[np.clip(i - 1, 0, last)], pb.t_s[np.clip(i, 0, last)]
        near = np.minimum(np.abs(fs - before), np.abs(fs - after))  # from a frame with a tag
        extra = ft[odo.covers(fs + state.offset_s) & (near <= MAX_DEAD_RECKONING_S)]
        extra = _tied(pb.t_ns, extra, pb.max_gap_s)
    t_ns = np.concatenate([pb.t_ns, extra])
    order = np.argsort(t_ns, kind="stable")
    t_ns = t_ns[order]
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    posed = np.zeros(len(t_ns), bool)
    posed[rank[: len(pb.t_ns)]] = True
    t_s = (t_ns - t_ns[0]) * 1e-9
    shift = float(pb.t_s[0] - t_s[rank[0]])  # the odometry's clock is the first tag frame's
    R0 = np.repeat(np.eye(3)[None], len(t_ns), axis=0)
    t0 = np.zeros((len(t_ns), 3))
    R0[rank[: len(pb.t_ns)]], t0[rank[: len(pb.t_ns)]] = res.R_cam, res.t_cam
    odo_k = replace(odo, t_s=odo.t_s - shift)
    Rs, ts = dead_reckon(R0, t0, posed, t_s, odo_k, plane.u, state)
    ob = replace(pb.ob, frame=rank[pb.ob.frame])
    motion = replace(pb.motion, t_s=t_s)
    margin = abs(state.offset_s) + 0.05
    j = covered_steps(t_s, odo_k, pb.max_gap_s, margin)
    if len(j) < 4:
        return off("fewer than 4 steps between frames are covered by it")
    plane0 = fit_plane(Rs, ts, GROUND)

    def solve_with(
        recorded: Mount | None, st0: OdometryState
    ) -> tuple[OdometryPrior, JointResult, GroundReport | None]:
        """All frames with the odometry: first with the motion prior alone beside it (the
        plane held where the start's cameras lie), then the ground plane's and the drive's
        decisions as the settings say, each solve with the odometry."""

        def part_for(start: JointResult | None, extra: Sequence[Prior]) -> OdometryPrior:
            gp = next((p for p in extra if isinstance(p, GroundPlane)), None)
            st = st0 if start is None else start.unknowns.get("odometry", st0)
            pl = plane0 if gp is None else gp.start
            return OdometryPrior(odo_k, t_s, j, ODOMETRY_SIGMA_M, st, pl, gp is not None, recorded)

        def again(start: JointResult, extra: Sequence[Prior]) -> JointResult:
            return solve_joint(
                start.R_tag,
                start.t_tag,
                start.R_cam,
                start.t_cam,
                ob,
                free,
                pb.corners,
                [motion, *extra, part_for(start, extra)],
                max_iter=max_iter,
                covariance=True,
            )

        first = solve_joint(
            res.R_tag,
            res.t_tag,
            Rs,
            ts,
            ob,
            free,
            pb.corners,
            [motion, part_for(None, [])],
            max_iter=max_iter,
            covariance=True,
        )
        rep = None
        out = first
        if settings.ground != "none":
            out, rep = solve_grounded(
                first,
                again,
                GROUND,
                settings.ground,
                None if settings.drive == "free" else DRIVE,
                settings.drive,
                motion,
                fallback,
            )
        grounded = rep is not None and rep.applied
        part = OdometryPrior(
            odo_k,
            t_s,
            j,
            ODOMETRY_SIGMA_M,
            out.unknowns["odometry"],
            out.unknowns["ground"] if grounded else plane0,
            grounded,
            recorded,
        )
        return part, out, rep

    part, out, ground2 = solve_with(given, state)
    st = out.unknowns["odometry"]
    u = part.plane.u
    source = data.mount_source or "recorded" if given is not None else "solved"
    notes: list[str] = []
    if given is not None:
        dl = abs(st.mount.lever_m - given.lever_m)
        dyaw = abs(camera_yaw_deg(st.mount, u) - camera_yaw_deg(given, u))
        if dl > 3 * MOUNT_LEVER_SIGMA_M or np.radians(dyaw) > 3 * MOUNT_YAW_SIGMA_RAD:
            # the motion pulls the mount away from the recorded one: that one is wrong
            fresh = fit_state(
                res.R_cam, res.t_cam, pb.t_s, odo, plane, None, pb.max_gap_s, ODOMETRY_SIGMA_M
            )
            part, out, ground2 = solve_with(None, fresh)
            st = out.unknowns["odometry"]
            u = part.plane.u
            notes.append(
                f"the recorded base-to-camera transform ({source}) puts the camera "
                f"{given.lever_m:.3f} m ahead of the base at {camera_yaw_deg(given, u):.1f} deg; "
                f"the motion says {st.mount.lever_m:.3f} m at {camera_yaw_deg(st.mount, u):.1f} "
                "deg: the solved one is used"
            )
            source = "solved; the recorded one disagreed"
    q = part.residuals(out.R_cam, out.t_cam, out.unknowns)
    _, w = part.weights(q)
    vf = out.variance_factor if np.isfinite(out.variance_factor) else 1.0
    fit = float(np.mean(np.sum(q * q, axis=1) * w) / 3.0) / max(vf, 1e-12)
    applied = mode == "on" or fit < ODOM_BOUND
    report = OdometryReport(
        mode=mode,
        applied=applied,
        why=(
            "on in the settings"
            if mode == "on"
            else f"it agrees with the tags: score {fit:.2f}, limit {ODOM_BOUND:.1f}"
            if applied
            else f"it disagrees with the tags: score {fit:.2f}, limit {ODOM_BOUND:.1f}"
        ),
        topic=topic,
        offset_ms=1e3 * st.offset_s,
        scale=st.scale,
        yaw_scale=st.yaw_scale,
        yaw_per_m_deg=float(np.degrees(st.yaw_per_m)),
        yaw_drift_dps=float(np.degrees(st.yaw_drift_rps)),
        lever_m=st.mount.lever_m,
        camera_yaw_deg=camera_yaw_deg(st.mount, u),
        mount_source=source,
        strain=fit,
        down_weighted=float(np.mean(np.sum(q * q, axis=1) > part.f_scale**2)),
        steps=len(part.j),
        frames_odometry_only=len(extra) if applied else 0,
        notes=tuple(notes),
    )
    if not applied:
        return pb, res, report, None, ground
    pb2 = replace(pb, ob=ob, t_ns=t_ns, t_s=t_s, motion=motion)
    return pb2, out, report, part, ground2
