"""The tag map of stage ``optimize``, from the pairwise edges to the joint solve.

:func:`build_map` drives it for one connected tag graph. The pose graph of the edges
(:class:`EdgeSet`, solved as :class:`GraphSettings` say; :mod:`tagtrail.geometry.posegraph` for
the maths): the anchor tag is fixed at the identity (gauge); every other tag has a rotation vector
and a translation; the residual per edge observation ``[t_pred - t_obs ; rot_weight_m *
Log(R_pred^T R_obs)]`` scaled by ``sqrt(weight)``, the robust loss acting on its norm;
initialised from a spanning tree of robust per-pair means, solved by Levenberg-Marquardt on the
pair-accumulated normal equations. That map then checks each observation's IPPE solution in its
frame (:func:`map_checked_edges`, :func:`tagtrail.geometry.ippe.map_branches`): edges built from
a solution the map disagrees with are rebuilt from the other, and the graph solved again.

With :class:`JointInputs`, the tag pairs with a close rival hypothesis are decided by the
frames' continuity, and the tag poses and the camera pose of every frame that sees a mapped tag
solved jointly on the corner reprojection error (:mod:`tagtrail.geometry.joint.mapping`), from
the pose-graph map, each frame at the IPPE solution its neighbours agree with; tags the pose
graph left out (seen with the map only ambiguously, or never together with it) are placed
through the trajectory first. The pairwise edges of Eq. 3.2 carry the bias of single-tag PnP (a
small tag's out-of-plane rotation error levered over the distance to the other tag) and the pose
graph inherits it; the joint solve does not. It needs redundancy: its gain is averaging many
frames; from a handful of photos the shared camera pose couples the tags' model errors instead
(a miscalibrated lens: a near tag fitting poorly drags the far ones; seen on the real FRC field
photos, 3 frames per group of tags), so it runs only when ``min_frames`` frames or more see a
mapped tag.

Beside it: the tag graph's connected components (:func:`tag_components`) and the per-tag figures
of a map (:func:`per_tag_rms`, :func:`poorly_constrained`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.camera import CameraModel
from tagtrail.geometry.ippe import map_branches
from tagtrail.geometry.joint.mapping import MapRefinement, choose_hypotheses, refine_map
from tagtrail.geometry.joint.odometry import OdometryData
from tagtrail.geometry.joint.problem import CornerRows
from tagtrail.geometry.joint.settings import JointSettings
from tagtrail.geometry.posegraph import PoseGraph, PoseGraphResult, relative_residuals, solve
from tagtrail.geometry.robust import LossName
from tagtrail.geometry.rotations import geodesic_angle
from tagtrail.geometry.se3 import R_from_quat_xyzw, inv, xyz_quat_from_T


def pair_key(tag_i: I64 | int, tag_j: I64 | int) -> I64:
    """One int64 per tag pair ``(i, j)`` (ids below 2**32)."""
    return np.asarray(tag_i, dtype=np.int64) * (1 << 32) + np.asarray(tag_j, dtype=np.int64)


@dataclass(frozen=True)
class EdgeSet:
    """Pairwise edges over the sorted tag ids ``tags``: per edge its tags ``tag_i``, ``tag_j``,
    stamp ``t_ns``, observed ``i_T_j`` as ``pose (E, 7)`` (x, y, z, qx, qy, qz, qw), ``weight``
    and ``hypothesis`` (0: the IPPE solutions the pair agrees on; 1: a close rival's)."""

    tags: I64
    tag_i: I64
    tag_j: I64
    t_ns: I64
    pose: F64
    weight: F64
    hypothesis: I64

    @property
    def idx_i(self) -> I64:
        return np.searchsorted(self.tags, self.tag_i)

    @property
    def idx_j(self) -> I64:
        return np.searchsorted(self.tags, self.tag_j)

    @property
    def key(self) -> I64:
        return pair_key(self.tag_i, self.tag_j)

    def graph(self, use: np.ndarray, anchor_id: int, rot_weight_m: float) -> PoseGraph:
        """The pose graph of the edges ``use`` (bool), gauge at tag ``anchor_id``."""
        vals = self.pose[use]
        return PoseGraph(
            n_tags=len(self.tags),
            anchor=int(np.searchsorted(self.tags, anchor_id)),
            idx_i=self.idx_i[use],
            idx_j=self.idx_j[use],
            R_obs=R_from_quat_xyzw(vals[:, 3:]),
            t_obs=vals[:, :3],
            weight=self.weight[use],
            rot_weight_m=rot_weight_m,
        )


def _rows_of(key_t: I64, key_tag: I64, t: I64, tag: I64) -> I64:
    """Index of each pair ``(t, tag)`` among the unique pairs ``(key_t, key_tag)``; -1 where
    it is not one of them."""
    if not len(key_t) or not len(t):
        return np.full(len(t), -1, np.int64)
    u = np.unique(key_t)
    lo = min(int(key_tag.min()), int(tag.min()))
    span = max(int(key_tag.max()), int(tag.max())) - lo + 1
    keys = np.searchsorted(u, key_t) * span + (key_tag - lo)
    r = np.searchsorted(u, t)
    has_t = u[np.minimum(r, len(u) - 1)] == t
    q = r * span + (tag - lo)
    order = np.argsort(keys, kind="stable")
    pos = np.minimum(np.searchsorted(keys[order], q), len(keys) - 1)
    hit = has_t & (keys[order][pos] == q)
    return np.where(hit, order[pos], -1)


def map_checked_edges(
    edges: EdgeSet,
    use: np.ndarray,
    skip: np.ndarray,
    obs_t_ns: I64,
    obs_tag: I64,
    obs_frame: I64,
    cam_T_tag: F64,
    world_R_tag: F64,
) -> tuple[EdgeSet, int]:
    """``edges`` with the rows in ``use`` (and not in ``skip``) rebuilt from the IPPE
    solutions the map picks for their observations (:func:`~tagtrail.geometry.ippe.map_branches`)
    where that turns them by more than a degree; and the number of rows rebuilt. The
    observations (one per stamp and tag): stamps, tag ids, frames, both solutions
    ``cam_T_tag (O, 2, 4, 4)`` and the map's orientation of each one's tag ``(O, 3, 3)``."""
    if not np.isfinite(cam_T_tag[:, 1]).all(axis=(1, 2)).any():
        return edges, 0
    pick = map_branches(obs_frame, world_R_tag, cam_T_tag[:, :, :3, :3])
    chosen = cam_T_tag[np.arange(len(obs_t_ns)), pick]
    ri = _rows_of(obs_t_ns, obs_tag, edges.t_ns, edges.tag_i)
    rj = _rows_of(obs_t_ns, obs_tag, edges.t_ns, edges.tag_j)
    rows = np.flatnonzero(use & (ri >= 0) & (rj >= 0) & ~skip)
    T_new = inv(chosen[ri[rows]]) @ chosen[rj[rows]]
    R_old = R_from_quat_xyzw(edges.pose[rows, 3:])
    changed = geodesic_angle(R_old, T_new[:, :3, :3]) > np.radians(1.0)
    if not changed.any():
        return edges, 0
    xyz, q = xyz_quat_from_T(T_new[changed])
    pose = edges.pose.copy()
    pose[rows[changed]] = np.concatenate([xyz, q], axis=1)
    return replace(edges, pose=pose), int(changed.sum())


def tag_components(tags: I64, tag_i: I64, tag_j: I64, anchor_id: int) -> list[I64]:
    """The connected components (tag ids) of the graph of the sorted ``tags`` with the edges
    ``tag_i``-``tag_j``: the anchor's first, then by size (ties: the smaller lowest id)."""
    ii, jj = np.searchsorted(tags, tag_i), np.searchsorted(tags, tag_j)
    adj = coo_matrix((np.ones(len(ii)), (ii, jj)), shape=(len(tags), len(tags)))
    n, label = connected_components(adj, directed=False)
    first = label[np.searchsorted(tags, anchor_id)]
    order = sorted(
        range(n), key=lambda c: (c != first, -int((label == c).sum()), int(tags[label == c].min()))
    )
    return [tags[label == c] for c in order]


def per_tag_rms(idx_i: I64, idx_j: I64, sq: F64, n: int) -> F64:
    """RMS of per-edge values ``sqrt(sq)`` over the edges touching each tag (NaN if none)."""
    s = np.bincount(idx_i, sq, n) + np.bincount(idx_j, sq, n)
    c = np.bincount(idx_i, minlength=n) + np.bincount(idx_j, minlength=n)
    return np.where(c > 0, np.sqrt(s / np.maximum(c, 1)), np.nan)


def poorly_constrained(std: F64) -> np.ndarray:
    """Tags whose position standard deviation ``std (T,)`` (m) exceeds 3x the map's median
    (or 5 cm): what the diagnostics list and ``map.png`` draws apart. All False when the map
    has no uncertainty (all NaN)."""
    if not np.isfinite(std).any():
        return np.zeros(len(std), bool)
    med = float(np.nanmedian(std[std > 0])) if (std > 0).any() else 0.0
    return np.asarray(np.isfinite(std) & (std > min(3.0 * med, 0.05)) & (std > 0))


@dataclass(frozen=True)
class GraphSettings:
    """How the pose graph is solved (:func:`~tagtrail.geometry.posegraph.solve`): the robust
    ``loss`` and its ``f_scale`` (m), the evaluations allowed, metres per radian of rotation."""

    loss: LossName
    f_scale: float
    max_nfev: int
    rot_weight_m: float

    def solve(self, edges: EdgeSet, use: np.ndarray, anchor_id: int) -> PoseGraphResult:
        """The pose graph of the edges ``use``, gauge at tag ``anchor_id``, solved."""
        g = edges.graph(use, anchor_id, self.rot_weight_m)
        return solve(g, loss=self.loss, f_scale=self.f_scale, max_nfev=self.max_nfev)


@dataclass(frozen=True)
class Sightings:
    """The map's tags' observations, one per stamp and tag: stamps, tag ids, frames and both
    IPPE solutions ``cam_T_tag (O, 2, 4, 4)`` (what the branch check weighs)."""

    t_ns: I64
    tag_id: I64
    frame_idx: I64
    cam_T_tag: F64


@dataclass(frozen=True)
class JointInputs:
    """What the joint solve from the pose graph needs: the corner ``rows`` of every observed
    tag, the camera, the settings, whether the stamps are capture times, the frames needed
    (``min_frames``), the rival pair keys to try in order (None: no rival search) and the
    iterations each is scored by; ``odometry``: the wheel-odometry prior's data (None:
    none)."""

    rows: CornerRows
    camera: CameraModel
    settings: JointSettings
    timed: bool
    min_frames: int
    rivals: list[int] | None
    rival_max_iter: int
    odometry: OdometryData | None = None


@dataclass(frozen=True)
class MapBuild:
    """A tag map: the ids ``tags`` (sorted) and their ``world_T_tag`` (``R``, ``t``), standard
    deviations ``std (T, 2)`` (m, rad; NaN: unknown, the anchor 0); the edges used (``use``)
    and their residuals against the map ``res_t``, ``res_r`` ``(E', 3)``; the pose graph's
    solution, the edges the branch check rebuilt, the rival pairs flipped, what the joint
    solve was given (None: not tried), the frames seeing a mapped tag with corners and the
    joint solve (None: not run)."""

    tags: I64
    R: F64
    t: F64
    std: F64
    use: np.ndarray
    res_t: F64
    res_r: F64
    graph: PoseGraphResult
    rebuilt: int
    flipped: list[list[int]]
    joint: JointInputs | None
    n_frames: int
    refined: MapRefinement | None

    def lines(self) -> list[str]:
        """What the build did, in the order it did it, in plain words (for the log)."""
        out = []
        if self.rebuilt:
            out.append(
                f"{self.rebuilt} tag-pair links rebuilt from the mirror-image poses the map "
                "agrees with"
            )
        if self.flipped:
            out.append(
                f"tag pairs {self.flipped}: the other of the two mirror-image poses fits the "
                "camera's smooth motion better and is used"
            )
        joint, refined = self.joint, self.refined
        if joint is None:
            return out
        if not joint.timed and joint.settings.motion != "none":
            out.append(
                "the stamps are the files' order, not capture times: no motion prior, no tags "
                "linked through the trajectory"
            )
        if refined is None:
            return out + [
                f"only {self.n_frames} frames see a mapped tag (joint_min_frames "
                f"{joint.min_frames}): the map from tag pairs is kept, not refined over all "
                "frames together"
            ]
        if refined.linked:
            out.append(f"tags {refined.linked} linked to the map through the trajectory")
        ground, odo = refined.solved.ground, refined.solved.odometry
        return (
            out + ([] if ground is None else ground.lines()) + ([] if odo is None else [odo.line()])
        )

    def warnings(self) -> list[str]:
        """What went wrong, after :meth:`lines` (for the log)."""
        res = None if self.refined is None else self.refined.solved.res
        odo = None if self.refined is None else self.refined.solved.odometry
        notes = [] if odo is None else list(odo.notes)
        if res is None or res.converged:
            return notes
        return [*notes, f"the joint solve stopped after {res.iters} iterations before converging"]


def build_map(
    edges: EdgeSet,
    anchor_id: int,
    gs: GraphSettings,
    check: Sightings | None,
    skip: I64,
    joint: JointInputs | None,
) -> MapBuild:
    """The tag map of one connected tag graph: the pose graph of the edges of hypothesis 0;
    with ``check``, up to 3 rounds of the map's branch check (:func:`map_checked_edges`; the
    pairs ``skip`` left to the rival search), each solved again; with ``joint``, the rival
    pairs decided (:func:`~tagtrail.geometry.joint.choose_hypotheses`) and the joint solve on the
    corners (:func:`~tagtrail.geometry.joint.refine_map`) when ``min_frames`` frames or more see
    a mapped tag."""
    tags = edges.tags
    use = edges.hypothesis == 0
    res, rebuilt = gs.solve(edges, use, anchor_id), 0
    for _ in range(0 if check is None else 3):
        assert check is not None
        R_obs = res.R[np.searchsorted(tags, check.tag_id)]
        edges, n = map_checked_edges(
            edges,
            use,
            np.isin(edges.key, skip),
            check.t_ns,
            check.tag_id,
            check.frame_idx,
            check.cam_T_tag,
            R_obs,
        )
        if n == 0:
            break
        rebuilt += n
        res = gs.solve(edges, use, anchor_id)
    anchor = int(np.searchsorted(tags, anchor_id))
    flipped: list[list[int]] = []
    if joint is not None and (edges.hypothesis > 0).any() and joint.rivals is not None:
        final = edges  # the rival search solves the graph of the checked edges

        def solve_graph(u: np.ndarray) -> PoseGraphResult:
            return gs.solve(final, u, anchor_id)

        use, res, flipped = choose_hypotheses(
            joint.rows.take(np.isin(joint.rows.tag_id, tags)),
            tags,
            anchor,
            joint.camera,
            joint.settings,
            edges.key,
            edges.hypothesis,
            joint.rivals,
            res,
            solve_graph,
            joint.rival_max_iter,
        )
    std = np.full((len(tags), 2), np.nan)
    std[anchor] = 0.0
    n_frames, refined = 0, None
    res_t, res_r = res.res_t, res.res_r
    if joint is not None:
        n_frames = int(np.unique(joint.rows.frame_idx[np.isin(joint.rows.tag_id, tags)]).size)
    if joint is not None and n_frames >= joint.min_frames:
        refined = refine_map(
            res.R,
            res.t,
            tags,
            anchor,
            joint.rows,
            joint.camera,
            joint.settings,
            joint.timed,
            joint.odometry,
        )
        sel = np.searchsorted(refined.ids, tags)
        g = edges.graph(use, anchor_id, gs.rot_weight_m)
        res_t, res_r = relative_residuals(refined.R[sel], refined.t[sel], g)
        tags, R, t, std = refined.ids, refined.R, refined.t, refined.std
    else:
        R, t = res.R, res.t
    return MapBuild(
        tags, R, t, std, use, res_t, res_r, res, rebuilt, flipped, joint, n_frames, refined
    )
