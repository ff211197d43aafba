"""Benchmark (issue 12): the whole recording phase on a 9,000-frame (5 min at 30 Hz) detections
recording, wall time and peak memory vs the targets (< 30 s, < 1.5 GB), median of 3.

The recording: ``tagtrail simulate room --detections --frames 9000`` (one slow lap of the room,
~4 tags per frame, ~36k detections), mapped with the pipeline ``tagtrail init`` writes. Each
repeat starts from an empty artifact store (``artifacts/`` and ``outputs/`` removed: nothing
cached, the source hashed again) and runs ``tagtrail run`` (extract .. smooth and eval) in a child
process; wall time is measured around it. Peak RSS is the largest resident set of that process
(its own high-water mark, ``VmHWM``) and of the detector workers it waited for (their
``ru_maxrss``), reported by the child at its exit: not the child's ``ru_maxrss`` seen from here,
which Linux seeds with this (large, long-running) process's peak across fork and exec.

Per-stage times come from the last repeat's run log (``artifacts/runs/last_run.json``).
Run: ``.venv/bin/python bench/bench_scale.py [--frames 9000] [--repeats 3] [--keep DIR]``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BIN = Path(sys.executable).parent
TARGET_S, TARGET_GB = 30.0, 1.5


# `tagtrail ARGS` (its console script's entry) that prints, at exit, the peak resident set of
# itself (VmHWM) and of the workers it waited for (the idle detector pool closed first).
PEAK = """
import resource, sys
from tagtrail import pool
from tagtrail.cli import main_entry
try:
    main_entry()
finally:
    pool._close_idle()
    hwm = next(int(s.split()[1]) for s in open("/proc/self/status") if s.startswith("VmHWM:"))
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    print(f"PEAK_KIB {max(hwm, kids)}", file=sys.stderr)
"""


def timed_run(project: Path, *args: str) -> tuple[float, float, str]:
    """(wall s, peak RSS GB, stdout) of ``tagtrail run ARGS`` in ``project`` from scratch."""
    for d in ("artifacts", "outputs"):
        shutil.rmtree(project / d, ignore_errors=True)
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, "-c", PEAK, "run", *args], cwd=project, stdout=out, stderr=err
        )
        proc.wait()
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        log = err.read().decode()
        if proc.returncode != 0:
            raise RuntimeError(f"tagtrail run failed ({proc.returncode}):\n{log}")
        kib = int(log.rsplit("PEAK_KIB ", 1)[1].split()[0])
        return wall, kib / 2**20, out.read().decode()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=9000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--keep", type=Path, help="work in DIR and keep it")
    args = ap.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="tagtrail-bench-scale-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        subprocess.run(
            [
                str(BIN / "tagtrail"),
                "simulate",
                "room",
                "--out",
                "sim",
                "--detections",
                "--frames",
                str(args.frames),
                "--query-frames",
                "2",
                "--no-progress",
                "--force",
            ],
            cwd=work,
            check=True,
            capture_output=True,
        )
        subprocess.run(
            [
                str(BIN / "tagtrail"),
                "init",
                "--reference",
                "sim/reference",
                "--tag-size",
                "0.16",
                "--force",
            ],
            cwd=work,
            check=True,
            capture_output=True,
        )
        print(
            f"recording: room --detections --frames {args.frames} "
            f"(simulated in {time.perf_counter() - t0:.1f} s)"
        )
        walls, rss = [], []
        for i in range(args.repeats):
            wall, gb, _ = timed_run(work)
            walls.append(wall)
            rss.append(gb)
            print(f"  run {i + 1}: {wall:6.2f} s, peak RSS {gb:.3f} GB", flush=True)
        stages = json.loads((work / "artifacts" / "runs" / "last_run.json").read_text())
        wall, gb = statistics.median(walls), statistics.median(rss)
        print(
            "per stage (last run): "
            + ", ".join(f"{s['stage']} {s['seconds']:.2f} s" for s in stages)
        )
        print(
            f"recording phase, median of {args.repeats}: {wall:.2f} s "
            f"(target < {TARGET_S:.0f} s: {'yes' if wall < TARGET_S else 'no'}), "
            f"peak RSS {gb:.3f} GB (target < {TARGET_GB} GB: "
            f"{'yes' if gb < TARGET_GB else 'no'})"
        )
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
