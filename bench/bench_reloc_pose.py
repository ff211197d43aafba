"""Per-pose cost of the live relocalization node, in process (no zenoh): where a pose's time goes.

For reference trajectories of 1,000 and 1,000,000 samples (the ellipse of ``bench_stream.py``,
plane x–z) and the query poses of ``bench_stream.py`` (a drive along the reference; ``random``:
anywhere near the loop), times each step of ``Relocalizer.handle`` separately, pose after pose in
stream order, and the whole of it:

- ``decode``: CDR PoseStamped → values (``codec.decode_pose``);
- ``nearest``: ``ReferencePath.query_one`` alone (k*, D, phi of an already aligned pose, with
  its array arguments);
- ``process``: checks + alignment + nearest sample + the result tuple (``Relocalizer.process``);
- ``encode``: every per-pose output (D, phi, state JSON, two PoseStamped, MarkerArray);
- ``handle``: bytes in → all keyed payloads out — what the node does per pose besides zenoh's
  own ``put`` calls and its lock/stats bookkeeping.

These run back to back, hot (the cost of the code itself; per pose the fastest of ``--repeats``
passes). In the node a pose arrives every 500 µs at 2,000 poses/s and the thread sleeps in
between while other processes use the cores: the code then runs cold, 2–4x slower. ``paced``
times ``handle`` that way (one pose every 500 µs, sleeping in between; one pass).

``--baseline DIR``: a checkout of another version (e.g. ``git worktree add /tmp/base HEAD~1``)
is imported alongside this one and timed on the same poses, interleaved in chunks of 100 poses
(paced: pose by pose), so that the load of a shared machine hits both alike; prints both and
the ratio baseline/this. Prints the paced ``handle`` median as a share of the 500 µs a pose may
take at 2,000 poses/s.

    .venv/bin/python bench/bench_reloc_pose.py [--poses 10000] [--baseline DIR]
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
sys.path.insert(0, str(ROOT))

from bench_stream import queries  # noqa: E402

from tagtrail.geometry.se3 import R_from_quat_xyzw  # noqa: E402
from tagtrail.stream import codec  # noqa: E402
from tagtrail.stream import reloc_node as relocalize  # noqa: E402
from tests.stream.cases import reference_frame  # noqa: E402

BUDGET_US = 1e6 / 2000.0  # one pose's share of a second at 2,000 poses/s
CHUNK = 100  # poses per turn when two versions are interleaved


def load_checkout(root: Path) -> tuple[ModuleType, ModuleType]:
    """``(codec, relocalize)`` of the ``tagtrail`` in checkout ``root``, imported alongside the
    one already loaded (its modules are swapped out of ``sys.modules`` meanwhile)."""

    def ours() -> list[str]:
        return [k for k in sys.modules if k == "tagtrail" or k.startswith("tagtrail.")]

    saved = {k: sys.modules.pop(k) for k in ours()}
    sys.path.insert(0, str(root))
    try:
        mods = (
            importlib.import_module("tagtrail.stream.codec"),
            importlib.import_module("tagtrail.stream.reloc_node"),
        )
        if not Path(mods[0].__file__ or "").is_relative_to(root):
            raise SystemExit(f"--baseline {root}: no tagtrail package there")
    finally:
        sys.path.remove(str(root))
        for k in ours():
            del sys.modules[k]
        sys.modules.update(saved)
    return mods


def steps(
    cdc: ModuleType, rel: ModuleType, n_ref: int, payloads: list[bytes]
) -> dict[str, tuple[Callable[[Any], Any], list]]:
    """The timed steps of one version: name → (function, its inputs in stream order)."""
    reloc = rel.Relocalizer(reference_frame(n_ref), "xz")
    for p in payloads[:500]:  # warm-up (builds the long-path index)
        list(reloc.handle(p))
    poses = [cdc.decode_pose(p) for p in payloads]
    outs = [reloc.process(p) for p in poses]
    R = R_from_quat_xyzw(np.array([o.current[3:] for o in outs]))
    aligned = [(o.current[:3], R[i]) for i, o in enumerate(outs)]  # no alignment: = the pose
    path = reloc.path
    return {
        "decode": (cdc.decode_pose, payloads),
        "nearest": (lambda a: path.query_one(*a), aligned),
        "process": (reloc.process, poses),
        "encode": (reloc.encode, outs),
        "handle": (lambda p: list(reloc.handle(p)), payloads),
    }


def hot(fns: list[tuple[Callable[[Any], Any], list]], repeats: int) -> list[np.ndarray]:
    """Per-item time (µs) of each ``fn(item)``, items in order; versions take turns every
    ``CHUNK`` items; per item the fastest of ``repeats`` passes."""
    clock = time.perf_counter_ns
    n = len(fns[0][1])
    best = [np.full(n, np.inf) for _ in fns]
    for _ in range(repeats):
        for lo in range(0, n, CHUNK):
            for (fn, items), b in zip(fns, best, strict=True):
                for i in range(lo, min(lo + CHUNK, n)):
                    t0 = clock()
                    fn(items[i])
                    b[i] = min(b[i], clock() - t0)
    return [b / 1e3 for b in best]


def paced(fns: list[Callable[[Any], Any]], items: list, period_s: float) -> list[np.ndarray]:
    """Per-item time (µs) of each ``fn(item)`` with a call every ``period_s``, sleeping in
    between (versions take turns pose by pose)."""
    clock = time.perf_counter_ns
    t = np.empty((len(fns), len(items)))
    t_next = time.perf_counter()
    for i, it in enumerate(items):
        for v, fn in enumerate(fns):
            t_next += period_s
            time.sleep(max(0.0, t_next - time.perf_counter()))
            t0 = clock()
            fn(it)
            t[v, i] = clock() - t0
    return list(t / 1e3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1_000, 1_000_000])
    ap.add_argument("--poses", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=3, help="passes; per pose the fastest counts")
    ap.add_argument("--paced", type=int, default=3000, help="poses timed at 2,000/s")
    ap.add_argument("--baseline", type=Path, help="checkout of another version to compare")
    args = ap.parse_args()
    versions = [(codec, relocalize)]
    if args.baseline:
        versions.insert(0, load_checkout(args.baseline.resolve()))
    print(
        f"bench_reloc_pose: {args.poses:,} poses (hot: fastest of {args.repeats} passes), "
        f"{args.paced:,} paced at 2,000/s, {os.cpu_count()} cores, load "
        f"{os.getloadavg()[0]:.2f}" + (f", baseline {args.baseline}" if args.baseline else "")
    )
    cols = ["base p50", "base p99"] if args.baseline else []
    cols += ["p50 us", "p99 us"] + (["base/this"] if args.baseline else [])
    print(f"{'reference':>10} {'poses':>6} {'step':>8}" + "".join(f"{c:>10}" for c in cols))
    for n in args.sizes:
        for kind in ("drive", "random"):
            payloads = queries(args.poses, kind == "random")
            fns = [steps(c, r, n, payloads) for c, r in versions]
            res = {s: hot([f[s] for f in fns], args.repeats) for s in fns[0]}
            handle = [f["handle"][0] for f in fns]
            res["paced"] = paced(handle, payloads[: args.paced], BUDGET_US / 1e6)
            for step, ts in res.items():
                figs = [(float(np.median(t)), float(np.percentile(t, 99))) for t in ts]
                line = f"{n:>10,} {kind:>6} {step:>8}"
                line += "".join(f" {p50:9.1f} {p99:9.1f}" for p50, p99 in figs)
                if len(figs) == 2:
                    line += f" {figs[0][0] / figs[1][0]:8.2f}x"
                print(line, flush=True)
            share = float(np.median(res["paced"][-1])) / BUDGET_US
            print(f"{'':>17} paced handle p50 = {share:.1%} of a pose's 500 us at 2,000/s")


if __name__ == "__main__":
    main()
