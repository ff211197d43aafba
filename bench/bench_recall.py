"""Benchmark: recall, false detections and detection time of extract's defaults against
``quad_decimate`` 1.0 and 2.0 without ``small_tags`` (issue 12: decimation loses small tags).

Sets (gray frames, decoded beforehand, not timed):

- ``swatbotics``: ../shared/realdata/swatbotics_mapping_feb_2014 (72 photos 816x612, tags ~12-70
  px); present = the hand-made per-image visible ids (``groundtruth.txt``; it includes tags no
  setting finds, so full resolution's recall is < 1); false = an id not in the image's list;
- ``duckietown``: ../shared/realdata/duckietown_dt_apriltags_test (26 frames, tags ~11-90 px, many
  seen at a grazing angle); present = full resolution's detections; false = an id not in the
  frame's scene (the ids its README lists for the sample, rotation and multiple-tag images);
- ``photonvision``: ../shared/realdata/photonvision_frc2024_field (15 photos 1280x720, tags ~30-100
  px); present = full resolution's detections; false = an id not on the field (1-16);
- ``sim``: frames of the simulator's ``room`` (every 15th of the loop) with 6 cm tags; present =
  tags in view, facing, with edges >= 12 px (``sim.camera.tag_visibility``); false = a detection
  whose centre is not within 3 px of its id's projected centre.

Detection runs in one worker process (never in this one: see tagtrail.vision.apriltag), through
``tagtrail.vision.apriltag.detect`` (detector, filters, corner re-fit) with extract's defaults
changed only as each mode says. Time is the worker's CPU time per frame (the machine may be shared;
detection is single-threaded), the median of ``--repeats`` passes over a set, the modes
interleaved within each pass. Prints per set and mode: found / present, recall, false detections,
duplicates, ms per frame and the ratios (time vs decimation 2, recall vs full resolution), then
the defaults against the targets of issue 12 (recall >= 0.95 x full resolution's, time <= 1.5 x
decimation 2's).
Run: ``.venv/bin/python bench/bench_recall.py [--repeats 7] [--sets swatbotics,duckietown]``;
a run over every set also writes bench/RECALL.md (``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import re
import statistics
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from tagtrail.stages import extract

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata"
DEFAULT = f"default ({extract.Params().small_tags})"
MODES = {
    "decimate 1": {"quad_decimate": 1.0, "small_tags": "off"},
    "decimate 2": {"quad_decimate": 2.0, "small_tags": "off"},
    DEFAULT: {},
}
RECALL_TARGET, TIME_TARGET = 0.95, 1.5


@dataclass
class Set:
    """Frames, the tags present in each (None: full resolution's detections) and a judge of
    each detection: ``is_false(frame_index, tag_id, corners (4, 2) px) -> bool``."""

    frames: list[np.ndarray]
    present: list[set[int]] | None
    is_false: Callable[[int, int, np.ndarray], bool]


def _gray(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, path
    return img


def swatbotics() -> Set:
    root = REALDATA / "swatbotics_mapping_feb_2014"
    frames, truth = [], []
    for line in (root / "groundtruth.txt").read_text().splitlines():
        name, *ids = line.split()
        if (root / "images" / name).exists():
            frames.append(_gray(root / "images" / name))
            truth.append({int(i) for i in ids})
    return Set(frames, truth, lambda k, tag, _c: tag not in truth[k])


DUCKIETOWN_IDS = {
    "test_image.png": {60, 82, 318, 328, 387},
    "rotation": {76},
    "multiple": {22, 24, 58, 85, 144, 198},
}  # the set's README


def duckietown() -> Set:
    files = sorted((REALDATA / "duckietown_dt_apriltags_test").glob("*.png"))
    scene = [next(v for k, v in DUCKIETOWN_IDS.items() if k in f.name) for f in files]
    return Set([_gray(f) for f in files], None, lambda k, tag, _c: tag not in scene[k])


def photonvision() -> Set:
    files = sorted((REALDATA / "photonvision_frc2024_field" / "images").glob("*.jpg"))
    layout = (REALDATA / "photonvision_frc2024_field" / "2024-crescendo.json").read_text()
    field = {int(i) for i in re.findall(r'"ID"\s*:\s*(\d+)', layout)}
    assert field == set(range(1, 17)), field
    return Set([_gray(f) for f in files], None, lambda _k, tag, _c: tag not in field)


def sim(tag_size_m: float = 0.06, step: int = 15) -> Set:
    from tagtrail.sim.camera import tag_visibility
    from tagtrail.sim.render import Renderer
    from tagtrail.sim.scenarios import SimOptions, room

    opts = SimOptions(tag_size_m=tag_size_m)
    scene = room(opts)[0]
    vis = tag_visibility(
        scene.camera,
        scene.cam_T_tags(),
        scene.tag_sizes,
        max_range_m=20.0,
        max_incidence_deg=65.0,
        min_edge_px=12.0,
    )
    renderer, rng = Renderer(scene, opts.realism, seed=0), np.random.default_rng(0)
    in_front = scene.cam_T_tags()[..., 2, 3] > 0
    frames, truth, centres = [], [], []
    for i in range(0, len(scene.t_ns), step):
        frames.append(cv2.cvtColor(renderer.render(scene.scene_T_cam[i], rng), cv2.COLOR_RGB2GRAY))
        truth.append({int(t) for t in scene.tag_ids[vis.visible[i]]})
        centres.append(
            {
                int(t): c
                for t, c, ok in zip(
                    scene.tag_ids, vis.corners_px[i].mean(axis=1), in_front[i], strict=True
                )
                if ok
            }
        )

    def is_false(k: int, tag: int, corners: np.ndarray) -> bool:
        c = centres[k].get(tag)
        return c is None or float(np.hypot(*(corners.mean(axis=0) - c))) > 3.0

    return Set(frames, truth, is_false)


SETS = {
    "swatbotics": swatbotics,
    "duckietown": duckietown,
    "photonvision": photonvision,
    "sim": sim,
}


def _run_modes(
    frames: list[np.ndarray], repeats: int
) -> dict[str, tuple[list[tuple[Any, Any]], float]]:
    """Per mode: (detections per frame, median CPU ms per frame) — runs in the worker."""
    from tagtrail.vision.apriltag import detect

    cv2.setNumThreads(1)
    cfgs = {m: extract.Params(**o).detector() for m, o in MODES.items()}
    found = {m: [detect(f, cfg) for f in frames] for m, cfg in cfgs.items()}  # also the warm-up
    times: dict[str, list[float]] = {m: [] for m in cfgs}
    for _ in range(repeats):
        for m, cfg in cfgs.items():
            t = time.process_time()
            for f in frames:
                detect(f, cfg)
            times[m].append(time.process_time() - t)
    return {m: (found[m], 1e3 * statistics.median(times[m]) / len(frames)) for m in cfgs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--sets", default=",".join(SETS))
    ap.add_argument(
        "--out", type=Path, help="markdown file (default: bench/RECALL.md when every set runs)"
    )
    args = ap.parse_args()
    out = args.out or (REPO / "bench" / "RECALL.md" if args.sets == ",".join(SETS) else None)
    lines: list[str] = []

    def say(line: str = "") -> None:
        print(line, flush=True)
        lines.append(line)

    ctx = mp.get_context("forkserver")
    pool = ctx.Pool(1)
    summary = []
    try:
        say(
            f"{'set':13} {'mode':17} {'found':>6} {'present':>7} {'recall':>7} {'false':>5} "
            f"{'dup':>4} {'ms/frame':>9} {'time/dec2':>9} {'recall/full':>11}"
        )
        for name in args.sets.split(","):
            data = SETS[name]()
            res = pool.apply(_run_modes, (data.frames, args.repeats))
            ref = data.present or [set(ints[:, 0].tolist()) for ints, _ in res["decimate 1"][0]]
            present = sum(len(r) for r in ref)
            recall, false = {}, {}
            for m, (dets, ms) in res.items():
                ids = [ints[:, 0].tolist() for ints, _ in dets]
                hits = sum(len(set(i) & r) for i, r in zip(ids, ref, strict=True))
                dup = sum(len(i) - len(set(i)) for i in ids)
                false[m] = sum(
                    data.is_false(k, int(t), f[1:].reshape(4, 2))
                    for k, (ints, floats) in enumerate(dets)
                    for t, f in zip(ints[:, 0], floats, strict=True)
                )
                recall[m] = hits / max(present, 1)
                say(
                    f"{name:13} {m:17} {hits:6d} {present:7d} {recall[m]:7.3f} {false[m]:5d} "
                    f"{dup:4d} {ms:9.2f} {ms / res['decimate 2'][1]:9.2f} "
                    f"{recall[m] / max(recall['decimate 1'], 1e-9):11.3f}"
                )
            rel = recall[DEFAULT] / max(recall["decimate 1"], 1e-9)
            ratio = res[DEFAULT][1] / res["decimate 2"][1]
            ok = rel >= RECALL_TARGET and ratio <= TIME_TARGET and false[DEFAULT] == 0
            summary.append(
                f"{name:13} {recall['decimate 2']:7.3f} {recall[DEFAULT]:7.3f} "
                f"{recall['decimate 1']:7.3f} {rel:9.3f} {false[DEFAULT]:5d} "
                f"{ratio:9.2f}  {'yes' if ok else 'NO'}"
            )
        say(
            f"\n{DEFAULT} against issue 12's targets (recall >= {RECALL_TARGET} x full "
            f"resolution's, time <= {TIME_TARGET} x decimation 2's, no false detections):"
        )
        say(
            f"{'set':13} {'dec2':>7} {'default':>7} {'full':>7} {'vs full':>9} {'false':>5} "
            f"{'time/dec2':>9}  met"
        )
        for line in summary:
            say(line)
        if out is not None:
            commit = subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True
            ).stdout.strip()
            out.write_text(
                "# Small-tag recall benchmark (issue 12)\n\n"
                f"Produced by `bench/bench_recall.py` (definitions in its docstring) at commit "
                f"{commit}, {time.strftime('%Y-%m-%d %H:%M')}, {os.cpu_count()} cores, load "
                f"average {os.getloadavg()[0]:.1f}; {args.repeats} passes per set, times are "
                "medians.\n\n```\n" + "\n".join(lines).strip("\n") + "\n```\n"
            )
            print(f"wrote {out}")
    finally:
        pool.terminate()  # the worker's exit status is not trusted (pupil-apriltags #46)


if __name__ == "__main__":
    main()
