"""Benchmark (issue 12): accuracy of the defaults `tagtrail init` writes, per method, scenario,
noise level and source, against the simulator's ground truth and each scenario's per-frame floor.

For each scenario (circle, room's ``reference``, hall, corridor) x noise level (``low``: images
with the renderer's defaults, 2 DN noise / 0.5 px blur, detections with 0.3 px corner noise;
``high``: twice as noisy, 4 DN / 1.0 px, 0.6 px) x source (``images``: MCAP rgb8;
``detections``: /detections + /camera_info): ``tagtrail simulate`` into a temporary folder,
``tagtrail init --reference``, then ``tagtrail run --force`` with the defaults (``joint``) and
with ``-S optimize.method=pairwise -S trajectory.method=lsq`` (the paper's method: its pose
graph, per-frame fusion and the smoother), each timed end to end (``run s``).

Figures, all from the run's artifacts:

- trajectory (the smoothed one, every frame posed) and tag errors: ``tagtrail eval --json``'s
  ``gauge_free`` block, i.e. after the best rigid fit of the map to ground truth, applied to map
  and trajectory alike (the fair comparison with the floor, which has no gauge); ``anch``: the
  anchored trajectory mean (world = the map's anchor tag), for reference;
- ``tags``: mapped / ground-truth tags, ``comp``: components of the tag graph (edges.graph);
- ``posed``: posed frames / frames with at least one detection (extract.detections);
- ``floor``: multi-tag PnP of every frame against the TRUE tag map from the run's own detections
  and observations (``geometry.fusion.frame_poses``, method ``pnp``: frames with one tag get the
  lower-reprojection IPPE pose), the best any frame-by-frame method can do; its ``target`` cell
  gives its median, the share of one-tag frames and how many frames are off by > 50 cm (IPPE
  flips of a single oblique tag: they dominate the floor's mean in sparse or noisy scenes).

Targets (issue 12): dense (circle, room): trajectory mean <= 0.75 x floor mean, tags <= 0.6 cm,
rotation <= 0.3 deg; sparse (hall, corridor): trajectory mean <= 2.5 cm and max <= 10 cm, tags
<= 2 cm, every tag in one map, >= 95 % of the frames that see a tag posed. Tag error = mean
position error. The ``target`` column says yes or which failed.

Run: ``.venv/bin/python bench/bench_accuracy.py [--quick] [--scenarios hall,room] [--keep DIR]``
(full: the scenarios' natural lengths at 0.3 m/s and 30 fps, ~15 min on 2 cores; ``--quick``:
a third of the frames). Prints a markdown table and writes it to bench/ACCURACY.md (full runs
only, unless ``--out``), keeping the real-data part bench_realdata_tables.py put there.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tagtrail.geometry.fusion import frame_poses
from tagtrail.geometry.ippe import best_pose
from tagtrail.geometry.se3 import T_from_xyz_quat, pose_error
from tagtrail.io.layouts import read_tag_map, read_trajectory
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.schemas.artifacts import CORNER_COLS, POSE_COLS, ippe_solutions
from tagtrail.sim.scenarios import SimOptions, build
from tagtrail.stages import REGISTRY

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SCENARIOS = ("circle", "room", "hall", "corridor")
RECORDING = {"room": "reference"}  # the recording mapped; others: the scenario's name
DENSE = ("circle", "room")
LEVELS = {  # simulate flags per source and noise level
    ("images", "low"): ["--image-noise", "2", "--blur", "0.5"],
    ("images", "high"): ["--image-noise", "4", "--blur", "1.0"],
    ("detections", "low"): ["--detections", "--corner-noise", "0.3"],
    ("detections", "high"): ["--detections", "--corner-noise", "0.6"],
}
# the paper's method: pairwise pose graph, per-frame fusion (the original tool's lsq), smoothing
METHODS = {
    "joint": [],
    "pairwise": ["-S", "optimize.method=pairwise", "-S", "trajectory.method=lsq"],
}
REALDATA_MARKER = "<!-- realdata -->"  # bench_realdata_tables.py's part of ACCURACY.md follows
ODOMETRY_MARKER = "<!-- odometry -->"  # --odometry's part (between two of these)
# --odometry: the scenes with and without the wheel-odometry prior (issue 27): the existing ones
# (never worse with it by more than 5 %) and those with a stretch without a tag in view
ODOM_SCENARIOS = ("circle", "room", "hall", "corridor", "corridor_gap", "room_blank_turn")
ODOM_FLAGS = ["--detections", "--corner-noise", "0.3", "--odom-scale-error", "0.02"]


@dataclass
class Row:
    scenario: str
    source: str
    level: str
    method: str
    traj_mean: float
    traj_p95: float
    traj_max: float
    rot_mean: float
    traj_anchored: float | None = None
    tags_mean: float | None = None
    tags_max: float | None = None
    tags: str = ""
    comps: int | None = None
    all_tags: bool = False
    posed: int = 0
    seen: int = 0
    run_s: float | None = None
    target: str = ""


def tagtrail(*args: str, cwd: Path) -> str:
    """Run the ``tagtrail`` command of this venv in ``cwd``; its stdout (raises on failure)."""
    res = subprocess.run([str(BIN / "tagtrail"), *args], cwd=cwd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"tagtrail {' '.join(args)} failed ({res.returncode}):\n{res.stderr}")
    return res.stdout


def artifact(runner: Runner, stage: str, output: str) -> Any:
    key = next(s.key for s in runner.plan([stage]) if s.stage == stage and s.status == "cached")
    assert key is not None, f"{stage} is not up to date"
    return runner.store.load(stage, key, output)


def natural_frames(scenario: str) -> int:
    scenes = build(scenario, SimOptions())
    name = RECORDING.get(scenario, scenario)
    return len(next(s for s in scenes if s.name == name).t_ns)


def poses(df: pd.DataFrame) -> np.ndarray:
    v = df[POSE_COLS].to_numpy(np.float64)
    return T_from_xyz_quat(v[:, :3], v[:, 3:])


def floor(runner: Runner, gt_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame floor: (position errors m, angle errors deg, tags per frame) of multi-tag PnP of
    every posed frame against the true tag map, from the run's detections and observations."""
    gt_tags, _ = read_tag_map(gt_dir / "tag_map.yaml")
    gt_traj = read_trajectory(gt_dir / "trajectory.csv")
    true = dict(zip(gt_tags["tag_id"].to_numpy(np.int64), poses(gt_tags), strict=True))
    obs = artifact(runner, "pnp", "observations")
    det = artifact(runner, "extract", "detections")
    camera = artifact(runner, "extract", "camera")
    obs = obs[obs["tag_id"].isin(list(true))]
    obs = obs[~obs.duplicated(["frame_idx", "tag_id"], keep=False)]
    obs = obs.sort_values(["frame_idx", "tag_id"], kind="stable")
    uframe, group = np.unique(obs["frame_idx"].to_numpy(np.int64), return_inverse=True)
    t_ns = obs.groupby("frame_idx")["t_ns"].first().reindex(uframe).to_numpy(np.int64)
    d = det.drop_duplicates(["frame_idx", "tag_id"], keep=False).set_index(["frame_idx", "tag_id"])
    key = pd.MultiIndex.from_arrays([obs["frame_idx"].to_numpy(), obs["tag_id"].to_numpy()])
    px = d[CORNER_COLS].reindex(key).to_numpy(np.float64).reshape(-1, 4, 2)
    W = np.stack([true[t] for t in obs["tag_id"].to_numpy(np.int64)])
    res = frame_poses(
        W,
        best_pose(*ippe_solutions(obs)),
        group,
        len(uframe),
        corners_px=px,
        size_m=obs["size_m"].to_numpy(np.float64),
        camera=camera,
        method="pnp",
        loss="soft_l1",
        f_scale=0.1,
        rot_weight_m=1.0,
        ransac_px=3.0,
    )
    gt = dict(zip(gt_traj["t_ns"].to_numpy(np.int64), poses(gt_traj), strict=True))
    ok = np.isfinite(res.world_T_cam).all(axis=(1, 2)) & np.isin(t_ns, list(gt))
    dt, dr = pose_error(res.world_T_cam[ok], np.stack([gt[t] for t in t_ns[ok]]))
    return dt, np.degrees(dr), res.n_tags[ok]


def method_row(project: Path, scenario: str, source: str, level: str, method: str) -> Row:
    """Run ``method`` on the project (timed), read its evaluation and artifacts."""
    t0 = time.perf_counter()
    tagtrail("run", "--force", *METHODS[method], cwd=project)
    run_s = time.perf_counter() - t0
    doc = json.loads(tagtrail("eval", "--json", *METHODS[method], cwd=project))["evaluation"]
    free = doc["gauge_free"] or {}
    traj, tags = free.get("trajectory") or doc["trajectory"], free.get("tags") or doc["tags"]
    runner = Runner(
        load_pipeline(
            project / "pipeline.yaml", REGISTRY, [a for a in METHODS[method] if a != "-S"]
        )
    )
    frames = artifact(runner, "extract", "detections")["t_ns"].unique()
    est = artifact(runner, "smooth", "trajectory")
    tag_map = artifact(runner, "optimize", "tag_map")
    graph = artifact(runner, "edges", "graph")
    gt_tags, _ = read_tag_map(project / "sim" / RECORDING.get(scenario, scenario) / "ground_truth")
    n_gt = gt_tags["tag_id"].nunique()
    mapped = int(tag_map["tag_id"].isin(gt_tags["tag_id"]).sum())
    pos, ang = traj["position_m"], traj["angle_deg"]
    return Row(
        scenario,
        source,
        level,
        method,
        pos["mean"],
        pos["p95"],
        pos["max"],
        ang["mean"],
        doc["trajectory"]["position_m"]["mean"],
        tags["position_m"]["mean"],
        tags["position_m"]["max"],
        f"{mapped}/{n_gt}",
        int(graph["n_components"]),
        mapped == n_gt,
        int(np.isin(est["t_ns"], frames).sum()),
        len(frames),
        run_s,
    )


def target(row: Row, floor_mean: float) -> str:
    """'yes', or the issue-12 targets this row misses."""
    miss = []
    if row.scenario in DENSE:
        if row.traj_mean > 0.75 * floor_mean:
            miss.append(f"traj {row.traj_mean / floor_mean:.2f}x floor")
        if row.tags_mean is None or row.tags_mean > 0.006:
            miss.append("tags")
        if row.rot_mean > 0.3:
            miss.append("rot")
    else:
        if row.traj_mean > 0.025:
            miss.append("traj mean")
        if row.traj_max > 0.10:
            miss.append("traj max")
        if row.tags_mean is None or row.tags_mean > 0.02:
            miss.append("tags")
        if not row.all_tags or row.comps != 1:
            miss.append("one map")
        if row.posed < 0.95 * row.seen:
            miss.append("posed")
    return "yes" if not miss else "no: " + ", ".join(miss)


def combo(
    work: Path, scenario: str, source: str, level: str, frames: int, keep: bool = False
) -> list[Row]:
    """Simulate one recording, init, run both methods; rows floor, joint, pairwise."""
    project = work / f"{scenario}-{source}-{level}"
    project.mkdir(parents=True)
    tagtrail(
        "simulate",
        scenario,
        "--out",
        "sim",
        "--frames",
        str(frames),
        "--query-frames",
        "2",
        "--no-progress",
        *LEVELS[(source, level)],
        cwd=project,
    )
    rec = RECORDING.get(scenario, scenario)
    tagtrail("init", "--reference", f"sim/{rec}", "--tag-size", "0.16", cwd=project)
    rows = [method_row(project, scenario, source, level, m) for m in METHODS]
    dt, dr, n = floor(
        Runner(load_pipeline(project / "pipeline.yaml", REGISTRY)),
        project / "sim" / rec / "ground_truth",
    )
    note = (
        f"median {100 * np.median(dt):.2f} cm; {100 * np.mean(n == 1):.0f}% one-tag frames, "
        f"{int((dt > 0.5).sum())} off > 50 cm"
    )
    fl = Row(
        scenario,
        source,
        level,
        "floor",
        float(dt.mean()),
        float(np.percentile(dt, 95)),
        float(dt.max()),
        float(dr.mean()),
        posed=len(dt),
        seen=rows[0].seen,
        target=note,
    )
    for r in rows:
        r.target = target(r, fl.traj_mean)
    if not keep:
        shutil.rmtree(project / "sim")  # images are ~1 MB a frame
    return [fl, *rows]


def cm(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.2f}"


def table(rows: list[Row]) -> str:
    head = (
        "| scenario | source | noise | method | traj mean / p95 / max (cm) | rot (°) | "
        "anch (cm) | tags mean / max (cm) | tags | comp | posed / seen | run (s) | target |"
    )
    lines = [head, "|" + "---|" * 13]
    for r in rows:
        posed = f"{r.posed}/{r.seen} ({100 * r.posed / max(r.seen, 1):.0f}%)"
        lines.append(
            f"| {r.scenario} | {r.source} | {r.level} | {r.method} | {cm(r.traj_mean)} / "
            f"{cm(r.traj_p95)} / {cm(r.traj_max)} | {r.rot_mean:.3f} | {cm(r.traj_anchored)} | "
            f"{cm(r.tags_mean)} / {cm(r.tags_max)} | {r.tags or '–'} | "
            f"{'–' if r.comps is None else r.comps} | {posed} | "
            f"{'–' if r.run_s is None else f'{r.run_s:.1f}'} | {r.target or '–'} |"
        )
    return "\n".join(lines)


def machine() -> str:
    cpu = next(
        (
            ln.split(":", 1)[1].strip()
            for ln in Path("/proc/cpuinfo").read_text().splitlines()
            if ln.startswith("model name")
        ),
        platform.processor(),
    )
    mem = next(
        (
            int(ln.split()[1]) / 2**20
            for ln in Path("/proc/meminfo").read_text().splitlines()
            if ln.startswith("MemTotal")
        ),
        0.0,
    )
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"],
        cwd=REPO,
        capture_output=True,
        text=True,
    ).stdout.strip()
    return (
        f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GB RAM; {platform.system()} "
        f"{platform.release()}; Python {platform.python_version()}; commit {commit}"
        f"{' (+ uncommitted changes)' if dirty else ''}; {time.strftime('%Y-%m-%d %H:%M')}; "
        f"load average {os.getloadavg()[0]:.1f} at the end (run times grow with it)"
    )


PAPER_4_2 = {  # Table 4.2: mean, min, max (m / deg)
    "trajectory": ((0.0584, 0.97), (0.0126, 0.11), (0.1485, 2.67)),
    "tags": ((0.0364, 0.73), (0.0156, 0.73), (0.0583, 0.73)),
}


def table_4_2(work: Path) -> str:
    """The paper's Table 4.2 (10 cm Gaussian noise on the observations' translations, §4.1)
    through the whole pipeline on ``tagtrail simulate observations``, both methods, beside the
    paper's figures (its scene is not ours: magnitudes compare, not digits). Anchored errors,
    as the paper reports them."""
    project = work / "table-4-2"
    project.mkdir(parents=True, exist_ok=True)
    tagtrail(
        "simulate", "observations", "--out", "sim", "--noise-t", "0.10", "--force", cwd=project
    )
    (project / "pipeline.yaml").write_text(
        "datasets:\n  reference:\n    source: sim/observations\n"
    )
    lines = [
        "| method | metric | mean (m / °) | min | max | paper mean | paper min | paper max |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for method, flags in METHODS.items():
        tagtrail("run", "--force", *flags, cwd=project)
        doc = json.loads(tagtrail("eval", "--json", *flags, cwd=project))["evaluation"]
        for block, label in (("trajectory", "camera trajectory"), ("tags", "tag poses")):
            pos, ang = doc[block]["position_m"], doc[block]["angle_deg"]
            ours = [f"{pos[k]:.4f} / {ang[k]:.2f}" for k in ("mean", "min", "max")]
            paper = [f"{m:.4f} / {d:.2f}" for m, d in PAPER_4_2[block]]
            lines.append(f"| {method} | {label} | " + " | ".join(ours + paper) + " |")
    return "\n".join(lines) + "\n"


def stretch(scenario: str) -> tuple[float, float] | None:
    """The scenario's stretch without a tag in view (s from its first frame), if it has one."""
    from tagtrail.sim import scenarios

    return getattr(scenarios, "BLANK_STRETCH_S", {}).get(scenario)


def odometry_rows(work: Path, scenario: str, quick: bool) -> list[dict[str, Any]]:
    """One recording from detections (0.3 px) with /odom at 2 % wheel-scale error, run without
    and with the odometry prior (``optimize.joint.odometry`` off / auto): frames posed of all
    frames, the trajectory's error (the ``trajectory`` stage's, after the best rigid fit of the
    posed positions to the truth), its largest in the stretch without a tag, the tags' error
    (``tagtrail eval``, gauge-free), the run time and what the odometry prior reported."""
    from tagtrail.geometry.registration import umeyama

    project = work / f"odom-{scenario}"
    project.mkdir(parents=True)
    n = natural_frames(scenario)
    frames = max(60, n // 3) if quick else n
    tagtrail(
        "simulate",
        scenario,
        "--out",
        "sim",
        "--frames",
        str(frames),
        "--query-frames",
        "2",
        "--no-progress",
        *ODOM_FLAGS,
        cwd=project,
    )
    rec = RECORDING.get(scenario, scenario)
    tagtrail("init", "--reference", f"sim/{rec}", "--tag-size", "0.16", cwd=project)
    gt_dir = project / "sim" / rec / "ground_truth"
    gt_traj = read_trajectory(gt_dir / "trajectory.csv")
    gt = dict(zip(gt_traj["t_ns"].to_numpy(np.int64), poses(gt_traj)[:, :3, 3], strict=True))
    gt_tags, _ = read_tag_map(gt_dir / "tag_map.yaml")
    rows = []
    for label, extra in (("off", ["-S", "optimize.joint.odometry=off"]), ("auto", [])):
        t0 = time.perf_counter()
        tagtrail("run", "--force", *extra, cwd=project)
        run_s = time.perf_counter() - t0
        doc = json.loads(tagtrail("eval", "--json", *extra, cwd=project))["evaluation"]
        tags = (doc["gauge_free"] or {}).get("tags") or doc["tags"]
        runner = Runner(load_pipeline(project / "pipeline.yaml", REGISTRY, extra[1::2]))
        all_frames = artifact(runner, "extract", "frames")
        traj = artifact(runner, "trajectory", "trajectory")
        report = artifact(runner, "optimize", "report")
        tag_map = artifact(runner, "optimize", "tag_map")
        t = traj["t_ns"].to_numpy(np.int64)
        ok = np.isin(t, list(gt))
        P = traj[POSE_COLS[:3]].to_numpy(np.float64)[ok]
        G = np.stack([gt[x] for x in t[ok]])
        _, R, tr = umeyama(P, G, with_scale=False)
        e = np.linalg.norm(P @ R.T + tr - G, axis=1)
        blind = stretch(scenario)
        ts = (t[ok] - int(all_frames["t_ns"].min())) * 1e-9
        inb = (ts >= blind[0]) & (ts < blind[1]) if blind else np.zeros(len(ts), bool)
        n_blind = 0
        if blind:
            fs = (all_frames["t_ns"].to_numpy(np.int64) - int(all_frames["t_ns"].min())) * 1e-9
            n_blind = int(((fs >= blind[0]) & (fs < blind[1])).sum())
        odo = (report.bundle.odometry if report.bundle is not None else None) or None
        rows.append(
            dict(
                scenario=scenario,
                odometry=label,
                posed=len(t),
                frames=len(all_frames),
                blind=f"{int(inb.sum())}/{n_blind}" if blind else "–",
                mean=float(e.mean()),
                max=float(e.max()),
                blind_max=float(e[inb].max()) if inb.any() else None,
                tags_mean=tags["position_m"]["mean"],
                tags_max=tags["position_m"]["max"],
                tags=f"{int(tag_map['tag_id'].isin(gt_tags['tag_id']).sum())}/"
                f"{gt_tags['tag_id'].nunique()}",
                run_s=run_s,
                prior=(
                    "–"
                    if odo is None
                    else (
                        f"on: {odo.offset_ms:.0f} ms, x{odo.scale:.3f}, lever {odo.lever_m:.3f} m"
                        if odo.applied
                        else f"off: {odo.why}"
                    )
                ),
            )
        )
    return rows


def odometry_table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| scenario | odometry | frames posed | blind stretch posed | traj mean / max (cm) | "
        "blind max (cm) | tags mean / max (cm) | tags | run (s) | the prior |"
    )
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        lines.append(
            f"| {r['scenario']} | {r['odometry']} | {r['posed']}/{r['frames']} "
            f"({100 * r['posed'] / max(r['frames'], 1):.1f}%) | {r['blind']} | "
            f"{cm(r['mean'])} / {cm(r['max'])} | {cm(r['blind_max'])} | "
            f"{cm(r['tags_mean'])} / {cm(r['tags_max'])} | {r['tags']} | {r['run_s']:.1f} | "
            f"{r['prior']} |"
        )
    return "\n".join(lines)


def write_odometry(out: Path, md: str, quick: bool) -> None:
    """Put the odometry table between its markers in ``out`` (after the main table, before the
    real-data part), the rest kept."""
    old = out.read_text() if out.exists() else ""
    block = (
        f"{ODOMETRY_MARKER}\n## The wheel-odometry prior (issue 27)\n\n"
        f"Machine: {machine()}. Mode: {'quick' if quick else 'full'}. Produced by "
        "`bench/bench_accuracy.py --odometry` (`odometry_rows`: detections at 0.3 px, /odom at "
        "2 % wheel-scale error; each recording run with `optimize.joint.odometry: off` and with "
        "the default `auto`). Frames posed: of all the recording's frames; trajectory: the "
        "`trajectory` stage's, after the best rigid fit of its positions to the truth; blind: "
        "the stretch with no tag in view (`tagtrail.sim.scenarios.BLANK_STRETCH_S`); tags: "
        "`tagtrail eval`, gauge-free. Targets: >= 99 % of the frames posed where odometry "
        "exists, the blind stretch within 5 cm, no existing scene worse with odometry by more "
        "than 5 %.\n\n" + md + f"\n{ODOMETRY_MARKER}\n"
    )
    if old.count(ODOMETRY_MARKER) >= 2:
        a = old.index(ODOMETRY_MARKER)
        b = old.index(ODOMETRY_MARKER, a + 1) + len(ODOMETRY_MARKER) + 1
        new = old[:a] + block + old[b:]
    elif REALDATA_MARKER in old:
        a = old.index(REALDATA_MARKER)
        new = old[:a] + block + "\n" + old[a:]
    else:
        new = old + "\n" + block
    out.write_text(new)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a third of the frames")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--sources", default="images,detections")
    ap.add_argument("--levels", default="low,high")
    ap.add_argument("--keep", type=Path, help="work in DIR and keep the projects")
    ap.add_argument(
        "--odometry",
        action="store_true",
        help="only the wheel-odometry rows (ODOM_SCENARIOS, or --scenarios), written to their "
        "part of bench/ACCURACY.md",
    )
    ap.add_argument(
        "--no-paper", dest="paper", action="store_false", help="leave out the paper's Table 4.2 run"
    )
    ap.add_argument(
        "--out",
        type=Path,
        help="markdown file (default: bench/ACCURACY.md on a full run of everything, else none)",
    )
    args = ap.parse_args()
    scenarios = args.scenarios.split(",")
    sources, levels = args.sources.split(","), args.levels.split(",")
    work = args.keep or Path(tempfile.mkdtemp(prefix="tagtrail-bench-accuracy-"))
    if args.odometry:
        chosen = ODOM_SCENARIOS if args.scenarios == ",".join(SCENARIOS) else scenarios
        t0 = time.perf_counter()
        orows: list[dict[str, Any]] = []
        try:
            for scenario in chosen:
                orows += odometry_rows(work, scenario, args.quick)
                print(f"{scenario}: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
        finally:
            if args.keep is None:
                shutil.rmtree(work, ignore_errors=True)
        md = odometry_table(orows)
        print(md)
        write_odometry(args.out or REPO / "bench" / "ACCURACY.md", md, args.quick)
        return
    rows: list[Row] = []
    t0 = time.perf_counter()
    try:
        for scenario in scenarios:
            n = natural_frames(scenario)
            frames = max(60, n // 3) if args.quick else n
            for source in sources:
                for level in levels:
                    t1 = time.perf_counter()
                    rows += combo(work, scenario, source, level, frames, args.keep is not None)
                    print(
                        f"{scenario} {source} {level}: {frames} frames, "
                        f"{time.perf_counter() - t1:.0f} s",
                        file=sys.stderr,
                        flush=True,
                    )
        paper = table_4_2(work) if args.paper else ""
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    md = table(rows)
    if paper:
        md += (
            "\n### The paper's Table 4.2 (10 cm noise on the observations, §4.1)\n\n"
            "`tagtrail simulate observations --noise-t 0.10` (observations only: the joint "
            "method falls back to the pose graph; its trajectory is the per-frame fusion, "
            "smoothed), anchored errors as the paper gives them, beside the paper's figures "
            "(a different scene: magnitudes compare).\n\n" + paper
        )
    print(md)
    full = (
        not args.quick
        and set(scenarios) == set(SCENARIOS)
        and len(sources) == 2
        and len(levels) == 2
    )
    out = args.out or (REPO / "bench" / "ACCURACY.md" if full else None)
    if out is not None:
        old = out.read_text() if out.exists() else ""
        keep = next((m for m in (ODOMETRY_MARKER, REALDATA_MARKER) if m in old), None)
        tail = old[old.index(keep) :] if keep else ""  # the odometry and real-data parts
        out.write_text(
            "# Accuracy benchmark (issue 12)\n\n"
            f"Machine: {machine()}.\n"
            f"Mode: {'quick' if args.quick else 'full'}; bench time "
            f"{time.perf_counter() - t0:.0f} s. Produced by `bench/bench_accuracy.py`; "
            "definitions and targets in its docstring.\n\n"
            "Errors: gauge-free (after the best rigid fit of the map to ground truth, "
            "`tagtrail eval --json`), smoothed trajectory; `anch`: the anchored trajectory "
            "mean; `floor`: multi-tag PnP of every frame against the true tag map from the same "
            "detections.\n\n" + md + "\n" + (f"\n{tail}" if tail else "")
        )
        print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
