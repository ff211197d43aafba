"""Benchmark (issue 12): extract's corners against the simulator's TRUE projected corners, per
image realism level, tag size and obliqueness: is there a bias that averaging cannot remove?

For each scenario, every ``--step``-th frame is rendered by the simulator's renderer
(``tagtrail.sim.render``) at each level (``low``: 2 DN noise / 0.5 px blur, ``high``: 4 DN / 1.0 px,
plus the same blurs without noise), detected with extract's default settings
(``vision.apriltag``), and the corners re-fitted (``vision.corners``). Truth: the tag corners
projected through the camera (``sim.camera.tag_visibility``).

Figures per (level, bin of the tag's cell size in px), for the detector's corners (``det``) and
the re-fit (``fit``):

- ``rms``: corner error RMS (px); ``mean|e|`` of the per-corner error vector's mean over the
  bin (a bias common to all corners of the bin);
- ``out``: the mean signed offset of each fitted edge line from the true edge along the outward
  normal (px; > 0: the tag looks larger), and ``out/cell``: the same in cells (a scale bias
  is a fraction of the tag's size);
- ``sd(out)``: its standard deviation per edge; ``sys(out)``: in cells, the RMS over the
  (tag, edge) pairs seen >= 5 times of their mean offset (what averaging over frames leaves).

Run: ``.venv/bin/python bench/bench_corners.py [--scenarios room,corridor] [--step 6]
[--levels low,high,blur1]``; prints markdown tables.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from typing import Any

import numpy as np

from tagtrail.sim.camera import tag_visibility
from tagtrail.sim.render import Realism, Renderer
from tagtrail.sim.scenarios import SimOptions, build
from tagtrail.stages import extract
from tagtrail.vision.apriltag import detect
from tagtrail.vision.corners import refine_many

LEVELS = {
    "low": Realism(noise_sigma=2.0, blur_sigma=0.5),
    "high": Realism(noise_sigma=4.0, blur_sigma=1.0),
    "blur05": Realism(noise_sigma=0.0, blur_sigma=0.5),
    "blur1": Realism(noise_sigma=0.0, blur_sigma=1.0),
    "noise4": Realism(noise_sigma=4.0, blur_sigma=0.5),
}
CELL_BINS = (0.0, 3.0, 4.0, 6.0, 10.0, np.inf)  # px per cell (the tag's shorter side / 8)


def edge_offsets(c: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Signed outward offset ``(m, 4)`` (px) of the edges of quads ``c`` from the true edges:
    the mean of both end corners' distances from the true edge's line."""
    a, b = truth, np.roll(truth, -1, axis=1)
    d = (b - a) / np.linalg.norm(b - a, axis=2, keepdims=True)
    n = np.stack([d[..., 1], -d[..., 0]], axis=-1)
    centre = truth.mean(axis=1, keepdims=True)
    n *= np.sign(np.einsum("mki,mki->mk", n, a - centre))[..., None]  # outward
    ca, cb = c, np.roll(c, -1, axis=1)
    return 0.5 * (np.einsum("mki,mki->mk", ca - a, n) + np.einsum("mki,mki->mk", cb - a, n))


def measure(scenario: str, level: str, step: int, seed: int) -> dict[str, np.ndarray]:
    """Per detected tag: cell px, incidence cos, truth, detector and re-fitted corners."""
    scene = build(scenario, SimOptions())[0]
    cfg = extract.Params().detector()
    cfg = replace(cfg, refit_corners=False)
    renderer = Renderer(scene, LEVELS[level], seed=seed)
    rng = np.random.default_rng(seed)
    frames = np.arange(0, len(scene.t_ns), step)
    cam_T_tags = scene.cam_T_tags()[frames]
    vis = tag_visibility(
        scene.camera,
        cam_T_tags,
        scene.tag_sizes,
        max_range_m=20.0,
        max_incidence_deg=89.0,
        min_edge_px=0.0,
    )
    out: dict[str, list[Any]] = {
        k: [] for k in ("cell", "cos", "truth", "det", "fit", "rng", "tag")
    }
    for k, i in enumerate(frames):
        gray = renderer.render(scene.scene_T_cam[i], rng)[..., 0].copy()
        ints, floats = detect(gray, cfg)  # the detector's corners (re-fit off), filtered
        if not len(ints):
            continue
        det = floats[:, 1:].reshape(-1, 4, 2)
        fit = refine_many([gray], [det], scene.camera)[0]
        col = {int(t): j for j, t in enumerate(scene.tag_ids)}
        for d, f, tid in zip(det, fit, ints[:, 0], strict=True):
            j = col.get(int(tid))
            if j is None:
                continue
            truth = vis.corners_px[k, j]
            side = np.linalg.norm(np.roll(truth, -1, axis=0) - truth, axis=1).min()
            out["cell"].append(side / 8)
            out["cos"].append(vis.cos_incidence[k, j])
            out["rng"].append(vis.range_m[k, j])
            out["tag"].append(int(tid))
            out["truth"].append(truth)
            out["det"].append(d)
            out["fit"].append(f)
    return {k: np.array(v) for k, v in out.items()}


def systematic(off: np.ndarray, tags: np.ndarray) -> float:
    """RMS over (tag, edge) of the mean offset ``off`` ``(m, 4)`` of that tag's edge over the
    frames: what averaging over frames leaves (for tags seen >= 5 times)."""
    means = [off[tags == t].mean(axis=0) for t in np.unique(tags) if (tags == t).sum() >= 5]
    return float(np.sqrt(np.mean(np.square(means)))) if means else float("nan")


def table(res: dict[str, np.ndarray], title: str) -> str:
    lines = [
        f"### {title}",
        "",
        "| cell px | tags | det rms | fit rms | fit mean|e| | det out | fit out "
        "| fit out/cell | fit sd(out) | fit sys(out) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    cell = res["cell"]
    bins = [*zip(CELL_BINS[:-1], CELL_BINS[1:], strict=True), (0.0, np.inf)]
    for lo, hi in bins:
        sel = (cell >= lo) & (cell < hi)
        if not sel.any():
            continue
        t, d, f = res["truth"][sel], res["det"][sel], res["fit"][sel]
        rms = [np.sqrt(np.mean(np.sum((x - t) ** 2, axis=2))) for x in (d, f)]
        bias = np.linalg.norm((f - t).mean(axis=(0, 1)))
        od, of = edge_offsets(d, t), edge_offsets(f, t)
        name = "all" if (lo, hi) == (0.0, np.inf) else f"{lo:g}–{hi:g}"
        lines.append(
            f"| {name} | {sel.sum()} | {rms[0]:.3f} | {rms[1]:.3f} | {bias:.3f} | "
            f"{od.mean():+.3f} | {of.mean():+.3f} | {(of / cell[sel, None]).mean():+.4f} | "
            f"{of.std():.3f} | {systematic(of / cell[sel, None], res['tag'][sel]):.4f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", default="room,corridor")
    ap.add_argument("--levels", default="blur05,blur1,low,high")
    ap.add_argument("--step", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    for scenario in args.scenarios.split(","):
        for level in args.levels.split(","):
            t0 = time.perf_counter()
            res = measure(scenario, level, args.step, args.seed)
            r = LEVELS[level]
            print(
                table(
                    res,
                    f"{scenario}, {level} (noise {r.noise_sigma:g} DN, blur "
                    f"{r.blur_sigma:g} px), {time.perf_counter() - t0:.0f} s",
                )
            )
            print()


if __name__ == "__main__":
    main()
