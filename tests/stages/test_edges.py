"""Stage edges: Eq. 3.2 pairs, anchor choice, ambiguity filter, connectivity."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pydantic
import pytest
from scipy.spatial.transform import Rotation

from tagtrail.errors import DataError, DisconnectedTagGraph
from tagtrail.geometry.se3 import T_from_xyz_quat, inv, make_T
from tagtrail.runner.stage import stage_spec
from tagtrail.stages import edges
from tests.stages.mapping_scene import POSE, observations, ring_scene


def test_stage_contract() -> None:
    spec = stage_spec("edges", edges)
    assert spec.outputs == ("edges", "graph")
    assert str(spec.inputs["observations"]) == "pnp.observations"
    with pytest.raises(pydantic.ValidationError):
        edges.Params(on_disconnected="ignore")
    with pytest.raises(pydantic.ValidationError):
        edges.Params(max_ambiguity=1.5)


def test_pair_indices_match_a_loop() -> None:
    frame = np.array([0, 0, 0, 1, 2, 2, 3, 3, 3, 3])
    a, b = edges.pair_indices(frame)
    loop = [(i, j) for i in range(10) for j in range(i + 1, 10) if frame[i] == frame[j]]
    assert list(zip(a.tolist(), b.tolist(), strict=True)) == loop
    assert len(edges.pair_indices(np.zeros(0, int))[0]) == 0


def test_edges_are_exact_relative_poses() -> None:
    scene = ring_scene()
    obs = observations(scene)
    out = edges.run(obs, edges.Params(weighting="uniform"))
    e, graph = out["edges"], out["graph"]
    assert list(e.columns) == ["t_ns", "tag_i", "tag_j", *POSE, "weight", "hypothesis"]
    assert e["t_ns"].dtype == np.int64 and e["tag_i"].dtype == np.int32
    assert (e["tag_i"] < e["tag_j"]).all() and (e["weight"] == 1.0).all()
    T = T_from_xyz_quat(e[POSE[:3]].to_numpy(), e[POSE[3:]].to_numpy())
    W = scene.world_T_tag
    expected = inv(W[e["tag_i"].to_numpy()]) @ W[e["tag_j"].to_numpy()]
    assert np.abs(T - expected).max() < 1e-12
    n_pairs = sum(k * (k - 1) // 2 for k in np.bincount(scene.frame))
    assert len(e) == n_pairs
    assert graph["tags"] == list(range(12)) and graph["dropped"] == []
    assert graph["n_components"] == 1


def test_anchor_most_observed_lowest_id_on_ties_or_given() -> None:
    obs = observations(ring_scene())
    counts = obs["tag_id"].value_counts()
    top = counts[counts == counts.max()].index.min()
    assert edges.run(obs, edges.Params())["graph"]["anchor_id"] == top
    assert edges.run(obs, edges.Params(anchor_id=5))["graph"]["anchor_id"] == 5
    with pytest.raises(DataError, match="anchor tag 99 is never observed"):
        edges.run(obs, edges.Params(anchor_id=99))
    with pytest.raises(DataError, match="no tag observations"):
        edges.run(obs.iloc[:0], edges.Params())


def _two_islands() -> pd.DataFrame:
    """Tags 0-1 seen together 3 times; tags 7-8 together twice (never with 0 or 1)."""
    scene = ring_scene()
    obs = observations(scene)
    rows = []
    for f, (a, b) in enumerate([(0, 1), (0, 1), (0, 1), (7, 8), (7, 8)]):
        for tag in (a, b):
            r = obs.iloc[0].copy()
            r["frame_idx"], r["t_ns"], r["tag_id"] = f, 1000 + f, tag
            r[POSE[:3]] = [0.1 * tag, 0.0, 2.0]
            rows.append(r)
    df = pd.DataFrame(rows).reset_index(drop=True)
    return df.astype({"frame_idx": np.int32, "tag_id": np.int32, "t_ns": np.int64})


def test_disconnected_graph_dropped_with_warning(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="tagtrail.stages.edges"):
        out = edges.run(_two_islands(), edges.Params())
    g = out["graph"]
    assert g["anchor_id"] == 0 and g["tags"] == [0, 1] and g["n_components"] == 2
    assert g.model_dump()["dropped"] == [{"tag_id": 7, "n_obs": 2}, {"tag_id": 8, "n_obs": 2}]
    assert set(out["edges"]["tag_i"]) == {0}
    assert "7 (2 obs), 8 (2 obs)" in caplog.text and "anchor tag 0" in caplog.text


def test_disconnected_graph_fails_when_told() -> None:
    with pytest.raises(DisconnectedTagGraph, match=r"7 \(2 obs\), 8 \(2 obs\)"):
        edges.run(_two_islands(), edges.Params(on_disconnected="fail"))


def test_min_edge_obs_cuts_weak_pairs() -> None:
    out = edges.run(_two_islands(), edges.Params(anchor_id=7, min_edge_obs=3))
    assert out["graph"]["tags"] == [7] and len(out["edges"]) == 0
    assert [d["tag_id"] for d in out["graph"]["dropped"]] == [0, 1, 8]


def test_ambiguous_observations_are_left_out() -> None:
    scene = ring_scene()
    obs = observations(scene)
    flip = make_T(Rotation.from_euler("x", 40, degrees=True).as_matrix(), np.zeros(3))
    alt = scene.cam_T_tag() @ flip
    amb = np.where(np.arange(len(obs)) % 5 == 0, 0.9, 0.2)
    obs = observations(scene, ambiguity=amb, alt_cam_T_tag=alt)

    def used(p: edges.Params, ob: pd.DataFrame = obs) -> pd.DataFrame:
        e = edges.run(ob, p)["edges"]
        return e[e["hypothesis"] == 0]

    kept, all_ = used(edges.Params()), used(edges.Params(max_ambiguity=None))
    assert 0 < len(kept) < len(all_)
    assert len(used(edges.Params(max_ambiguity=0.95))) == len(all_)
    assert len(used(edges.Params(), obs.assign(ambiguity=np.nan))) == len(all_)  # NaN: kept


def test_ambiguous_observations_that_hold_the_graph_together_are_kept_down_weighted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Every observation of tags 6-11 in a frame that also shows one of tags 0-5 is ambiguous:
    left out, the ring would split in two; they are kept instead (and only they: other
    ambiguous observations are left out), their edges weighted ``ambiguous_weight``, and the
    map is whole (and, noise-free, exact)."""
    from tagtrail.stages import optimize

    scene = ring_scene()
    obs = observations(scene)
    frame, tag = obs["frame_idx"].to_numpy(), obs["tag_id"].to_numpy()
    low = pd.Series(tag < 6).groupby(frame).transform("any").to_numpy()
    inner = ~low & (tag >= 6) & (np.arange(len(obs)) % 3 == 0)  # ambiguous, linking nothing
    amb = np.where(low & (tag >= 6) | inner, 0.9, 0.2)
    alt = scene.cam_T_tag() @ make_T(
        Rotation.from_euler("x", 40, degrees=True).as_matrix(), np.zeros(3)
    )
    obs = observations(scene, ambiguity=amb, alt_cam_T_tag=alt)
    with caplog.at_level(logging.WARNING, logger="tagtrail.stages.edges"):
        out = edges.run(obs, edges.Params(weighting="uniform"))
    g, e = out["graph"], out["edges"]
    assert g["tags"] == list(range(12)) and g["dropped"] == [] and g["n_components"] == 1
    assert g["ambiguous_kept"] == (low & (tag >= 6)).sum()  # those bridging the two halves
    assert "ambiguous observations kept" in caplog.text
    cross = (e["tag_i"] < 6) & (e["tag_j"] >= 6)
    assert cross.any() and (e.loc[cross, "weight"] == 0.1).all()
    assert (e.loc[(e["tag_j"] < 6), "weight"] == 1.0).all()
    tag_map = optimize.run(e, g, obs, optimize.Params(method="pairwise"))["tag_map"]
    T = T_from_xyz_quat(tag_map[POSE[:3]].to_numpy(), tag_map[POSE[3:]].to_numpy())
    W = inv(scene.world_T_tag[g["anchor_id"]]) @ scene.world_T_tag
    assert np.abs(T - W[tag_map["tag_id"].to_numpy()]).max() < 1e-6
    without = edges.run(obs[~(low & (tag >= 6))].reset_index(drop=True), edges.Params())
    assert without["graph"]["n_components"] == 2  # the premise: they alone link the halves
    assert edges.run(obs, edges.Params(max_ambiguity=0.95))["graph"]["ambiguous_kept"] == 0


def test_distance_weights_favour_close_tags() -> None:
    w = edges.edge_weights(
        np.array([1.0, 1.0, 3.0]), np.array([1.0, 2.0, 3.0]), np.full(3, 0.16), np.full(3, 0.16)
    )
    assert w[1] == 1.0 and w[0] > w[1] > w[2]


def test_bridges_match_brute_force() -> None:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    def n_comp(pairs: np.ndarray, n: int) -> int:
        adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        return connected_components(adj, directed=False)[0]

    rng = np.random.default_rng(0)
    for _ in range(60):
        n = int(rng.integers(2, 14))
        all_pairs = np.array([(u, v) for u in range(n) for v in range(u + 1, n)])
        pairs = all_pairs[rng.random(len(all_pairs)) < rng.uniform(0.1, 0.5)].reshape(-1, 2)
        base = n_comp(pairs, n)
        want = {
            (int(u), int(v))
            for k, (u, v) in enumerate(pairs)
            if n_comp(np.delete(pairs, k, axis=0), n) > base
        }
        assert edges.bridges(pairs, n) == want


def test_weak_links_reported(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="tagtrail.stages.edges"):
        out = edges.run(_two_islands(), edges.Params(anchor_id=7))
    assert out["graph"].model_dump()["weak_links"] == [{"tag_i": 7, "tag_j": 8, "n_frames": 2}]
    assert "weak links in the tag graph" in caplog.text and "7-8 (2 frames)" in caplog.text
    # seen together in 3 frames: a bridge, but not weak
    assert edges.run(_two_islands(), edges.Params(anchor_id=0))["graph"]["weak_links"] == []
    # the ring: every tag pair lies on a cycle
    assert edges.run(observations(ring_scene()), edges.Params())["graph"]["weak_links"] == []
