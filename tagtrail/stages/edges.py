"""edges: relative tag poses from co-visible tags (Eq. 3.2) and the tag graph's connectivity.

For every frame and every pair of tags ``i < j`` seen in it: ``i_T_j = (cam_T_i)^-1 cam_T_j``.
Before pairing, observations whose IPPE solution is ambiguous -- ``ambiguity`` (best / second-best
reprojection error) above ``max_ambiguity`` -- are dropped; ``NaN`` (poses given directly by a
source) is kept. Measured on the simulator's circle / room / corridor recordings (detections with
0.3 px corner noise), mean tag error: 0.6 -> 3.3 / 3.3 / 14.4 cm; no filter 6.9 / 3.9 / 14.8;
0.4 -> 6.3 / 3.4 / 20.5; 0.8 -> 4.1 / 3.7 / 12.0. (Keeping ambiguous tags whose two solutions
are within 10 deg made it worse: 3.8 cm on the circle.)

Which IPPE solution forms an edge (``branches="consistent"``): per tag pair the combination of
the two tags' solutions that agrees across frames (``geometry.ippe.consistent_branches``), not
each frame's lower-reprojection one; a pair seen only while the view hardly changes can agree
with a mirrored solution too, so where such a pair is a bridge of the tag graph (nothing else
can check it) a close runner-up is kept as rival edges (``hypothesis`` 1) and ``optimize``
decides on the frames' continuity. On the corridor rendered at twice the
default noise, three of its eight chain links were mirrored in 60-70 % of their frames: tags
1.4 m off with the best solutions, 3.0 cm with this.

Edge weight (``weighting="distance"``): IPPE's depth error of a tag of size ``s`` at range ``d``
grows like ``sigma ~ d^2 / s``, so ``w_ij = 1 / (sigma_i^2 + sigma_j^2)``, normalised to a median
of 1 (so ``optimize.f_scale`` keeps its meaning in metres for a typical edge) and clipped to
``[0.01, 100]``. ``"uniform"``: all 1 (the paper). Measured as above: distance 3.3 / 3.3 / 14.4 cm,
uniform 3.3 / 5.2 / 12.9 cm.

Only the anchor's connected component is mapped; other tags are dropped with a warning
(``on_disconnected="drop"``) or fail the stage (``"fail"``: :class:`DisconnectedTagGraph`), or
every component is kept (``"keep"``) for ``optimize`` to place by a surveyed world's known tags.
Weak links are reported too (warning + ``graph["weak_links"]``): tag pairs that are the only
connection between two parts of the map (bridges of the tag graph) and are seen together in fewer
than ``WEAK_LINK_OBS`` frames -- one bad frame there moves a whole part of the map, and no
optimizer can tell.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tagtrail.errors import DataError, DisconnectedTagGraph
from tagtrail.geometry.ippe import Branches, consistent_branches
from tagtrail.geometry.se3 import T_from_xyz_quat, inv, xyz_quat_from_T
from tagtrail.schemas.artifacts import POSE_COLS, columns
from tagtrail.schemas.documents import TagGraph
from tagtrail.schemas.ranges import TagId
from tagtrail.stages.base import StageParams

log = logging.getLogger(__name__)

EDGE_COLS = columns("edges.edges")
WEAK_LINK_OBS = 3


class Params(StageParams):
    anchor_id: TagId | None = None
    """Gauge tag (world frame). None: the most observed tag, ties -> lowest id."""
    max_ambiguity: float | None = Field(0.6, gt=0.0, le=1.0)
    """Drop observations with IPPE ratio reproj/alt_reproj above this (None: keep all)."""
    min_edge_obs: int = Field(1, ge=1, le=1_000_000)
    """A tag pair needs this many co-observations to form edges."""
    weighting: Literal["uniform", "distance"] = "distance"
    """Edge weight: ``distance`` (IPPE's depth error, ~ range^2 / tag size, normalised to a median
    of 1) or ``uniform`` (all 1, the paper's)."""
    branches: Literal["consistent", "best"] = "consistent"
    """Which IPPE solution of each tag forms an edge: ``consistent`` (per tag pair, the
    combination that agrees across frames, ``geometry.ippe.consistent_branches``), ``best``
    (the lower reprojection error, the paper)."""
    rival_ratio: float = Field(0.3, gt=0.0, le=1.0)
    """A bridge of the tag graph (the only link between two parts of the map) whose runner-up
    combination has at least this share of the winner's support keeps it as a rival hypothesis
    (edges rows with ``hypothesis`` 1) for optimize to test."""
    on_disconnected: Literal["drop", "fail", "keep"] = "drop"
    """Tags not linked to the anchor by co-observations: ``drop`` them (a warning), ``fail`` the
    stage, or ``keep`` every part for optimize to place by a survey's known tags."""
    ambiguous_weight: float = Field(0.1, gt=0.0, le=1.0)
    """Weight factor of the edges of ambiguous observations kept because, left out, they would
    split the tag graph (the pose graph's start; the joint solve uses every observation)."""


INPUTS = {"observations": "pnp.observations"}
OUTPUTS = ("edges", "graph")
SCOPE = "all"


def choose_anchor(n_obs: pd.Series, anchor_id: int | None) -> int:
    """The gauge tag: ``anchor_id`` if observed, else the most observed (lowest id on ties)."""
    if n_obs.empty:
        raise DataError("no tag observations: nothing to map (check the tag family and topics)")
    if anchor_id is None:
        top = n_obs[n_obs == n_obs.max()]
        return int(top.index.min())
    if anchor_id not in n_obs.index:
        seen = ", ".join(str(t) for t in n_obs.index[:20])
        raise DataError(
            f"anchor tag {anchor_id} is never observed; observed tags: {seen}"
            " (set edges.anchor_id to one of them, or leave it unset)"
        )
    return int(anchor_id)


def _unambiguous(obs: pd.DataFrame, p: Params) -> np.ndarray:
    """Mask of observations kept by the IPPE ambiguity test (NaN ambiguity is kept)."""
    if p.max_ambiguity is None or "ambiguity" not in obs.columns:
        return np.ones(len(obs), dtype=bool)
    return ~(obs["ambiguity"].to_numpy(np.float64) > p.max_ambiguity)


def _components(key: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """Connected components (count, label per tag) of ``n`` tags linked by the pair keys
    ``key = i * n + j``."""
    adj = coo_matrix((np.ones(len(key)), (key // n, key % n)), shape=(n, n))
    n_comp, label = connected_components(adj, directed=False)
    return int(n_comp), label


def _bridging(
    obs: pd.DataFrame, keep: np.ndarray, amb: np.ndarray, ids: np.ndarray, min_edge_obs: int
) -> np.ndarray:
    """Mask of the ambiguous observations (``amb``) seen in a frame with a tag that the
    unambiguous ones (``keep``) leave in another part of the tag graph: dropped, they would
    split the graph (issue 12: kept and down-weighted instead), where the two parts are seen
    together in ``WEAK_LINK_OBS`` frames or more."""
    out = np.zeros(len(obs), bool)
    if not amb.any():
        return out
    frame = obs["frame_idx"].to_numpy(np.int64)
    tag = np.searchsorted(ids, obs["tag_id"].to_numpy(np.int64))
    k = np.flatnonzero(keep)
    k = k[np.argsort(frame[k], kind="stable")]
    a, b = pair_indices(frame[k])
    key, cnt = np.unique(tag[k[a]] * len(ids) + tag[k[b]], return_counts=True)
    _, label = _components(key[cnt >= min_edge_obs], len(ids))
    u = np.flatnonzero(keep | amb)
    u = u[np.argsort(frame[u], kind="stable")]
    a, b = pair_indices(frame[u])
    ra, rb = u[a], u[b]
    cross = (label[tag[ra]] != label[tag[rb]]) & (amb[ra] | amb[rb])
    ra, rb = ra[cross], rb[cross]
    # a link seen in a frame or two (a photo) is as likely mirrored as not: left out
    parts = np.sort(np.stack([label[tag[ra]], label[tag[rb]]], axis=1), axis=1)
    link = parts[:, 0] * len(ids) + parts[:, 1]
    frames = pd.Series(frame[ra]).groupby(link).nunique()
    ok = np.isin(link, frames.index[frames.to_numpy() >= WEAK_LINK_OBS])
    out[ra[ok & amb[ra]]] = True
    out[rb[ok & amb[rb]]] = True
    return out


def pair_indices(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All index pairs ``(a, b)``, ``a < b``, of rows sharing a frame; ``frame`` must be sorted."""
    n = len(frame)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    ends = np.r_[starts[1:], n]
    end_of = np.repeat(ends, ends - starts)
    cnt = end_of - np.arange(n) - 1
    a = np.repeat(np.arange(n), cnt)
    first = np.cumsum(cnt) - cnt
    b = a + 1 + (np.arange(len(a)) - np.repeat(first, cnt))
    return a, b


def _consistent(
    ob: pd.DataFrame, T: np.ndarray, a: np.ndarray, b: np.ndarray, key: np.ndarray
) -> Branches:
    """``consistent_branches`` on the co-observations ``(a, b)`` (rows of ``ob``, poses ``T``)."""
    alt_cols = [f"alt_{c}" for c in POSE_COLS]
    if all(c in ob.columns for c in alt_cols):
        alt = ob[alt_cols].to_numpy(np.float64)
        has = np.isfinite(alt).all(axis=1)
        T_alt = np.full_like(T, np.nan)
        T_alt[has] = T_from_xyz_quat(alt[has, :3], alt[has, 3:])
        amb = ob["ambiguity"].to_numpy(np.float64) if "ambiguity" in ob else np.ones(len(ob))
        w_alt = np.where(has & np.isfinite(amb), np.clip(amb, 0.0, 1.0), 0.0)
    else:
        T_alt, w_alt = np.full_like(T, np.nan), np.zeros(len(ob))
    both = np.stack([T, T_alt], axis=1)
    w = np.stack([np.ones(len(ob)), w_alt], axis=1)
    return consistent_branches(key, both[a], both[b], w[a], w[b])


def bridges(pairs: np.ndarray, n: int) -> set[tuple[int, int]]:
    """Bridges ``(u, v)``, ``u < v``, of the undirected graph on nodes ``0..n-1`` with edges
    ``pairs`` (k, 2) (no repeats): Tarjan's low-link, iterative."""
    adj: list[list[int]] = [[] for _ in range(n)]
    for u, v in pairs.tolist():
        adj[u].append(v)
        adj[v].append(u)
    order = [-1] * n
    low = [0] * n
    out: set[tuple[int, int]] = set()
    counter = 0
    for root in range(n):
        if order[root] >= 0:
            continue
        order[root] = low[root] = counter
        counter += 1
        stack = [(root, -1, iter(adj[root]))]
        while stack:
            node, parent, it = stack[-1]
            child = next(it, None)
            if child is None:
                stack.pop()
                if parent >= 0:
                    low[parent] = min(low[parent], low[node])
                    if low[node] > order[parent]:
                        out.add((min(parent, node), max(parent, node)))
            elif order[child] < 0:
                order[child] = low[child] = counter
                counter += 1
                stack.append((child, node, iter(adj[child])))
            elif child != parent:
                low[node] = min(low[node], order[child])
    return out


def edge_weights(d_i: np.ndarray, d_j: np.ndarray, s_i: np.ndarray, s_j: np.ndarray) -> np.ndarray:
    """Distance weights (module docstring); ``d`` ranges (m), ``s`` tag sizes (m)."""
    var = (d_i**2 / s_i) ** 2 + (d_j**2 / s_j) ** 2
    w = 1.0 / np.maximum(var, 1e-18)
    out_: np.ndarray = np.clip(w / np.median(w), 0.01, 100.0) if len(w) else w
    return out_


def _bridge_pairs(
    keys: np.ndarray, counts: np.ndarray, ids: np.ndarray, in_map: np.ndarray
) -> list[dict[str, int]]:
    """Bridges among the mapped tags (``tag_i``, ``tag_j``, ``n_frames`` seen together); ``keys``:
    ``i * len(ids) + j`` of the tag pairs (indices into ``ids``) with their frame ``counts``."""
    i, j = keys // len(ids), keys % len(ids)
    m = in_map[i] & in_map[j]
    pairs = np.stack([i[m], j[m]], axis=1)
    n_of = {(u, v): c for (u, v), c in zip(pairs.tolist(), counts[m].tolist(), strict=True)}
    return [
        {"tag_i": int(ids[u]), "tag_j": int(ids[v]), "n_frames": int(n_of[(u, v)])}
        for u, v in sorted(bridges(pairs, len(ids)))
    ]


def run(observations: pd.DataFrame, params: Params) -> dict[str, Any]:
    """Edges (``EDGE_COLS``) among the anchor's component and the graph summary (JSON)."""
    obs = observations
    n_obs = obs.groupby("tag_id").size().sort_index() if len(obs) else pd.Series(dtype=int)
    anchor = choose_anchor(n_obs, params.anchor_id)

    dup = obs.duplicated(["frame_idx", "tag_id"], keep=False).to_numpy()
    if dup.any():
        log.warning("edges: %d observations of a tag seen twice in one frame ignored", dup.sum())
    keep = ~dup & _unambiguous(obs, params)
    amb = ~dup & ~keep
    ids = n_obs.index.to_numpy(np.int64)  # sorted
    back = _bridging(obs, keep, amb, ids, params.min_edge_obs)
    if amb.any():
        log.info(
            "edges: %d views of a tag left out of the tag-pair links: ambiguous (its two "
            "mirror-image poses fit almost equally)",
            int((amb & ~back).sum()),
        )
    if back.any():
        log.warning(
            "edges: %d ambiguous observations kept (their edges weighted x%g): without "
            "them the tag graph splits",
            int(back.sum()),
            params.ambiguous_weight,
        )
    ob = obs[keep | back].assign(_back=back[keep | back])
    ob = ob.sort_values(["frame_idx", "tag_id"], kind="stable")

    a, b = pair_indices(ob["frame_idx"].to_numpy())
    tag = ob["tag_id"].to_numpy(np.int64)
    T = T_from_xyz_quat(ob[POSE_COLS[:3]].to_numpy(np.float64), ob[POSE_COLS[3:]].to_numpy())
    weak_row = ob["_back"].to_numpy(bool)
    ni, nj = np.searchsorted(ids, tag[a]), np.searchsorted(ids, tag[b])
    alt = None
    if params.branches == "consistent" and len(a):
        br = _consistent(ob, T, a, b, ni * len(ids) + nj)
        n_alt = int((br.choice > 0).sum())
        if n_alt:
            log.info(
                "edges: %d of %d tag pairs seen together use a tag's other mirror-image "
                "pose (the one the pair agrees on across frames)",
                n_alt,
                len(a),
            )
        close = (br.ratio >= params.rival_ratio) & (br.alt_choice >= 0)
        alt = (a[close], b[close], br.alt_T_ij[close], br.ratio[close])
        T_ij = br.T_ij
    else:
        n_alt = 0
        T_ij = inv(T[a]) @ T[b]
    ti, tj = tag[a], tag[b]
    ukey, pair, cnt = np.unique(ni * len(ids) + nj, return_inverse=True, return_counts=True)
    ok = cnt[pair] >= params.min_edge_obs
    a, b, ti, tj, T_ij = a[ok], b[ok], ti[ok], tj[ok], T_ij[ok]
    n_comp, label = _components(ukey[cnt >= params.min_edge_obs], len(ids))
    in_map = label == label[np.searchsorted(ids, anchor)]
    if params.on_disconnected == "keep":
        in_map[:] = True
    dropped = [{"tag_id": int(t), "n_obs": int(n_obs[t])} for t in ids[~in_map]]
    if dropped:
        names = ", ".join(f"{d['tag_id']} ({d['n_obs']} obs)" for d in dropped)
        msg = (
            f"tag graph has {n_comp} components: tags {names} are not linked to anchor tag"
            f" {anchor} by unambiguous co-observations (frames showing two tags together,"
            " directly or through other tags)"
        )
        msg_keep = (
            "; with known tag poses (optimize.survey), edges.on_disconnected=keep "
            "places each part by its known tags"
        )
        if params.on_disconnected == "fail":
            raise DisconnectedTagGraph(
                msg + "; record frames showing them together with mapped tags, choose another"
                " edges.anchor_id, or set edges.on_disconnected=drop"
            )
        log.warning("edges: %s; dropping them from the map%s", msg, msg_keep)

    mapped = np.isin(ti, ids[in_map])
    a, b, ti, tj, T_ij = a[mapped], b[mapped], ti[mapped], tj[mapped], T_ij[mapped]
    xyz, q = xyz_quat_from_T(T_ij)
    size = ob["size_m"].to_numpy(np.float64) if "size_m" in ob else np.ones(len(ob))
    size = np.where(np.isfinite(size) & (size > 0), size, 1.0)
    dist = np.linalg.norm(T[:, :3, 3], axis=1)
    if params.weighting == "distance":
        w = edge_weights(dist[a], dist[b], size[a], size[b])
    else:
        w = np.ones(len(a))
    w = np.where(weak_row[a] | weak_row[b], w * params.ambiguous_weight, w)
    edges = pd.DataFrame(
        {
            "t_ns": ob["t_ns"].to_numpy(np.int64)[a],
            "tag_i": ti.astype(np.int32),
            "tag_j": tj.astype(np.int32),
        }
    )
    edges[POSE_COLS] = np.concatenate([xyz, q], axis=1)
    edges["weight"] = w
    edges["hypothesis"] = np.zeros(len(edges), np.int32)
    strong = cnt >= params.min_edge_obs
    bridge = _bridge_pairs(ukey[strong], cnt[strong], ids, in_map)
    weak = [b for b in bridge if b["n_frames"] < WEAK_LINK_OBS]
    rivals: list[dict[str, Any]] = []
    if alt is not None:
        # rivals only where nothing else can tell: a pair in a loop of the tag graph is checked
        # by the loop (the pose graph's robust loss); a bridge is the only link of its parts
        ra, rb, rT, ratio = alt
        on = np.isin(
            tag[ra] * (1 << 32) + tag[rb], [b["tag_i"] * (1 << 32) + b["tag_j"] for b in bridge]
        )
        ra, rb, rT, ratio = ra[on], rb[on], rT[on], ratio[on]
        rxyz, rq = xyz_quat_from_T(rT)
        rw = (
            edge_weights(dist[ra], dist[rb], size[ra], size[rb])
            if params.weighting == "distance"
            else np.ones(len(ra))
        )
        rw = np.where(weak_row[ra] | weak_row[rb], rw * params.ambiguous_weight, rw)
        rival = pd.DataFrame(
            {
                "t_ns": ob["t_ns"].to_numpy(np.int64)[ra],
                "tag_i": tag[ra].astype(np.int32),
                "tag_j": tag[rb].astype(np.int32),
            }
        )
        rival[POSE_COLS] = np.concatenate([rxyz, rq], axis=1)
        rival["weight"] = rw
        rival["hypothesis"] = np.ones(len(rival), np.int32)
        edges = pd.concat([edges, rival], ignore_index=True)
        first = ~rival.duplicated(["tag_i", "tag_j"]).to_numpy()
        rivals = [
            {"tag_i": int(i), "tag_j": int(j), "support_ratio": float(r)}
            for i, j, r in zip(tag[ra][first], tag[rb][first], ratio[first], strict=True)
        ]
    if weak:
        log.warning(
            "edges: weak links in the tag graph (the only connection between two parts "
            "of the map, seen together in < %d frames): %s",
            WEAK_LINK_OBS,
            ", ".join(
                f"{w['tag_i']}-{w['tag_j']} ({w['n_frames']} frame"
                f"{'s' if w['n_frames'] > 1 else ''})"
                for w in weak
            ),
        )
    graph = {
        "anchor_id": anchor,
        "tags": [int(t) for t in ids[in_map]],
        "dropped": dropped,
        "n_components": int(n_comp),
        "weak_links": weak,
        "second_solution_edges": n_alt,
        "rival_pairs": rivals,
        "ambiguous_kept": int(back.sum()),
    }
    return {"edges": edges.reset_index(drop=True), "graph": TagGraph.model_validate(graph)}
