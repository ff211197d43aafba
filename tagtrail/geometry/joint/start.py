"""The starting poses of the joint solve: each frame's camera among its tags' IPPE solutions
(:func:`initial_cameras`, decided by the frames' continuity), and tags the pose graph could not
place, placed through the trajectory (:func:`link_tags`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.joint.problem import CornerObservations, same_frame_pairs
from tagtrail.geometry.rotations import log_so3
from tagtrail.geometry.se3 import R_from_rotvec, inv


def initial_cameras(
    world_T_tag: F64,
    cam_T_tag: F64,
    ob: CornerObservations,
    t_s: F64,
    *,
    px_per_unit: float,
    max_gap_s: float,
    speed_mps: float = 1.5,
    turn_dps: float = 120.0,
    cap_px: float = 8.0,
) -> tuple[F64, I64, float]:
    """A start for :func:`~.solver.solve_joint`: each frame's ``cam_T_world`` ``(F, 4, 4)``
    chosen among its tags' IPPE solutions, the choice ``(F,)`` (the observation index * 2 +
    solution) and the sequence's total cost (the map's fit to the frames and their continuity).

    ``world_T_tag (O, 4, 4)`` is each observation's tag in the current map, ``cam_T_tag
    (O, 2, 4, 4)`` both IPPE solutions (NaN where absent). Every solution of every tag of a frame
    is a candidate camera pose, scored by how well it reprojects all the frame's tags (squared px,
    capped at ``cap_px`` per tag: the map may be off); consecutive frames (within ``max_gap_s``)
    add a penalty on the jump between candidates, ``(|dc| / (speed h + 2 cm))^2 + (angle /
    (turn h + 2 deg))^2``. Dynamic programming (Viterbi) over each chain picks the sequence of
    least total cost: a single-tag frame's ambiguous pair is decided by its neighbours."""
    n_o, n_f = len(ob.frame), len(t_s)
    cand = cam_T_tag @ inv(world_T_tag)[:, None]  # (O, 2, 4, 4) cam_T_world
    valid = np.isfinite(cand).all(axis=(2, 3))
    a, b = same_frame_pairs(ob.frame)
    unary = np.zeros((n_o, 2))
    pts_w = (
        np.einsum("oij,okj->oki", world_T_tag[:, :3, :3], ob.pts_tag) + world_T_tag[:, None, :3, 3]
    )
    cap2 = (cap_px / px_per_unit) ** 2
    for s in range(2):
        for lo in range(0, len(a), 200_000):
            aa, bb = a[lo : lo + 200_000], b[lo : lo + 200_000]
            err = _capped_sq(np.nan_to_num(cand[aa, s]), pts_w[bb], ob.uv[bb], cap2)
            unary[:, s] += np.bincount(aa, err, n_o)
    unary = unary * px_per_unit**2
    unary[~valid] = np.inf
    # candidates per frame, in frame order
    order = np.lexsort((np.arange(n_o), ob.frame))
    starts = np.searchsorted(ob.frame[order], np.arange(n_f + 1))
    choice = np.zeros(n_f, np.int64)
    out = np.zeros((n_f, 4, 4))
    Tc = np.nan_to_num(cand).reshape(-1, 4, 4)
    centre = -np.einsum("nji,nj->ni", Tc[:, :3, :3], Tc[:, :3, 3])
    U = unary.reshape(-1)
    gap = np.r_[np.inf, np.diff(t_s)]
    back: list[I64] = []
    cost = np.zeros(0)
    prev = np.zeros(0, np.int64)
    idx_of: list[I64] = []

    total = 0.0

    def finish(upto: int) -> None:  # backtrack the chain ending at frame upto - 1
        nonlocal total
        if not idx_of:
            return
        j = int(np.argmin(cost))
        total += float(cost[j])
        for fr in range(upto - 1, upto - 1 - len(idx_of), -1):
            c = idx_of[fr - (upto - len(idx_of))][j]
            choice[fr] = c
            out[fr] = Tc[c]
            j = int(back[fr - (upto - len(idx_of))][j])

    for fr in range(n_f):
        obs = order[starts[fr] : starts[fr + 1]]
        ids = (2 * obs[:, None] + np.arange(2)).reshape(-1)
        ids = ids[np.isfinite(U[ids])]
        if not len(ids):  # no usable solution: the caller keeps such frames out
            ids = 2 * obs[:1]
        if gap[fr] > max_gap_s or gap[fr] <= 0 or not idx_of:
            finish(fr)
            back, idx_of = [], []
            cost = U[ids].copy()
            back.append(np.zeros(len(ids), np.int64))
        else:
            h = gap[fr]
            dc = np.linalg.norm(centre[prev][:, None] - centre[ids][None], axis=-1)
            cosang = (np.einsum("pij,qij->pq", Tc[prev, :3, :3], Tc[ids, :3, :3]) - 1) / 2
            ang = np.arccos(np.clip(cosang, -1.0, 1.0))
            trans = (dc / (speed_mps * h + 0.02)) ** 2 + (
                ang / (np.radians(turn_dps) * h + np.radians(2.0))
            ) ** 2
            tot = cost[:, None] + trans
            bk = np.argmin(tot, axis=0)
            cost = tot[bk, np.arange(len(ids))] + U[ids]
            back.append(bk)
        idx_of.append(ids)
        prev = ids
    finish(n_f)
    return out, choice, total


def _pose_distance(A: F64, B: F64) -> F64:
    """``|dt| + 0.5 m * angle`` between poses ``(..., 4, 4)`` (broadcast)."""
    dt = np.linalg.norm(A[..., :3, 3] - B[..., :3, 3], axis=-1)
    c = (np.einsum("...ij,...ij->...", A[..., :3, :3], B[..., :3, :3]) - 1.0) / 2.0
    return np.asarray(dt + 0.5 * np.arccos(np.clip(c, -1.0, 1.0)))


def _medoid(cands: F64) -> F64:
    """The candidate pose ``(4, 4)`` among ``cands (n, 2, 4, 4)`` (both IPPE solutions of ``n``
    sightings, NaN where absent) closest, summed over the sightings, to each sighting's nearer
    solution: the solution the sightings agree on."""
    flat = cands.reshape(-1, 4, 4)
    ok = np.flatnonzero(np.isfinite(flat).all(axis=(1, 2)))
    d = _pose_distance(flat[ok][:, None, None], cands[None])  # (k, n, 2)
    d = np.where(np.isfinite(d), d, np.inf).min(axis=2)
    d = np.where(np.isfinite(d), d, 0.0).sum(axis=1)
    return np.asarray(flat[ok[int(np.argmin(d))]])


def link_tags(
    world_T_tag: F64,
    known: np.ndarray,
    cam_T_tag: F64,
    ob: CornerObservations,
    t_s: F64,
    *,
    px_per_unit: float,
    max_gap_s: float,
    sightings: int = 3,
    odometry: Callable[[float, float], F64] | None = None,
    reach_s: float = 0.0,
) -> tuple[F64, np.ndarray]:
    """Place tags the pose graph could not (never seen together with a mapped tag without
    ambiguity) through the trajectory: one sweep in time, each frame posed from its known tags
    (the candidate that reprojects them best) or, with none, by constant-velocity extrapolation
    from the last two posed frames -- never across more than ``max_gap_s`` -- and an unknown tag
    placed once it has ``sightings`` posed sightings (or at its last), at the IPPE solution they
    agree on. With ``odometry`` (``cam_a_T_cam_b`` (4, 4) between two times, s, by the wheels'
    dead reckoning) a frame with no known tag is posed from the last posed frame by it, up to
    ``reach_s`` after the last frame posed from known tags: tags beyond a stretch with no tag in
    view are linked too. Returns the map ``(T, 4, 4)`` and the known mask ``(T,)``; the joint
    solve then refines it all."""
    world_T_tag, known = world_T_tag.copy(), np.asarray(known, bool).copy()
    n_f = len(t_s)
    order = np.lexsort((ob.tag, ob.frame))
    starts = np.searchsorted(ob.frame[order], np.arange(n_f + 1))
    last_sighting = np.full(len(known), -1)
    np.maximum.at(last_sighting, ob.tag, ob.frame)
    pending: dict[int, list[F64]] = {}
    original = known.copy()  # with odometry, tags linked on the way are provisional (below)
    seen: dict[int, list[F64]] = {}  # a provisional tag's sightings from posed frames
    posed: list[tuple[float, F64]] = []  # (t, world_T_cam) of the last two posed frames
    t_known = -np.inf  # when a frame was last posed from known tags
    for fr in range(n_f):
        obs = order[starts[fr] : starts[fr + 1]]
        k = known[ob.tag[obs]]
        pose = None
        pred = None
        if odometry is not None and posed and t_s[fr] - t_known <= reach_s:
            pred = posed[-1][1] @ odometry(posed[-1][0], float(t_s[fr]))
        # within the odometry's reach a frame is posed from the map's own tags when they agree
        # with it (a newly linked tag may be a far one's mirrored solution), else by it
        use = k & original[ob.tag[obs]] if pred is not None else k
        if use.any():
            pose = _best_candidate(world_T_tag, cam_T_tag, ob, obs[use], px_per_unit)
            if pose is not None and pred is not None and not _agree(pose, pred, posed[-1][1]):
                pose = pred
            elif pose is not None:
                t_known = float(t_s[fr])
        elif pred is not None:
            pose = pred
        elif len(posed) == 2 and t_s[fr] - t_known <= max_gap_s:
            (t1, T1), (t2, T2) = posed
            a = (t_s[fr] - t2) / max(t2 - t1, 1e-9)
            pose = np.eye(4)
            pose[:3, :3] = T2[:3, :3] @ R_from_rotvec(a * log_so3(T1[:3, :3].T @ T2[:3, :3]))
            pose[:3, 3] = T2[:3, 3] + a * (T2[:3, 3] - T1[:3, 3])
        if pose is None:
            continue
        if posed and t_s[fr] - posed[-1][0] > max_gap_s and odometry is None:
            posed = []
        posed = [*posed[-1:], (float(t_s[fr]), pose)]
        for o in obs:
            tag = int(ob.tag[o])
            if tag in seen:  # provisional: placed again from its last 30 sightings
                seen[tag] = [*seen[tag][-29:], pose @ cam_T_tag[o]]
                world_T_tag[tag] = _medoid(np.stack(seen[tag]))
            elif not known[tag]:
                pending.setdefault(tag, []).append(pose @ cam_T_tag[o])
                if len(pending[tag]) >= sightings or fr >= last_sighting[tag]:
                    got = pending.pop(tag)
                    world_T_tag[tag] = _medoid(np.stack(got))
                    known[tag] = True
                    if odometry is not None:
                        seen[tag] = got
    return world_T_tag, known


def _agree(pose: F64, pred: F64, last: F64) -> bool:
    """Whether a frame's pose from its known tags ``pose`` agrees with the odometry's ``pred``
    (both ``world_T_cam``): within 0.2 m plus 10 % of the way from the last posed frame
    ``last``, and 10 deg plus 10 % of its turn."""
    way = float(np.linalg.norm(pred[:3, 3] - last[:3, 3]))
    turn = float(np.linalg.norm(log_so3((last[:3, :3].T @ pred[:3, :3])[None])[0]))
    d = float(np.linalg.norm(pose[:3, 3] - pred[:3, 3]))
    a = float(np.linalg.norm(log_so3((pred[:3, :3].T @ pose[:3, :3])[None])[0]))
    return d <= 0.2 + 0.1 * way and a <= np.radians(10.0) + 0.1 * turn


def _best_candidate(
    world_T_tag: F64, cam_T_tag: F64, ob: CornerObservations, kn: I64, px_per_unit: float
) -> F64 | None:
    """Of the IPPE candidates ``world_T_cam`` of observations ``kn`` (known tags of one frame),
    the one reprojecting all of them best (squared px, capped per tag); None if none is finite."""
    cand = (world_T_tag[ob.tag[kn]][:, None] @ inv(cam_T_tag[kn])).reshape(-1, 4, 4)
    cand = cand[np.isfinite(cand).all(axis=(1, 2))]
    if not len(cand):
        return None
    pts_w = (
        np.einsum("oij,okj->oki", world_T_tag[ob.tag[kn], :3, :3], ob.pts_tag[kn])
        + world_T_tag[ob.tag[kn], None, :3, 3]
    )
    score = _capped_sq(
        inv(cand)[:, None], pts_w[None], ob.uv[kn][None], (8.0 / px_per_unit) ** 2
    ).sum(1)
    return np.asarray(cand[int(np.argmin(score))])


def _capped_sq(cam_T_world: F64, pts_w: F64, uv: F64, cap2: float) -> F64:
    """Mean squared corner error (normalised units) of world corners ``pts_w (..., 4, 3)`` seen
    at ``uv (..., 4, 2)`` from ``cam_T_world (..., 4, 4)`` (broadcast), capped at ``cap2``
    (a corner behind the camera counts as the cap): the candidate score of the start poses."""
    pc = (
        np.einsum("...ij,...kj->...ki", cam_T_world[..., :3, :3], pts_w)
        + cam_T_world[..., None, :3, 3]
    )
    z = pc[..., 2:3]
    e = np.where(z > 1e-6, pc[..., :2] / np.where(z > 1e-6, z, 1.0) - uv, 1e3)
    return np.asarray(np.minimum(np.mean(np.sum(e * e, -1), -1), cap2))
