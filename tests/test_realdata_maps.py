"""Mapping real photos (third-party data in ../shared/realdata) through the real pipeline."""

from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.stages import REGISTRY

pytestmark = pytest.mark.slow  # maps of the real photo sets (make test-all)


def run_map(tmp_path: Path, source: Path, tag_size: float, *overrides: str) -> Runner:
    (tmp_path / "pipeline.yaml").write_text(
        f"datasets:\n  reference:\n    source: {source}\n"
        f"stages:\n  pnp:\n    tag_size: {tag_size}\n"
    )
    runner = Runner(load_pipeline(tmp_path / "pipeline.yaml", REGISTRY, overrides))
    runner.run(["optimize"])
    return runner


def artifact(runner: Runner, stage: str, output: str) -> object:
    key = next(s.key for s in runner.plan([stage]) if s.stage == stage)
    return runner.store.load(stage, key, output)


def two_edge_connected(pairs: np.ndarray, n: int) -> bool:
    """Every single pair can be removed and the tag graph stays connected (a closed loop)."""
    for drop in range(len(pairs)):
        keep = np.delete(pairs, drop, axis=0)
        g = coo_matrix((np.ones(len(keep)), (keep[:, 0], keep[:, 1])), shape=(n, n))
        if connected_components(g, directed=False)[0] != 1:
            return False
    return True


def test_swatbotics_room_maps_all_20_tags_with_the_loop_closed(
    tmp_path: Path, realdata: Path
) -> None:
    runner = run_map(tmp_path, realdata / "swatbotics_mapping_feb_2014" / "images", 0.127)
    tags = artifact(runner, "optimize", "tag_map")
    assert sorted(tags["tag_id"]) == list(range(20))
    edges = artifact(runner, "edges", "edges")
    ids = {t: i for i, t in enumerate(sorted(tags["tag_id"]))}
    pairs = np.unique(
        np.array([[ids[a], ids[b]] for a, b in zip(edges["tag_i"], edges["tag_j"], strict=True)]),
        axis=0,
    )
    assert two_edge_connected(pairs, 20)
    res = artifact(runner, "optimize", "edge_residuals")["res_t_m"].to_numpy()
    print(
        f"\nswatbotics: 20 tags, {len(pairs)} tag pairs, {len(res)} edges, residual median "
        f"{np.median(res):.3f} m, p95 {np.percentile(res, 95):.3f} m, max {res.max():.2f} m"
    )
    # The closed loop is consistent: the typical edge agrees with the map to hand-held single-view
    # PnP noise (tags up to several metres away, no lens distortion given); the few flipped
    # (ambiguous) observations are what the robust loss is for.
    assert np.median(res) < 0.05
    assert np.mean(res < 0.2) > 0.95


def lap_map(
    tmp_path: Path, realdata: Path, lo: int, hi: int, *overrides: str
) -> dict[int, np.ndarray]:
    """Tag positions mapped from the swatbotics photos IMG_<lo>..IMG_<hi> alone."""
    src = realdata / "swatbotics_mapping_feb_2014" / "images"
    folder = tmp_path / f"img{lo}"
    if not folder.exists():
        folder.mkdir()
        for f in sorted(src.glob("IMG_*.JPG")):
            if lo <= int(f.stem.split("_")[1]) <= hi:
                (folder / f.name).symlink_to(f)
        shutil.copy(src / "camera.yaml", folder / "camera.yaml")
    work = tmp_path / f"run{lo}-{len(list(tmp_path.glob(f'run{lo}-*')))}"
    work.mkdir()
    tags = artifact(run_map(work, folder, 0.127, *overrides), "optimize", "tag_map")
    xyz = tags[["x_m", "y_m", "z_m"]].to_numpy()
    return {int(t): p for t, p in zip(tags["tag_id"], xyz, strict=True)}


def distance_differences(a: dict[int, np.ndarray], b: dict[int, np.ndarray]) -> np.ndarray:
    ids = sorted(set(a) & set(b))
    return np.array(
        [
            abs(np.linalg.norm(a[i] - a[j]) - np.linalg.norm(b[i] - b[j]))
            for i, j in itertools.combinations(ids, 2)
        ]
    )


def test_swatbotics_laps_map_alike_with_the_small_tags_found(
    tmp_path: Path, realdata: Path
) -> None:
    """The loop's two laps, mapped apart with the defaults (small tags re-detected): lap 2's 25
    photos add 22 px views of far tags, one mirrored at ambiguity 0.31; the map's check of each
    observation's IPPE solution keeps it from bending lap 2's pose graph."""
    lap1 = lap_map(tmp_path, realdata, 1368, 1406)
    lap2 = lap_map(tmp_path, realdata, 1407, 1431)
    unchecked = lap_map(tmp_path, realdata, 1407, 1431, "optimize.branch_check=none")
    d, d_unchecked = distance_differences(lap1, lap2), distance_differences(lap1, unchecked)
    print(
        f"\nswatbotics lap 1 vs lap 2, {len(d)} tag pairs: {d.mean():.3f} m mean, "
        f"{d.max():.3f} m max (unchecked: {d_unchecked.mean():.3f} / {d_unchecked.max():.3f})"
    )
    assert len(d) == 190
    assert d.mean() < 0.04 and d.max() < 0.15
    assert d_unchecked.mean() > 1.5 * d.mean()


def official_layout(path: Path) -> dict[int, np.ndarray]:
    doc = json.loads(path.read_text())
    return {t["ID"]: np.array([t["pose"]["translation"][k] for k in "xyz"]) for t in doc["tags"]}


def test_photonvision_field_distances_vs_official_layout(tmp_path: Path, realdata: Path) -> None:
    root = realdata / "photonvision_frc2024_field"
    layout = official_layout(root / "2024-crescendo.json")
    runner = run_map(tmp_path, root / "images", 0.1651)
    components = []
    graph = artifact(runner, "edges", "graph")
    components.append(artifact(runner, "optimize", "tag_map"))
    pending = [d["tag_id"] for d in graph["dropped"]]
    while pending:  # map every connected component: rerun with its tag as the anchor
        runner = run_map(tmp_path, root / "images", 0.1651, f"edges.anchor_id={pending[0]}")
        tags = artifact(runner, "optimize", "tag_map")
        if len(tags) > 1:
            components.append(tags)
        pending = [t for t in pending if t not in set(tags["tag_id"])]
    rows = []
    for tags in components:
        pos = {
            int(t): np.array(p)
            for t, p in zip(tags["tag_id"], tags[["x_m", "y_m", "z_m"]].to_numpy(), strict=True)
        }
        for a, b in itertools.combinations(sorted(pos), 2):
            est = float(np.linalg.norm(pos[a] - pos[b]))
            ref = float(np.linalg.norm(layout[a] - layout[b]))
            rows.append((a, b, est, ref, abs(est - ref)))
    assert rows, "no connected pair of tags"
    print("\nsource  target  estimated [m]  official [m]  abs error [m]")
    for a, b, est, ref, err in rows:
        print(f"{a:>6} {b:>7} {est:>14.3f} {ref:>13.3f} {err:>14.3f}")
    errs = np.array([r[4] for r in rows])
    print(
        f"mean {errs.mean():.3f}  max {errs.max():.3f}  min {errs.min():.3f}  "
        f"(paper Table A.1, tape vs map: mean 0.039, max 0.099, min 0.001)"
    )
    rel = errs / np.array([r[3] for r in rows])
    print(f"relative error: median {np.median(rel):.3f}, max {rel.max():.3f}")
    # Single photos 1-6 m from the tags, with the calibration of another unit of the same camera
    # model (see the data's README): distances agree with the official layout to a few percent.
    assert np.median(rel) < 0.03 and rel.max() < 0.05
