"""Numbers that must not move: record every output of a fixed set of runs, compare two records.

Issue 27 rebuilds the joint solve (``optimize``'s and ``trajectory``'s) without changing what it
computes. This script runs a fixed set of cases and writes every number they produce to a JSON:

- ``demo``: ``tagtrail demo`` (the room's rendered images: a reference and three parked queries);
- ``room``, ``hall``, ``corridor``: ``tagtrail simulate SCENE --detections`` through
  ``tagtrail run`` (the demo's stages);
- ``corridor_img``: ``tagtrail simulate corridor --compressed --frames 150`` (rendered images).

Per case and dataset: every numeric column of the exported CSVs (``trajectory.csv``,
``tag_map.csv``, ...), every numeric leaf of the exported JSONs (``evaluation.json``,
``summary.json``) and of the ``optimize`` and ``trajectory`` artifacts (the optimize report, the
tag map, the unsmoothed trajectory). The recordings are simulated once into ``--work`` and kept
(the simulator is not under test); artifacts and outputs are cleared before every run.

``compare A.json B.json`` prints, per case and file, the largest difference of lengths (m and
everything not in degrees), of angles (columns/keys naming ``deg``) and, apart, of stamps and
indices (which frame a row names), and the files or columns present on one side only. The
target where the algorithm is unchanged: 1e-6 m / 1e-4 deg.

Run (each side with its own code on ``PYTHONPATH``)::

    PYTHONPATH=. .venv/bin/python bench/bench_refactor_check.py record before.json
    PYTHONPATH=. .venv/bin/python bench/bench_refactor_check.py record after.json
    .venv/bin/python bench/bench_refactor_check.py compare before.json after.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

BIN = Path(sys.executable).parent
TAGTRAIL = str(BIN / "tagtrail")
SCENES = {  # case -> simulate arguments
    "room": ["room", "--detections"],
    "hall": ["hall", "--detections"],
    "corridor": ["corridor", "--detections"],
    "corridor_img": ["corridor", "--compressed", "--frames", "150"],
}
STAMPS = ("stamp_", "t_ns", "t_rel_s", "_idx")  # columns naming a frame, compared apart
QUERY_INPUTS = {
    "trajectory.tag_map": "reference:optimize.tag_map",
    "trajectory.map_report": "reference:optimize.report",
    "align.tag_map": "reference:optimize.tag_map",
}


def sh(cmd: list[str], cwd: Path) -> None:
    res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=os.environ.copy())
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stderr[-3000:]}")


def pipeline_for(data: Path) -> str:
    """The demo's pipeline over the recordings in ``data`` (``reference`` the first, or the
    one named so; every other recording a query localized against its map)."""
    from tagtrail.commands.demo import template

    doc = yaml.safe_load(template())
    recs = sorted(p.name for p in data.iterdir() if p.is_dir())
    ref = "reference" if "reference" in recs else recs[0]
    datasets: dict[str, Any] = {"reference": {"source": str(data / ref)}}
    demo_q = doc["datasets"].get("query_1", {}).get("inputs", QUERY_INPUTS)
    for r in recs:
        if r != ref:
            datasets[r] = {"source": str(data / r), "inputs": dict(demo_q)}
    doc["reference"] = "reference"
    doc["datasets"] = datasets
    return yaml.safe_dump(doc, sort_keys=False)


def numbers(value: Any, prefix: str, out: dict[str, list[float]]) -> None:
    """Every numeric leaf of a JSON-like value, keyed by its path."""
    if isinstance(value, dict):
        for k, v in value.items():
            numbers(v, f"{prefix}.{k}" if prefix else str(k), out)
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            numbers(v, f"{prefix}[{i}]", out)
    elif isinstance(value, bool):
        out[prefix] = [float(value)]
    elif isinstance(value, int | float):
        out[prefix] = [float(value)]


def frame_numbers(df: pd.DataFrame) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {}
    for c in df.columns:
        if pd.api.types.is_bool_dtype(df[c]) or pd.api.types.is_numeric_dtype(df[c]):
            out[str(c)] = [float(v) for v in df[c].to_numpy(np.float64)]
    return out


def collect(project: Path) -> dict[str, dict[str, list[float]]]:
    """Numbers of the exported files and of the optimize/trajectory artifacts of ``project``."""
    files: dict[str, dict[str, list[float]]] = {}
    for f in sorted((project / "outputs").rglob("*")):
        rel = str(f.relative_to(project / "outputs"))
        if f.suffix == ".csv":
            try:
                files[rel] = frame_numbers(pd.read_csv(f))
            except (pd.errors.ParserError, pd.errors.EmptyDataError):
                continue
        elif f.suffix == ".json" and not f.name.startswith("."):
            nums: dict[str, list[float]] = {}
            numbers(json.loads(f.read_text()), "", nums)
            files[rel] = nums
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import load_pipeline
    from tagtrail.stages import REGISTRY

    cwd = Path.cwd()
    os.chdir(project)
    try:
        runner = Runner(load_pipeline(Path("pipeline.yaml"), REGISTRY), jobs=1)
        for s in runner.plan():
            if s.stage not in ("optimize", "trajectory") or s.status != "cached":
                continue
            for output in runner.pipe.stages[s.stage].outputs:
                val = runner.store.load(s.stage, s.key, output)
                name = f"{s.dataset}/artifact:{s.stage}.{output}"
                if isinstance(val, pd.DataFrame):
                    files[name] = frame_numbers(val)
                else:
                    dump = val.model_dump(mode="json") if hasattr(val, "model_dump") else val
                    nums = {}
                    numbers(dump, "", nums)
                    files[name] = nums
    finally:
        os.chdir(cwd)
    return files


def run_case(case: str, work: Path) -> dict[str, dict[str, list[float]]]:
    project = work / case
    for d in ("artifacts", "outputs", "sweeps"):
        shutil.rmtree(project / d, ignore_errors=True)
    if case == "demo":
        project.mkdir(parents=True, exist_ok=True)
        sh([TAGTRAIL, "demo", "--dir", str(project), "-j", "1"], cwd=work)
    else:
        data = project / "data"
        if not data.is_dir():
            sh([TAGTRAIL, "simulate", *SCENES[case], "--out", str(data), "--no-progress"], cwd=work)
        (project / "pipeline.yaml").write_text(pipeline_for(data))
        sh([TAGTRAIL, "run", "-j", "1"], cwd=project)  # exports the outputs too
    return collect(project)


def record(out: Path, work: Path, cases: list[str]) -> None:
    work.mkdir(parents=True, exist_ok=True)
    doc = json.loads(out.read_text()) if out.is_file() else {}
    for case in cases:
        print(f"{case} …", flush=True)
        doc[case] = run_case(case, work)
        out.write_text(json.dumps(doc))
    print(f"wrote {out}")


def _maxdiff(a: list[float], b: list[float]) -> float:
    if len(a) != len(b):
        return math.inf
    x, y = np.asarray(a, np.float64), np.asarray(b, np.float64)
    same_nan = np.isnan(x) & np.isnan(y)
    d = np.where(same_nan, 0.0, np.abs(x - y))
    return float(np.nanmax(np.where(np.isnan(d), np.inf, d))) if len(d) else 0.0


def compare(a_path: Path, b_path: Path, show: int) -> int:
    """Largest difference per case and file (lengths; angles), and what one side lacks."""
    a, b = json.loads(a_path.read_text()), json.loads(b_path.read_text())
    worst_m = worst_deg = 0.0
    for case in sorted(set(a) | set(b)):
        print(f"== {case}")
        if case not in a or case not in b:
            print("   only in", a_path if case in a else b_path)
            continue
        for f in sorted(set(a[case]) | set(b[case])):
            if f not in a[case] or f not in b[case]:
                print(f"   {f}: only in {a_path.name if f in a[case] else b_path.name}")
                continue
            fa, fb = a[case][f], b[case][f]
            dm = dd = ds = 0.0
            worst: list[tuple[float, str]] = []
            for col in sorted(set(fa) & set(fb)):
                d = _maxdiff(fa[col], fb[col])
                worst.append((d, col))
                if any(w in col for w in STAMPS):  # which frame: not a length
                    ds = max(ds, d)
                elif "deg" in col:
                    dd = max(dd, d)
                else:
                    dm = max(dm, d)
            only = sorted(set(fa) ^ set(fb))
            worst.sort(reverse=True)
            detail = ", ".join(f"{c} {d:.2g}" for d, c in worst[:show] if d > 0)
            print(
                f"   {f}: max |d| {dm:.3g} (m, other), {dd:.3g} deg"
                + (f", stamps/indices {ds:.3g}" if ds else "")
                + (f"  [{detail}]" if detail else "")
                + (f"  one side only: {only[:6]}" if only else "")
            )
            worst_m, worst_deg = max(worst_m, dm), max(worst_deg, dd)
    print(f"overall: {worst_m:.3g} (m, other), {worst_deg:.3g} deg")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("out", type=Path)
    r.add_argument("--work", type=Path, default=Path("/tmp/tagtrail_refactor_check"))
    r.add_argument("--cases", nargs="*", default=["demo", *SCENES])
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    c.add_argument("--show", type=int, default=3, help="largest columns shown per file")
    args = ap.parse_args()
    if args.cmd == "record":
        record(args.out, args.work.resolve(), args.cases)
        return 0
    return compare(args.a, args.b, args.show)


if __name__ == "__main__":
    sys.exit(main())
