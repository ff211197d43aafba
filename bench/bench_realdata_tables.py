"""Benchmark (issue 12): the paper's Table A.1 layout on real photos (../shared/realdata), for
both methods (``-S optimize.method=joint|pairwise``), through ``tagtrail eval --distances``.

With the defaults the joint solve needs ``joint_min_frames`` (30) frames showing two mapped tags,
and keeps the pose graph below that -- which photo sets of 15-40 shots often are: the solve
applied is printed per map, and a third column ``joint*`` forces it
(``-S optimize.joint_min_frames=1``).

- ``photonvision_frc2024_field``: 15 field photos (1280x720), tags 0.1651 m; the "measured"
  distances are the official field layout's (``2024-crescendo.json``, exact). The photos do not
  connect every tag: each connected component of the tag graph is mapped in turn (the first with
  the anchor ``tagtrail init`` leaves to the run, the others with ``-S edges.anchor_id``, as
  tests/test_realdata_maps.py does) and every pair of tags within a component is compared.
- ``swatbotics_mapping_feb_2014``: 72 hand-held photos (816x612) of 20 wall tags (0.127 m). It
  has no tape-measured distances and no layout file: only per-image visible ids
  (``groundtruth.txt``), a checkerboard calibration and a closed loop walked twice. What can be
  compared is consistency: lap 1 (IMG_1368-1406) and lap 2 (IMG_1407-1431) are mapped
  separately; the table gives lap 1's distances from tag 0 to every other tag against lap 2's
  (as "measured"), per method, and a summary over all 190 pairs. The whole set's map is
  reported too (tags mapped, graph components).

Each map comes from the pipeline ``tagtrail init --reference <images> --tag-size S`` writes.
Run: ``.venv/bin/python bench/bench_realdata_tables.py [--keep DIR]``. Prints markdown and puts
it in bench/ACCURACY.md after the line ``<!-- realdata -->`` (replacing what follows it).
"""

from __future__ import annotations

import argparse
import itertools
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.stages import REGISTRY

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata"
BIN = Path(sys.executable).parent
METHODS = {  # column label -> -S overrides; "joint*": the joint solve even on few frames
    "joint": ["optimize.method=joint"],
    "pairwise": ["optimize.method=pairwise"],
    "joint*": ["optimize.method=joint", "optimize.joint_min_frames=1"],
}
MARKER = "<!-- realdata -->"


def tagtrail(*args: str, cwd: Path) -> str:
    """Run the ``tagtrail`` command of this venv in ``cwd``; its stdout (raises on failure)."""
    res = subprocess.run([str(BIN / "tagtrail"), *args], cwd=cwd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"tagtrail {' '.join(args)} failed ({res.returncode}):\n{res.stderr}")
    return res.stdout


def init(project: Path, images: Path, tag_size: float) -> Path:
    project.mkdir(parents=True)
    tagtrail("init", "--reference", str(images), "--tag-size", str(tag_size), cwd=project)
    return project


def overrides(method: str, anchor: int | None = None) -> list[str]:
    return METHODS[method] + ([f"edges.anchor_id={anchor}"] if anchor is not None else [])


def sets(method: str, anchor: int | None = None) -> list[str]:
    return [a for o in overrides(method, anchor) for a in ("-S", o)]


def run_map(project: Path, method: str, anchor: int | None = None) -> tuple[Any, Any, str]:
    """(tag_map, graph, the method optimize applied) of the run with ``method`` (and
    ``anchor``): the joint solve keeps the pose graph below ``joint_min_frames``."""
    tagtrail("run", "optimize", *sets(method, anchor), cwd=project)
    runner = Runner(load_pipeline(project / "pipeline.yaml", REGISTRY, overrides(method, anchor)))
    out = []
    for stage, name in (("optimize", "tag_map"), ("edges", "graph"), ("optimize", "report")):
        key = runner.key_of(stage, "reference")
        assert key is not None
        out.append(runner.store.load(stage, key, name))
    return out[0], out[1], str(out[2]["method"])


def eval_distances(
    project: Path, csv: Path, method: str, anchor: int | None = None
) -> dict[str, Any]:
    """``tagtrail eval --json --distances csv``'s distances block for the run with ``method``."""
    doc = json.loads(
        tagtrail("eval", "--json", "--distances", str(csv), *sets(method, anchor), cwd=project)
    )
    dist: dict[str, Any] = doc["distances"]
    return dist


def write_csv(path: Path, rows: list[tuple[int, int, float]]) -> Path:
    path.write_text(
        "source_tag,target_tag,measured_m\n" + "".join(f"{a},{b},{m!r}\n" for a, b, m in rows)
    )
    return path


def num(v: float | None, digits: int = 3) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def table_a1(
    pairs: dict[str, dict[tuple[int, int], dict[str, Any]]], label: str, shared: bool = True
) -> list[str]:
    """Table A.1 side by side for both methods: one row per pair, then mean/max/min. ``shared``:
    one "measured" column (else each method has its own, from its own reference map)."""

    def group(m: str) -> list[str]:
        return ([] if shared else [f"{m} {label} (m)"]) + [
            f"{m} est (m)",
            f"{m} abs err (m)",
            f"{m} rel err (%)",
        ]

    cols = [
        "source",
        "target",
        *([f"{label} (m)"] if shared else []),
        *(c for m in METHODS for c in group(m)),
    ]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    keys = sorted(set().union(*(pairs[m] for m in METHODS)))
    for key in keys:
        cells = [str(key[0]), str(key[1])]
        if shared:
            cells.append(num(next(pairs[m][key]["measured_m"] for m in METHODS if key in pairs[m])))
        for m in METHODS:
            p = pairs[m].get(key)
            if not shared:
                cells.append("–" if p is None else num(p["measured_m"]))
            if p is None or p["estimated_m"] is None:
                cells += ["not connected", "–", "–"]
            else:
                cells += [num(p["estimated_m"]), num(p["abs_error_m"]), num(p["rel_error_pct"], 1)]
        lines.append("| " + " | ".join(cells) + " |")
    for stat in ("mean", "max", "min"):
        f = {"mean": np.mean, "max": np.max, "min": np.min}[stat]
        cells = [stat.capitalize(), "–", *(["–"] if shared else [])]
        for m in METHODS:
            ok = [p for p in pairs[m].values() if p["estimated_m"] is not None]
            a = np.array([p["abs_error_m"] for p in ok])
            r = np.array([p["rel_error_pct"] for p in ok])
            cells += [
                *([] if shared else ["–"]),
                "–",
                num(float(f(a))) if len(a) else "–",
                num(float(f(r)), 1) if len(r) else "–",
            ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def photonvision(work: Path) -> list[str]:
    root = REALDATA / "photonvision_frc2024_field"
    doc = json.loads((root / "2024-crescendo.json").read_text())
    layout = {
        int(t["ID"]): np.array([t["pose"]["translation"][k] for k in "xyz"]) for t in doc["tags"]
    }
    project = init(work / "photonvision", root / "images", 0.1651)
    pairs: dict[str, dict[tuple[int, int], dict[str, Any]]] = {m: {} for m in METHODS}
    comps: dict[str, list[list[int]]] = {m: [] for m in METHODS}
    applied_by: dict[str, str] = {}
    for method in METHODS:
        tags, graph, applied = run_map(project, method)
        ran = {applied}
        pending = [int(d["tag_id"]) for d in graph["dropped"]]
        anchor: int | None = None
        while True:
            ids = sorted(int(t) for t in tags["tag_id"] if int(t) in layout)
            comps[method].append(ids)
            rows = [
                (a, b, float(np.linalg.norm(layout[a] - layout[b])))
                for a, b in itertools.combinations(ids, 2)
            ]
            if rows:
                csv = write_csv(work / f"pv-{method}-{ids[0]}.csv", rows)
                for p in eval_distances(project, csv, method, anchor)["pairs"]:
                    pairs[method][(p["source_tag"], p["target_tag"])] = p
            pending = [t for t in pending if t not in ids and t != anchor]
            if not pending:
                break
            anchor = pending[0]
            tags, _, applied = run_map(project, method, anchor)
            ran.add(applied)
        applied_by[method] = "/".join(sorted(ran))
    out = [
        "### PhotonVision FRC 2024 field (Table A.1 layout; measured = official layout)",
        "",
        "Maps made (one per run, each a set of tags): "
        + "; ".join(
            f"{m}: " + ", ".join("{" + ",".join(map(str, c)) + "}" for c in comps[m])
            for m in METHODS
        )
        + ". Solve applied: "
        + "; ".join(f"{m}: {a}" for m, a in applied_by.items())
        + " (joint*: `-S optimize.joint_min_frames=1`).",
        "",
    ]
    return out + table_a1(pairs, "layout")


def lap_folder(work: Path, name: str, lo: int, hi: int) -> Path:
    src = REALDATA / "swatbotics_mapping_feb_2014" / "images"
    folder = work / name
    folder.mkdir()
    for f in sorted(src.glob("IMG_*.JPG")):
        if lo <= int(f.stem.split("_")[1]) <= hi:
            (folder / f.name).symlink_to(f)
    shutil.copy(src / "camera.yaml", folder / "camera.yaml")
    return folder


def swatbotics(work: Path) -> list[str]:
    size = 0.127
    whole = init(work / "sw-all", REALDATA / "swatbotics_mapping_feb_2014" / "images", size)
    lap1 = init(work / "sw-lap1", lap_folder(work, "lap1", 1368, 1406), size)
    lap2 = init(work / "sw-lap2", lap_folder(work, "lap2", 1407, 1431), size)
    notes: list[str] = []
    pairs: dict[str, dict[tuple[int, int], dict[str, Any]]] = {}
    summary: dict[str, dict[str, Any]] = {}
    for method in METHODS:
        tags, graph, a0 = run_map(whole, method)
        t1, _, a1 = run_map(lap1, method)
        t2, _, a2 = run_map(lap2, method)
        notes.append(
            f"{method}: whole set {len(tags)}/20 tags, {graph['n_components']} "
            f"component(s) ({a0}); lap 1 {len(t1)} tags ({a1}), lap 2 {len(t2)} "
            f"tags ({a2})"
        )
        pos2 = {
            int(t): p
            for t, p in zip(t2["tag_id"], t2[["x_m", "y_m", "z_m"]].to_numpy(), strict=True)
        }
        ids = sorted(pos2)
        every = [
            (a, b, float(np.linalg.norm(pos2[a] - pos2[b])))
            for a, b in itertools.combinations(ids, 2)
        ]
        from0 = [r for r in every if r[0] == 0]
        d = eval_distances(lap1, write_csv(work / f"sw-{method}-0.csv", from0), method)
        pairs[method] = {(p["source_tag"], p["target_tag"]): p for p in d["pairs"]}
        summary[method] = eval_distances(
            lap1, write_csv(work / f"sw-{method}-all.csv", every), method
        )
    out = [
        '### swatbotics mapping (Table A.1 layout; "measured" = each method\'s lap-2 map, '
        "estimated = its lap-1 map)",
        "",
        "No tape-measured distances and no layout in this set (per-image visible ids, a "
        "checkerboard calibration, a loop walked twice): the two laps are mapped "
        "independently and compared. Tags mapped and the solve applied: " + "; ".join(notes) + ".",
        "",
    ]
    out += table_a1(pairs, "lap 2", shared=False)
    out += [
        "",
        "All pairs (lap 1 vs lap 2): "
        + "; ".join(
            f"{m}: {s['n']} pairs, abs mean {num(s['abs_error_m']['mean'])} m / max "
            f"{num(s['abs_error_m']['max'])} m, rel mean {num(s['rel_error_pct']['mean'], 1)} % / "
            f"max {num(s['rel_error_pct']['max'], 1)} %"
            for m, s in summary.items()
        ),
    ]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, help="work in DIR and keep the projects")
    ap.add_argument(
        "--out",
        type=Path,
        default=REPO / "bench" / "ACCURACY.md",
        help="markdown file whose part after '<!-- realdata -->' is replaced",
    )
    args = ap.parse_args()
    if not REALDATA.is_dir():
        print(f"{REALDATA} not found: nothing to do")
        return
    work = args.keep or Path(tempfile.mkdtemp(prefix="tagtrail-bench-realdata-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        lines = [
            "## Real photos (bench/bench_realdata_tables.py)",
            "",
            *photonvision(work),
            "",
            *swatbotics(work),
        ]
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    md = "\n".join(lines)
    print(md)
    if args.out is not None:
        text = args.out.read_text() if args.out.exists() else ""
        head = text.split(MARKER)[0].rstrip("\n")
        args.out.write_text((head + "\n\n" if head else "") + MARKER + "\n\n" + md + "\n")
        print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
