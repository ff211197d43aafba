"""Benchmark: recall and detection time of quad_decimate 1.0, 2.0 and 2.0 + ``small_tags:
redetect`` (issue 12: decimation loses small tags).

Sets (gray frames, decoded beforehand, not timed):

- ``swatbotics``: ../shared/realdata/swatbotics_mapping_feb_2014 (72 photos 816x612, tags ~20-70
  px), ground truth = the hand-made per-image visible ids (``groundtruth.txt``; it includes tags
  no setting finds, so full resolution's recall is < 1);
- ``duckietown``: ../shared/realdata/duckietown_dt_apriltags_test (26 frames, tags ~15-90 px), no
  ground truth: full resolution's detections are the reference;
- ``photonvision``: ../shared/realdata/photonvision_frc2024_field (15 photos 1280x720, tags ~30-100
  px), reference = full resolution;
- ``sim``: frames of the simulator's ``room`` (every 15th of the loop) with 6 cm tags, ground
  truth = tags in view, facing, with edges >= 12 px (``sim.camera.tag_visibility``).

Detection runs in one worker process (never in this one: see tagtrail.vision.apriltag), through
``tagtrail.vision.apriltag.detect`` (detector, filters, corner re-fit), extract's default filters.
Prints recall (found / present), median time per frame (ms, median of ``--repeats`` passes over a
set) and the ratios: time vs decimation 2, recall vs full resolution.
Run: ``.venv/bin/python bench/bench_recall.py [--repeats 5] [--sets swatbotics,duckietown]``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import statistics
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from tagtrail.stages import extract

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
MODES = {"decimate 1.0": {"quad_decimate": 1.0}, "decimate 2.0": {"quad_decimate": 2.0},
         "2.0 + redetect": {"quad_decimate": 2.0, "small_tags": "redetect"}}


def _gray(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, path
    return img


def swatbotics() -> tuple[list[np.ndarray], list[set[int]] | None]:
    root = REALDATA / "swatbotics_mapping_feb_2014"
    frames, truth = [], []
    for line in (root / "groundtruth.txt").read_text().splitlines():
        name, *ids = line.split()
        if (root / "images" / name).exists():
            frames.append(_gray(root / "images" / name))
            truth.append({int(i) for i in ids})
    return frames, truth


def duckietown() -> tuple[list[np.ndarray], list[set[int]] | None]:
    files = sorted((REALDATA / "duckietown_dt_apriltags_test").glob("*.png"))
    return [_gray(f) for f in files], None


def photonvision() -> tuple[list[np.ndarray], list[set[int]] | None]:
    files = sorted((REALDATA / "photonvision_frc2024_field" / "images").glob("*.jpg"))
    return [_gray(f) for f in files], None


def sim(tag_size_m: float = 0.06, step: int = 15) -> tuple[list[np.ndarray], list[set[int]]]:
    from tagtrail.sim.camera import tag_visibility
    from tagtrail.sim.render import Renderer
    from tagtrail.sim.scenarios import SimOptions, room

    opts = SimOptions(tag_size_m=tag_size_m)
    scene = room(opts)[0]
    vis = tag_visibility(scene.camera, scene.cam_T_tags(), scene.tag_sizes, max_range_m=20.0,
                         max_incidence_deg=65.0, min_edge_px=12.0)
    renderer, rng = Renderer(scene, opts.realism, seed=0), np.random.default_rng(0)
    frames, truth = [], []
    for i in range(0, len(scene.t_ns), step):
        frames.append(cv2.cvtColor(renderer.render(scene.scene_T_cam[i], rng), cv2.COLOR_RGB2GRAY))
        truth.append({int(t) for t in scene.tag_ids[vis.visible[i]]})
    return frames, truth


SETS = {"swatbotics": swatbotics, "duckietown": duckietown, "photonvision": photonvision,
        "sim": sim}


def _time_mode(frames: list[np.ndarray], overrides: dict[str, Any], repeats: int
               ) -> tuple[list[list[int]], float]:
    """(ids found per frame, median ms per frame) — runs in the worker process."""
    from tagtrail.vision.apriltag import detect

    cv2.setNumThreads(1)
    cfg = extract.Params(**overrides).detector()
    found = [detect(f, cfg)[0][:, 0].tolist() for f in frames]  # also the warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        for f in frames:
            detect(f, cfg)
        times.append(time.perf_counter() - t)
    return found, 1e3 * statistics.median(times) / len(frames)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sets", default=",".join(SETS))
    args = ap.parse_args()
    ctx = mp.get_context("forkserver")
    pool = ctx.Pool(1)
    try:
        print(f"{'set':13} {'mode':15} {'found':>6} {'present':>7} {'recall':>7} {'dup':>4} "
              f"{'ms/frame':>9} {'time/dec2':>9} {'recall/full':>11}")
        for name in args.sets.split(","):
            frames, truth = SETS[name]()
            res = {m: pool.apply(_time_mode, (frames, o, args.repeats)) for m, o in MODES.items()}
            ref = truth or [set(ids) for ids in res["decimate 1.0"][0]]
            present = sum(len(r) for r in ref)
            recall = {}
            for m, (found, ms) in res.items():
                hits = sum(len(set(f) & r) for f, r in zip(found, ref, strict=True))
                dup = sum(len(f) - len(set(f)) for f in found)
                recall[m] = hits / max(present, 1)
                print(f"{name:13} {m:15} {hits:6d} {present:7d} {recall[m]:7.3f} {dup:4d} "
                      f"{ms:9.2f} {ms / res['decimate 2.0'][1]:9.2f} "
                      f"{recall[m] / max(recall['decimate 1.0'], 1e-9):11.3f}")
    finally:
        pool.terminate()  # the worker's exit status is not trusted (pupil-apriltags #46)


if __name__ == "__main__":
    main()
