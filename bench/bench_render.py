"""Benchmark the simulator's renderer: frames/s at 640x480 vs the 50 frames/s goal.

Usage: ``python bench/bench_render.py [--frames N] [--repeats R] [--scenario room]``. Prints the
median over repeats of (a) rendering alone (ideal canvas, one distortion remap, blur, exposure,
noise, RGB) and (b) ``simulate()`` end to end (render + CDR + MCAP write, raw rgb8 and jpeg).
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from tagtrail.sim import simulate
from tagtrail.sim.render import Renderer
from tagtrail.sim.scenarios import SimOptions, build

GOAL_FPS = 50.0


def bench_render(scenario: str, frames: int, repeats: int) -> list[float]:
    opts = SimOptions(frames=frames)
    scene = build(scenario, opts)[0]
    renderer = Renderer(scene, opts.realism, seed=0)
    rng = np.random.default_rng(0)
    renderer.render(scene.scene_T_cam[0], rng)  # warm-up: maps, textures
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for T in scene.scene_T_cam:
            renderer.render(T, rng)
        rates.append(len(scene.scene_T_cam) / (time.perf_counter() - t0))
    return rates


def bench_simulate(scenario: str, frames: int, repeats: int, **options: object) -> list[float]:
    rates = []
    for _ in range(repeats):
        tmp = Path(tempfile.mkdtemp(prefix="bench_sim_"))
        try:
            t0 = time.perf_counter()
            out = simulate(scenario, tmp, frames=frames, query_frames=1, **options)
            dt = time.perf_counter() - t0
            rates.append((frames + (len(out) - 1)) / dt)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return rates


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="room", choices=("room", "circle", "corridor"))
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--repeats", type=int, default=5)
    a = p.parse_args()
    rates = bench_render(a.scenario, a.frames, a.repeats)
    fps = statistics.median(rates)
    print(
        f"render {a.scenario} 640x480: {fps:.1f} frames/s (median of {a.repeats} x "
        f"{a.frames} frames; min {min(rates):.1f}, max {max(rates):.1f})"
    )
    print(f"ratio vs goal {GOAL_FPS:.0f} frames/s: {fps / GOAL_FPS:.2f}")
    for label, opts in (("raw rgb8 mcap", {}), ("jpeg mcap", {"compressed": True})):
        r = statistics.median(bench_simulate(a.scenario, a.frames, max(1, a.repeats // 2), **opts))
        print(
            f"simulate {a.scenario} end to end ({label}): {r:.1f} frames/s "
            f"(ratio vs goal {r / GOAL_FPS:.2f})"
        )


if __name__ == "__main__":
    main()
