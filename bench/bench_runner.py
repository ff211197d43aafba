"""Runner overhead: a no-op rerun and `status` when the source is a 1 GB file.

Prints the first (hashing) status time, then medians of repeated no-op `run` and `status`, in
process (runner only) and as whole CLI invocations (Python start-up + imports included).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tagtrail.runner.execute import Runner  # noqa: E402
from tagtrail.runner.spec import load_pipeline  # noqa: E402
from tests.runner.toy import copy_stages, load_registry  # noqa: E402

GB = 1 << 30


def timed(fn, n: int = 7) -> float:
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        stages = copy_stages(root / "stages")
        big = root / "big.bin"
        with open(big, "wb") as f:
            block = os.urandom(1 << 24)
            for _ in range(GB // len(block)):
                f.write(block)
        (root / "ref.csv").write_text("value\n1\n2\n")
        (root / "pipeline.yaml").write_text(
            "datasets:\n  reference: {source: ref.csv}\n  query: {source: big.bin}\nstages: {}\n"
        )
        reg = load_registry(stages)

        def runner() -> Runner:
            return Runner(load_pipeline(root / "pipeline.yaml", reg))

        t0 = time.perf_counter()
        runner().plan()
        first = time.perf_counter() - t0
        # The 1 GB query source is not a CSV the toy stages could read: `status` is measured on
        # it (it hashes it once, then only stats it); the no-op run on a readable pipeline.
        status = timed(lambda: runner().plan())
        (root / "pipeline.yaml").write_text(
            "datasets:\n  reference: {source: ref.csv}\n  query: {source: ref.csv}\nstages: {}\n"
        )
        runner().run()
        noop = timed(lambda: runner().run())

        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        driver = ROOT / "tests" / "runner" / "toy" / "driver.py"

        def cli(*args: str) -> None:
            subprocess.run(
                [sys.executable, str(driver), str(stages), *args],
                cwd=root,
                env=env,
                check=True,
                capture_output=True,
            )

        (root / "pipeline.yaml").write_text(
            "datasets:\n  reference: {source: ref.csv}\n  query: {source: big.bin}\nstages: {}\n"
        )
        cli_status = timed(lambda: cli("status"), n=5)

    real_noop, real_cli = real_pipeline()
    print(f"status, first (hashes the 1 GB source): {first:8.3f} s")
    print(
        f"status, median after hashing:           {status * 1e3:8.2f} ms  "
        f"(ratio to 1 s budget: {status:.4f})"
    )
    print(
        f"no-op run (9 nodes, all cached), median: {noop * 1e3:8.2f} ms  "
        f"(ratio to 1 s budget: {noop:.4f})"
    )
    print(
        f"`tagtrail status` CLI process, median:   {cli_status * 1e3:8.2f} ms  "
        f"(incl. interpreter start-up)"
    )
    print(
        f"real demo pipeline (9 stages x 4 datasets), no-op run, median: {real_noop * 1e3:8.2f}"
        f" ms  (ratio to 1 s budget: {real_noop:.4f})"
    )
    print(
        f"`tagtrail run` no-op CLI process on it, median:             {real_cli * 1e3:8.2f} ms"
        "  (incl. interpreter start-up and imports)"
    )


def real_pipeline() -> tuple[float, float]:
    """No-op rerun of the real demo pipeline on a small simulated `room` recording."""
    from tagtrail.commands.demo import template
    from tagtrail.sim import simulate
    from tagtrail.stages import REGISTRY

    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        simulate("room", root / "data", compressed=True, frames=60, query_frames=5)
        (root / "pipeline.yaml").write_text(template())
        Runner(load_pipeline(root / "pipeline.yaml", REGISTRY)).run()
        noop = timed(lambda: Runner(load_pipeline(root / "pipeline.yaml", REGISTRY)).run())

        def cli() -> None:
            subprocess.run(
                [sys.executable, "-m", "tagtrail.cli", "run"],
                cwd=root,
                check=True,
                capture_output=True,
                env={**os.environ, "PYTHONPATH": str(ROOT)},
            )

        return noop, timed(cli, n=5)


if __name__ == "__main__":
    main()
