"""The tag map around its pose graph (stage ``optimize``): the pairwise edges as arrays and the
pose graph of any subset of them (:class:`EdgeSet`), the map's check of each edge's IPPE
solutions (:func:`map_checked_edges`), the tag graph's connected components
(:func:`tag_components`) and the per-tag figures of a map (:func:`per_tag_rms`,
:func:`poorly_constrained`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tagtrail.geometry.arrays import F64, I64
from tagtrail.geometry.ippe import map_branches
from tagtrail.geometry.posegraph import PoseGraph
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
