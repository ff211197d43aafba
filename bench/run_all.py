"""``make bench``: every benchmark of issue 13 in one run, written to ``bench/RESULTS.md``.

One table; each figure is the median of repeats, and each ratio is measured side by side in this
run (the two sides alternate, so load from other work on the machine moves both alike), with the
machine described at the top. Sections (``--only NAME`` runs some):

- ``extract``: stage extract vs a bare single-process detector loop on real photos (JPEG bag);
- ``posegraph``: the pairwise pose graph vs GTSAM at 3 sizes (bench_gtsam);
- ``scale``: the recording phase (``tagtrail run``, joint solve) on ``room --detections`` from
  1,000 to 9,000 frames, and a 10,000-frame run's peak memory (bench_scale);
- ``runner``: no-op rerun and ``status`` at 50 datasets x every stage;
- ``sweep``: a 3x3 optimize sweep vs the 9 single runs it replaces;
- ``dask``: the dask executor (2-worker LocalCluster) vs the local one on 8 datasets;
- ``stream``: streaming relocalization latency (bench_stream).

Run: ``.venv/bin/python bench/run_all.py [--only extract posegraph ...] [--out FILE]``. Other
sections' rows are kept from the existing file when ``--only`` is given. The whole run takes
about 8 minutes on 2 cores.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # as tagtrail.cli.main_entry does, before numpy loads

import argparse  # noqa: E402
import contextlib  # noqa: E402
import importlib.metadata  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import yaml  # noqa: E402

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(ROOT))

from tagtrail.io.layouts import atomic_write_text  # noqa: E402

BIN = Path(sys.executable).parent
TAGTRAIL = str(BIN / "tagtrail")
RESULTS = BENCH / "RESULTS.md"
EXTRACT_COPIES = 2  # the 93 photos, twice over (as bench_extract)
PACKAGES = (
    "numpy",
    "scipy",
    "pandas",
    "pyarrow",
    "opencv-python-headless",
    "pupil-apriltags",
    "gtsam",
    "dask",
    "distributed",
    "eclipse-zenoh",
    "rosbags",
)


@dataclass
class Row:
    """One figure: what, the measurement (text), the ratio, the goal and whether it is met."""

    section: str
    figure: str
    measured: str
    ratio: float | None
    goal: str
    met: bool | None

    def __post_init__(self) -> None:  # numpy scalars -> plain, for the JSON block
        self.ratio = None if self.ratio is None else float(self.ratio)
        self.met = None if self.met is None else bool(self.met)

    def cells(self) -> list[str]:
        ratio = "" if self.ratio is None else f"{self.ratio:.2f}x"
        met = {True: "yes", False: "**no**", None: ""}[self.met]
        return [self.figure, self.measured, ratio, self.goal, met]


def med(xs: list[float]) -> float:
    return statistics.median(xs)


def run(*cmd: str, cwd: Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    res = subprocess.run(list(cmd), cwd=cwd, capture_output=True, text=True)
    if check and res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return res


def timed(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def fresh(project: Path) -> None:
    """An empty artifact store: nothing cached, sources hashed again."""
    for d in ("artifacts", "outputs", "sweeps"):
        shutil.rmtree(project / d, ignore_errors=True)


def demo_pipeline(datasets: dict[str, dict[str, object]]) -> str:
    """The demo pipeline's stages with ``datasets`` (a query names the reference's map)."""
    from tagtrail.commands.demo import template

    doc = yaml.safe_load(template())
    doc["datasets"] = datasets
    return yaml.safe_dump(doc, sort_keys=False)


def query(source: Path) -> dict[str, object]:
    return {
        "source": str(source),
        "inputs": {
            "trajectory.tag_map": "reference:optimize.tag_map",
            "trajectory.map_report": "reference:optimize.report",
            "align.tag_map": "reference:optimize.tag_map",
        },
    }


# --- extract ----------------------------------------------------------------------------------


def bench_extract(repeats: int) -> list[Row]:
    import bench_extract as be
    import cv2
    import numpy as np

    from tagtrail.io.camera_files import read_camera_file
    from tagtrail.io.sources import open_source
    from tagtrail.schemas.pipeline import DatasetConfig
    from tagtrail.stages import extract
    from tagtrail.vision.apriltag import detect, get_detector

    folder = be.REALDATA / "upenn_ar_tag36h11_id12_seq" / "frames"
    files = sorted(folder.glob("frame*.jpg")) * EXTRACT_COPIES
    cam = read_camera_file(folder / "camera.yaml")
    cfg = extract.Params().detector()
    gray = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    jpeg = [np.frombuffer(f.read_bytes(), np.uint8) for f in files]
    det = get_detector(cfg)
    sides: dict[str, Callable[[], object]] = {
        "bare": lambda: [det.detect(img) for img in gray],
        "bare_decode": lambda: [det.detect(cv2.imdecode(b, cv2.IMREAD_GRAYSCALE)) for b in jpeg],
        "bare_refit": lambda: [detect(img, cfg, cam) for img in gray],
    }
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "jpeg"
        be.write_bag(bag, files, cam, compressed=True)

        def ext(refit: bool) -> None:
            with open_source(DatasetConfig(source=bag)) as src:
                out = extract.run(src, extract.Params(workers=0, refit_corners=refit))
            assert len(out["frames"]) == len(files)

        sides["extract"] = lambda: ext(False)
        sides["extract_refit"] = lambda: ext(True)
        for fn in sides.values():  # warm-up: detectors built, worker processes started
            fn()
        times: dict[str, list[float]] = {k: [] for k in sides}
        cpu: dict[str, list[float]] = {k: [] for k in sides}
        for _ in range(repeats):
            for k, fn in sides.items():
                c0 = be.cpu_s()  # this process and its workers: the load-independent cost
                times[k].append(timed(fn))
                cpu[k].append(be.cpu_s() - c0)
    fps = {k: len(files) / med(v) for k, v in times.items()}
    ms = {k: 1e3 * med(v) / len(files) for k, v in cpu.items()}
    cores = len(os.sched_getaffinity(0))
    no_fit = fps["extract"] / fps["bare"]
    fit = fps["extract_refit"] / fps["bare_refit"]
    return [
        Row(
            "extract",
            "extract, no corner re-fit, vs the bare detector loop",
            f"{fps['extract']:.0f} vs {fps['bare']:.0f} frames/s ({len(files)} real 640x480 "
            f"JPEG frames; extract decodes them on {cores} workers, the loop gets them decoded; "
            f"loop incl. decoding {fps['bare_decode']:.0f} frames/s); CPU {ms['extract']:.1f} vs "
            f"{ms['bare']:.1f} ms/frame",
            no_fit,
            ">= 0.9x",
            no_fit >= 0.9,
        ),
        Row(
            "extract",
            "extract with the corner re-fit, vs the loop with the re-fit",
            f"{fps['extract_refit']:.0f} vs {fps['bare_refit']:.0f} frames/s; CPU "
            f"{ms['extract_refit']:.1f} vs {ms['bare_refit']:.1f} ms/frame",
            fit,
            "",
            None,
        ),
    ]


# --- pose graph vs GTSAM ----------------------------------------------------------------------


def bench_posegraph(repeats: int) -> list[Row]:
    import bench_gtsam as bg

    rows = []
    for n, e in bg.SIZES:
        c = bg.compare(n, e, repeats)
        size = f"{n} tags / {e // 1000}k edges"
        rows.append(
            Row(
                "posegraph",
                f"pose graph vs GTSAM, {size}: time",
                f"{c.ours_s:.3f} s ({c.nfev} evaluations) vs {c.gtsam_s:.3f} s (its LM "
                f"alone {c.gtsam_lm_s:.3f} s, {c.gtsam_iters} iterations)",
                c.time_ratio,
                "<= 1.5x",
                c.time_ratio <= 1.5,
            )
        )
        # the solvers compared on the same cost: both with GTSAM's Huber kernel; the default
        # soft_l1 beside it (a different cost, so a different minimum)
        rows.append(
            Row(
                "posegraph",
                f"pose graph vs GTSAM, {size}: error (same Huber kernel)",
                f"{c.huber_err_m * 1e3:.3f} vs {c.gtsam_err_m * 1e3:.3f} mm mean tag "
                f"position error; with the default soft_l1 {c.ours_err_m * 1e3:.3f} mm "
                f"= {c.error_ratio:.3f}x",
                c.same_kernel_error_ratio,
                "<= 1.0x",
                c.same_kernel_error_ratio <= 1.0,
            )
        )
    return rows


# --- the joint solver's scaling (the recording phase) -----------------------------------------


def recording(work: Path, scenario: str, frames: int) -> Path:
    project = work / f"{scenario}-{frames}"
    project.mkdir(parents=True)
    run(
        TAGTRAIL,
        "simulate",
        scenario,
        "--out",
        "sim",
        "--detections",
        "--frames",
        str(frames),
        "--query-frames",
        "2",
        "--no-progress",
        "--force",
        cwd=project,
    )
    reference = "sim/reference" if scenario == "room" else f"sim/{scenario}"
    run(TAGTRAIL, "init", "--reference", reference, "--tag-size", "0.16", "--force", cwd=project)
    return project


def phase(project: Path) -> tuple[float, float, dict[str, float]]:
    """(wall s, peak RSS GB, seconds per stage) of the recording phase from an empty store."""
    import bench_scale

    wall, gb, _ = bench_scale.timed_run(project)
    log = json.loads((project / "artifacts" / "runs" / "last_run.json").read_text())
    per: dict[str, float] = {}
    for s in log:
        per[s["stage"]] = per.get(s["stage"], 0.0) + s["seconds"]
    return wall, gb, per


def bench_scale_rows(repeats: int) -> list[Row]:
    import pandas as pd

    rows = []
    with tempfile.TemporaryDirectory(prefix="tagtrail-bench-") as d:
        for scenario, frames, reps in (
            ("room", 1000, repeats),
            ("hall", 1000, repeats),
            ("room", 3000, repeats),
            ("room", 9000, repeats),
            ("room", 10000, 1),
        ):
            project = recording(Path(d), scenario, frames)
            ref = project / "sim" / ("reference" if scenario == "room" else scenario)
            gt = pd.read_csv(ref / "ground_truth" / "tag_map.csv")
            walls, rss, opt, traj = [], [], [], []
            for _ in range(reps):
                wall, gb, per = phase(project)
                walls.append(wall)
                rss.append(gb)
                opt.append(per.get("optimize", float("nan")))
                traj.append(per.get("trajectory", float("nan")))
            what = f"{scenario}, {frames:,} frames x {len(gt)} tags"
            measured = (
                f"{med(walls):.1f} s, peak RSS {med(rss):.2f} GB; optimize (joint) "
                f"{med(opt):.1f} s, trajectory {med(traj):.1f} s"
                + (f" (median of {reps})" if reps > 1 else " (1 run)")
            )
            if (scenario, frames) == ("room", 9000):
                ok = med(walls) < 30.0 and med(rss) < 1.5
                rows.append(
                    Row(
                        "scale",
                        f"recording phase, {what} (issue 12)",
                        measured,
                        med(walls) / 30.0,
                        "< 30 s and < 1.5 GB (ratio: time / 30 s)",
                        ok,
                    )
                )
            elif frames == 10000:
                rows.append(
                    Row(
                        "scale",
                        f"peak memory of a 10,000-frame run ({what})",
                        measured,
                        med(rss) / 1.5,
                        "< 1.5 GB (ratio: RSS / 1.5 GB)",
                        med(rss) < 1.5,
                    )
                )
            else:
                rows.append(Row("scale", f"recording phase, {what}", measured, None, "", None))
            shutil.rmtree(project, ignore_errors=True)
    return rows


# --- runner overhead at 50 datasets -----------------------------------------------------------


def bench_runner(repeats: int) -> list[Row]:
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import load_pipeline
    from tagtrail.sim import simulate
    from tagtrail.stages import REGISTRY

    with tempfile.TemporaryDirectory(prefix="tagtrail-bench-") as d:
        root = Path(d)
        datasets: dict[str, dict[str, object]] = {}
        seed = 0
        while len(datasets) < 50:  # 4 maps (the recording phase) and 46 queries against one
            out = simulate(
                "room",
                root / "data" / f"s{seed}",
                frames=30,
                query_frames=3,
                detections=True,
                seed=seed,
            )
            for name, folder in out.items():
                if len(datasets) == 50:
                    break
                if seed == 0 and name == "reference":
                    datasets["reference"] = {"source": str(folder)}
                elif name == "reference" and seed < 4:  # another recording: its own map
                    datasets[f"map_{seed}"] = {"source": str(folder)}
                elif name != "reference":
                    datasets[f"{name}_s{seed}"] = query(folder)
            seed += 1
        (root / "pipeline.yaml").write_text(demo_pipeline(datasets))

        def runner() -> Runner:
            return Runner(load_pipeline(root / "pipeline.yaml", REGISTRY))

        first = timed(lambda: run(TAGTRAIL, "run", "-j", "2", cwd=root))
        states = runner().plan()
        if any(s.status != "cached" for s in states):  # the code changed meanwhile (a shared
            run(TAGTRAIL, "run", "-j", "2", cwd=root)  # working tree): catch up once
            states = runner().plan()
        stale = [f"{s.stage} [{s.dataset}]: {s.reason}" for s in states if s.status != "cached"]
        assert not stale, f"the first run left stale nodes: {stale[:5]}"
        n_nodes = len(states)
        noop, status, cli_run, cli_status = [], [], [], []
        for _ in range(repeats):
            noop.append(timed(lambda: runner().run()))
            status.append(timed(lambda: runner().plan()))
            cli_run.append(timed(lambda: run(TAGTRAIL, "run", cwd=root)))
            cli_status.append(timed(lambda: run(TAGTRAIL, "status", cwd=root)))
    note = f"4 maps + 46 queries, {n_nodes} nodes (first run {first:.0f} s with -j 2)"
    return [
        Row(
            "runner",
            "no-op rerun, 50 datasets x every stage",
            f"{med(noop):.2f} s in process; `tagtrail run` process {med(cli_run):.2f} s "
            f"(start-up, imports and the outputs check included); {note}",
            med(noop) / 1.0,
            "< 1 s (ratio: time / 1 s)",
            med(noop) < 1.0,
        ),
        Row(
            "runner",
            "`status`, 50 datasets x every stage",
            f"{med(status):.2f} s in process; `tagtrail status` process {med(cli_status):.2f} s",
            med(status) / 1.0,
            "< 1 s (ratio: time / 1 s)",
            med(status) < 1.0,
        ),
    ]


# --- sweep vs single runs ---------------------------------------------------------------------

LOSSES, SCALES = ("linear", "soft_l1", "huber"), ("0.05", "0.1", "0.2")
SWEEP_FRAMES = 100
DASK_FRAMES = 200


def bench_sweep(repeats: int) -> list[Row]:
    from tagtrail.sim import simulate

    with tempfile.TemporaryDirectory(prefix="tagtrail-bench-") as d:
        root = Path(d)
        out = simulate("room", root / "data", frames=SWEEP_FRAMES, query_frames=5, detections=True)
        (root / "pipeline.yaml").write_text(
            demo_pipeline(
                {n: ({"source": str(f)} if n == "reference" else query(f)) for n, f in out.items()}
            )
        )
        grid = [
            "-S",
            f"optimize.loss={','.join(LOSSES)}",
            "-S",
            f"optimize.f_scale={','.join(SCALES)}",
        ]

        def sweep() -> None:
            fresh(root)
            run(TAGTRAIL, "sweep", *grid, cwd=root)

        def singles() -> None:
            fresh(root)
            for loss in LOSSES:
                for fs in SCALES:
                    run(
                        TAGTRAIL,
                        "run",
                        "-S",
                        f"optimize.loss={loss}",
                        "-S",
                        f"optimize.f_scale={fs}",
                        cwd=root,
                    )

        t_sweep, t_single = [], []
        for _ in range(repeats):
            t_sweep.append(timed(sweep))
            t_single.append(timed(singles))
    ratio = med(t_sweep) / med(t_single)
    return [
        Row(
            "sweep",
            "3x3 optimize sweep vs the 9 single `tagtrail run -S` it replaces",
            f"{med(t_sweep):.1f} s vs {med(t_single):.1f} s (room, {SWEEP_FRAMES} frames, 4 "
            "datasets, empty store each time; both run extract once)",
            ratio,
            "<= 1x (no overhead)",
            ratio <= 1.0,
        )
    ]


# --- dask vs local ----------------------------------------------------------------------------


def bench_dask(repeats: int) -> list[Row]:
    from tagtrail.sim import simulate

    with tempfile.TemporaryDirectory(prefix="tagtrail-bench-") as d:
        root = Path(d)
        datasets: dict[str, dict[str, object]] = {}
        for seed in (0, 1):
            out = simulate(
                "room",
                root / "data" / f"s{seed}",
                frames=DASK_FRAMES,
                query_frames=10,
                detections=True,
                seed=seed,
            )
            for name, folder in out.items():
                if name == "reference":
                    datasets["reference" if seed == 0 else "map_1"] = {"source": str(folder)}
                else:
                    datasets[f"{name}_s{seed}"] = query(folder)
        assert len(datasets) == 8
        (root / "pipeline.yaml").write_text(demo_pipeline(datasets))

        def local() -> None:
            fresh(root)
            run(TAGTRAIL, "run", "-j", "2", cwd=root)

        def dask() -> float:
            """Seconds of a successful run; once more when the shared working tree's code
            changed under it (the workers refuse code the runner did not fingerprint)."""
            for _ in range(2):
                fresh(root)
                t0 = time.perf_counter()
                res = run(TAGTRAIL, "run", "--executor", "dask", "-j", "2", cwd=root, check=False)
                if res.returncode == 0:
                    return time.perf_counter() - t0
                if "runs other code" not in res.stderr:
                    break
            raise RuntimeError(f"tagtrail run --executor dask failed:\n{res.stderr[-2000:]}")

        t_local, t_dask = [], []
        for _ in range(repeats):
            t_local.append(timed(local))
            t_dask.append(dask())
    ratio = med(t_dask) / med(t_local)
    return [
        Row(
            "dask",
            "dask executor (2-worker LocalCluster) vs local (-j 2), 8 datasets",
            f"{med(t_dask):.1f} s vs {med(t_local):.1f} s (room detections, "
            f"{DASK_FRAMES}-frame "
            "maps, empty store each time; the cluster's start included)",
            ratio,
            "",
            None,
        )
    ]


# --- streaming --------------------------------------------------------------------------------


def bench_stream(repeats: int) -> list[Row]:
    import bench_stream as bs

    args = argparse.Namespace(
        poses=2000,
        repeats=repeats,
        rate=bs.GOAL_RATE,
        express=False,
        node_batching=False,
        random_poses=False,
    )
    n_ref = 1_000_000
    with (
        tempfile.TemporaryDirectory(prefix="tagtrail-bench-") as d,
        contextlib.redirect_stdout(io.StringIO()),
    ):
        res = bs.bench_size(n_ref, args, Path(d))

    def m(mode: str, key: str) -> float:
        return med([r[key] for r in res[mode]])

    lost = max(args.poses - r["received"] for r in res["paced"])
    p99 = m("ping-pong", "p99_ms")
    return [
        Row(
            "stream",
            "streaming relocalization latency, 1,000,000-sample reference",
            f"ping-pong p50 {m('ping-pong', 'p50_ms'):.2f} ms, p99 {p99:.2f} ms; paced at "
            f"2,000 poses/s p99 {m('paced', 'p99_ms'):.2f} ms, {lost} lost",
            p99 / bs.GOAL_P99_MS,
            "p99 < 2 ms (ratio: p99 / 2 ms)",
            p99 < bs.GOAL_P99_MS,
        ),
        Row(
            "stream",
            "streaming throughput (flood)",
            f"{m('flood', 'rate'):.0f} poses/s",
            m("flood", "rate") / bs.GOAL_RATE,
            ">= 2,000 poses/s (ratio: rate / 2,000)",
            m("flood", "rate") >= bs.GOAL_RATE,
        ),
    ]


SECTIONS: dict[str, tuple[Callable[[int], list[Row]], int]] = {
    "extract": (bench_extract, 3),
    "posegraph": (bench_posegraph, 3),
    "scale": (bench_scale_rows, 3),
    "runner": (bench_runner, 3),
    "sweep": (bench_sweep, 2),
    "dask": (bench_dask, 2),
    "stream": (bench_stream, 3),
}


# --- the file ---------------------------------------------------------------------------------


def machine() -> str:
    cpu = "unknown CPU"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    ram = "?"
    with contextlib.suppress(OSError, ValueError, IndexError):
        kb = int(Path("/proc/meminfo").read_text().split("MemTotal:")[1].split()[0])
        ram = f"{kb / 2**20:.0f} GB"
    versions = []
    for p in PACKAGES:
        try:
            versions.append(f"{p} {importlib.metadata.version(p)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{p} (not installed)")
    return (
        f"{cpu}, {os.cpu_count()} cores ({len(os.sched_getaffinity(0))} usable), {ram} RAM; "
        f"{platform.system()} {platform.release()}; Python {platform.python_version()}; "
        + ", ".join(versions)
    )


def commit() -> str:
    res = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    )
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    ).stdout.strip()
    return res.stdout.strip() + (" (with uncommitted changes)" if dirty else "")


def table(rows: list[Row]) -> list[str]:
    lines = ["| figure | measured | ratio | goal | met |", "|---|---|---|---|---|"]
    lines += ["| " + " | ".join(c.replace("|", "\\|") for c in r.cells()) + " |" for r in rows]
    return lines


def read_rows(path: Path) -> dict[str, list[Row]]:
    """The rows of an existing RESULTS.md by section (from its JSON block)."""
    try:
        text = path.read_text()
        block = text.split("<!-- rows\n", 1)[1].split("\n-->", 1)[0]
        return {s: [Row(**r) for r in rs] for s, rs in json.loads(block).items()}
    except (OSError, IndexError, ValueError, TypeError):
        return {}


def read_runs(path: Path) -> dict[str, dict[str, Any]]:
    """How each section of an existing RESULTS.md was run (seconds, load, commit, date)."""
    try:
        block = path.read_text().split("<!-- runs\n", 1)[1].split("\n-->", 1)[0]
        runs: dict[str, dict[str, Any]] = json.loads(block)
        return runs
    except (OSError, IndexError, ValueError):
        return {}


def write(path: Path, rows: dict[str, list[Row]], runs: dict[str, dict[str, Any]]) -> None:
    ordered = [r for s in SECTIONS for r in rows.get(s, [])]
    total = sum(r["s"] for r in runs.values())
    ran = ", ".join(
        f"{s} {r['s']:.0f} s (load {r['load']:.1f}, {r['commit']}, {r['date']})"
        for s, r in sorted(runs.items(), key=lambda kv: list(SECTIONS).index(kv[0]))
    )
    text = "\n".join(
        [
            "# tagtrail benchmarks",
            "",
            f"Written by `make bench` (`bench/run_all.py`; `--only SECTION` reruns one section and "
            f"keeps the others); the sections took {total / 60:.1f} min in all; per section (its "
            f"1-min load average at its start, the commit and the date it ran at): {ran}.",
            "",
            f"Machine: {machine()}.",
            "",
            "Each figure is the median of its repeats; each ratio is measured side by side in this "
            "run (the two sides alternate), so it holds better than the absolute times, which "
            "move with other work on the machine. Ratios against a goal are stated in the goal "
            "column.",
            "",
            *table(ordered),
            "",
            "Reading the table:",
            "",
            "- extract runs its workers on every core; its throughput ratio needs the second core "
            "free (the 1-min load average is given per section). The CPU per frame (this process "
            "and its workers) does not depend on the load.",
            "- The pose graph: tagtrail's default kernel is soft_l1, which GTSAM does not have; "
            "GTSAM runs Huber at the same scale (0.1). Both start from the same spanning-tree "
            "guess, timed on both sides; GTSAM's time includes building its factor graph from "
            "Python (its LM alone is given). The error ratio compares the solvers on the same "
            "cost (Huber on both sides); the default soft_l1's error is in the measured column.",
            "- The recording phase: `tagtrail run` (extract .. smooth, eval; the joint solve) in a "
            "child process from an empty store; peak RSS is the largest resident set of that "
            "process (its `VmHWM`) and of the workers it waited for, reported by the child (not "
            "its `ru_maxrss` seen from here, which Linux seeds with this process's own peak).",
            "- The runner rows time the runner itself (a `Runner` in this process); the `tagtrail` "
            "processes add Python's start-up and the imports.",
            "- dask: a fresh `LocalCluster` per run (its start included), on the same 2 cores.",
            "",
            "How each is measured: `bench/run_all.py` (the sections' docstrings), "
            "`bench_extract.py`, `bench_gtsam.py`, `bench_scale.py`, `bench_stream.py`.",
            "",
            "<!-- rows",
            json.dumps({s: [r.__dict__ for r in rs] for s, rs in rows.items()}, indent=1),
            "-->",
            "<!-- runs",
            json.dumps(runs, indent=1),
            "-->",
            "",
        ]
    )
    atomic_write_text(path, text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=list(SECTIONS), default=None)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rows = read_rows(args.out) if args.only else {}
    runs = read_runs(args.out) if args.only else {}
    for name, (fn, repeats) in SECTIONS.items():
        if args.only and name not in args.only:
            continue
        load = os.getloadavg()[0]
        print(f"[{name}] … (load average {load:.1f})", flush=True)
        t0 = time.perf_counter()
        rows[name] = fn(repeats)
        took = time.perf_counter() - t0
        runs[name] = {
            "s": took,
            "load": load,
            "commit": commit(),
            "date": time.strftime("%Y-%m-%d %H:%M"),
        }
        for r in rows[name]:
            print(
                f"  {r.figure}: {r.measured}"
                + ("" if r.ratio is None else f" -> {r.ratio:.2f}x")
                + ("" if r.met is None else f" ({'met' if r.met else 'NOT met'})"),
                flush=True,
            )
        print(f"  ({took:.0f} s)", flush=True)
    write(args.out, rows, runs)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
