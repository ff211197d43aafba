"""``tagtrail eval``: the paper's evaluation tables from the up-to-date artifacts of a run.

* Tables 4.1/4.2 layout (datasets with ground truth, from ``eval.evaluation``): trajectory errors
  (smoothed and raw) and tag-map errors, mean/min/max in m and degrees, n and coverage; anchored
  (world = the map's anchor tag) and gauge-free (after the best rigid fit of the map to ground
  truth), labelled.
* Table A.1 layout (``--distances CSV`` with columns ``source_tag,target_tag,measured_m``):
  tape-measured distances between tag centres against the same distances in the dataset's
  ``optimize.tag_map``; absolute (m) and relative (%) error per pair, then mean/max/min.

Nothing is computed here but distances between map positions: the numbers are the artifacts'.
Output: an aligned text table, ``--json`` for scripts, or ``--csv FILE`` (column ``table`` =
``errors`` or ``distances``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tagtrail.errors import SourceError, SpecError, one_line

TABLE_ERRORS = "errors"
TABLE_DISTANCES = "distances"
DISTANCE_COLUMNS = ("source_tag", "target_tag", "measured_m")
BLOCKS = (  # (key in the evaluation document, label); gauge-free rows get ", gauge-free"
    ("trajectory", "camera trajectory (smoothed)"),
    ("trajectory_raw", "camera trajectory (raw)"),
    ("tags", "tag poses"),
)
GAUGE_FREE_BLOCKS = (("trajectory", BLOCKS[0][1]), ("tags", BLOCKS[2][1]))
STATS = ("mean", "min", "max")
CSV_COLUMNS = (
    "table",
    "metric",
    "label",
    "n",
    "coverage",
    *(f"{s}_m" for s in STATS),
    *(f"{s}_deg" for s in STATS),
    "source_tag",
    "target_tag",
    "estimated_m",
    "measured_m",
    "abs_error_m",
    "rel_error_pct",
    "status",
)
_TAG_RE = re.compile(r"(?:tag36h11:)?(\d+)")
EXAMPLES = """examples:
  tagtrail eval
  tagtrail eval --dataset query --json
  tagtrail eval --distances tape.csv --csv eval.csv
  tagtrail eval -S optimize.f_scale=0.05     # the run made with that override

--distances CSV (tape-measured distances between tag centres, metres):
  source_tag,target_tag,measured_m
  16,2,1.380
  tag36h11:16,tag36h11:3,1.360
"""


@dataclass
class Pair:
    """One row of the distance table (``estimated_m`` None: a tag is not in the map)."""

    source_tag: int
    target_tag: int
    measured_m: float
    estimated_m: float | None = None
    missing: list[int] = field(default_factory=list)

    @property
    def abs_error_m(self) -> float | None:
        return None if self.estimated_m is None else abs(self.estimated_m - self.measured_m)

    @property
    def rel_error_pct(self) -> float | None:
        err = self.abs_error_m
        return None if err is None else 100.0 * err / self.measured_m

    @property
    def status(self) -> str:
        if not self.missing:
            return "ok"
        tags = " and ".join(f"tag {t}" for t in self.missing)
        return f"missing: {tags} not in the map"

    def as_dict(self) -> dict[str, Any]:
        return {
            "source_tag": self.source_tag,
            "target_tag": self.target_tag,
            "estimated_m": self.estimated_m,
            "measured_m": self.measured_m,
            "abs_error_m": self.abs_error_m,
            "rel_error_pct": self.rel_error_pct,
            "status": self.status,
            "missing": list(self.missing),
        }


# --- the distances CSV ------------------------------------------------------------------------


def _tag_id(f: Path, where: str, col: str, text: str) -> int:
    m = _TAG_RE.fullmatch(text.strip())
    if m is None:
        shown = repr(text.strip()) if text.strip() else "empty cell"
        raise SourceError(
            f"{f}: {where}, column {col}: {shown} is not a tag id "
            "(expected an integer or 'tag36h11:<id>')"
        )
    return int(m.group(1))


def _metres(f: Path, where: str, col: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        shown = repr(text.strip()) if text.strip() else "empty cell"
        raise SourceError(
            f"{f}: {where}, column {col}: {shown} is not a number (a distance in metres)"
        ) from None
    if not math.isfinite(v) or v <= 0:
        raise SourceError(
            f"{f}: {where}, column {col}: {text.strip()!r} is not a positive "
            "finite distance in metres"
        )
    return v


def read_distances(f: Path) -> list[Pair]:
    """The pairs of a ``source_tag,target_tag,measured_m`` CSV (other columns ignored, blank lines
    skipped). Any problem is one :class:`SourceError` naming the file, the 1-based data row (the
    header not counted; its line in the file in brackets) and the column."""
    try:
        text = Path(f).read_text(encoding="utf-8-sig")  # a spreadsheet's BOM is not a column
    except FileNotFoundError:
        raise SourceError(f"--distances {f}: no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise SourceError(f"--distances {f}: cannot read it: {one_line(err)}") from err
    reader = csv.reader(text.splitlines())
    header = next((row for row in reader if any(c.strip() for c in row)), None)
    if header is None:
        raise SourceError(
            f"{f}: empty file (expected a header line "
            f"{','.join(DISTANCE_COLUMNS)} and one row per tag pair)"
        )
    names = [c.strip() for c in header]
    missing = [c for c in DISTANCE_COLUMNS if c not in names]
    if missing:
        raise SourceError(
            f"{f}: missing column{'s' if len(missing) > 1 else ''} "
            f"{', '.join(missing)} (header needed: {','.join(DISTANCE_COLUMNS)}; "
            f"found: {','.join(names)})"
        )
    idx = {c: names.index(c) for c in DISTANCE_COLUMNS}
    pairs: list[Pair] = []
    for row in reader:
        if not any(c.strip() for c in row):
            continue
        where = f"data row {len(pairs) + 1} (line {reader.line_num})"
        cells: dict[str, str] = {}
        for col, i in idx.items():
            if i >= len(row):
                raise SourceError(
                    f"{f}: {where}, column {col}: missing cell "
                    f"(the row has {len(row)} of {len(names)} columns)"
                )
            cells[col] = row[i]
        a = _tag_id(f, where, "source_tag", cells["source_tag"])
        b = _tag_id(f, where, "target_tag", cells["target_tag"])
        if a == b:
            raise SourceError(f"{f}: {where}, column target_tag: tag {b} is also the source tag")
        pairs.append(Pair(a, b, _metres(f, where, "measured_m", cells["measured_m"])))
    if not pairs:
        raise SourceError(f"{f}: no tag pairs (only the header line)")
    return pairs


def match_distances(pairs: list[Pair], tag_map: pd.DataFrame) -> list[Pair]:
    """Fill each pair's estimated distance between the tag centres of ``tag_map``
    (``tag_id, x_m, y_m, z_m``); a tag not in the map leaves it None (listed as missing)."""
    ids = tag_map["tag_id"].to_numpy(np.int64)
    xyz = tag_map[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
    pos = {int(t): p for t, p in zip(ids, xyz, strict=True)}
    for p in pairs:
        p.missing = [t for t in dict.fromkeys((p.source_tag, p.target_tag)) if t not in pos]
        p.estimated_m = (
            None if p.missing else float(np.linalg.norm(pos[p.source_tag] - pos[p.target_tag]))
        )
    return pairs


def distance_summary(pairs: list[Pair]) -> dict[str, Any]:
    """Mean/max/min of the absolute (m) and relative (%) errors over the pairs with an estimate."""
    ok = [p for p in pairs if p.estimated_m is not None]
    out: dict[str, Any] = {"n": len(ok), "n_missing": len(pairs) - len(ok)}
    for key, values in (
        ("abs_error_m", [p.abs_error_m for p in ok]),
        ("rel_error_pct", [p.rel_error_pct for p in ok]),
    ):
        v = np.array(values, dtype=np.float64)
        out[key] = (
            {"mean": None, "max": None, "min": None}
            if v.size == 0
            else {"mean": float(v.mean()), "max": float(v.max()), "min": float(v.min())}
        )
    return out


# --- the evaluation rows ----------------------------------------------------------------------


def _as_dict(evaluation: Any) -> dict[str, Any]:
    """An ``Evaluation`` document (or its JSON form, e.g. a run's ``evaluation.json``) as a dict."""
    if hasattr(evaluation, "model_dump"):
        return dict(evaluation.model_dump(mode="json"))
    return dict(evaluation)


def error_rows(evaluation: Any) -> list[dict[str, Any]]:
    """The Table 4.1/4.2 rows of an ``eval.evaluation`` document (gauge-free rows after)."""
    doc = _as_dict(evaluation)

    def row(metric: str, label: str, block: dict[str, Any]) -> dict[str, Any]:
        out = {"metric": metric, "label": label, "n": block["n"], "coverage": block["coverage"]}
        out.update({f"{s}_m": block["position_m"][s] for s in STATS})
        out.update({f"{s}_deg": block["angle_deg"][s] for s in STATS})
        return out

    rows = [row(key, label, doc[key]) for key, label in BLOCKS]
    gf = doc.get("gauge_free")
    if gf is not None:
        rows += [
            row(f"gauge_free.{key}", f"{label}, gauge-free", gf[key])
            for key, label in GAUGE_FREE_BLOCKS
        ]
    return rows


# --- formatting -------------------------------------------------------------------------------


def _num(v: float | None, digits: int, unit: str = "") -> str:
    return "-" if v is None else f"{v:.{digits}f}{unit}"


def aligned(
    header: Sequence[str], rows: Sequence[Sequence[str]], text: Sequence[int] = (0,)
) -> list[str]:
    """Columns padded to their widest cell: the ``text`` columns left-aligned, the others
    (numbers) right-aligned."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    return [
        "  ".join(
            c.ljust(w) if i in text else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        ).rstrip()
        for r in [header, *rows]
    ]


def errors_text(evaluation: Any, dataset: str) -> list[str]:
    doc = _as_dict(evaluation)
    lines = [
        f"Errors against ground truth [{dataset}] (layout of paper Tables 4.1/4.2)",
        f"world: anchor tag {doc['anchor_id']} (ground truth's anchor: tag {doc['gt_anchor_id']})",
        "",
    ]

    def cell(r: dict[str, Any], s: str) -> str:
        return f"{_num(r[f'{s}_m'], 4, ' m')} / {_num(r[f'{s}_deg'], 2, '°')}"

    body = [
        [r["label"], str(r["n"]), f"{100 * r['coverage']:.1f}%", *(cell(r, s) for s in STATS)]
        for r in error_rows(doc)
    ]
    lines += aligned(["metric", "n", "coverage", "mean error", "minimum", "maximum"], body)
    gf = doc.get("gauge_free")
    if gf is None:
        lines.append(
            "gauge-free: n/a (fewer than 3 tags in common with ground truth, or all on a line)"
        )
    else:
        lines.append(
            f"gauge-free: after the best rigid fit of the map to ground truth "
            f"(rotation {gf['rotation_deg']:.2f}°, translation "
            f"{gf['translation_m']:.4f} m), applied to map and trajectory alike"
        )
    return lines


def distances_text(
    pairs: list[Pair], summary: dict[str, Any], dataset: str, source: Path
) -> list[str]:
    lines = [
        f"Tag distances [{dataset}]: optimize.tag_map vs {source} (layout of paper Table A.1)",
        "",
    ]
    body = [
        [
            str(p.source_tag),
            str(p.target_tag),
            _num(p.estimated_m, 3),
            _num(p.measured_m, 3),
            _num(p.abs_error_m, 3),
            _num(p.rel_error_pct, 1),
            "" if p.status == "ok" else p.status,
        ]
        for p in pairs
    ]
    for stat in ("mean", "max", "min"):
        body.append(
            [
                stat.capitalize(),
                "-",
                "-",
                "-",
                _num(summary["abs_error_m"][stat], 3),
                _num(summary["rel_error_pct"][stat], 1),
                "",
            ]
        )
    header = [
        "source tag",
        "target tag",
        "estimated [m]",
        "measured [m]",
        "abs error [m]",
        "rel error [%]",
        "",
    ]
    lines += aligned(header, body, text=(0, len(header) - 1))
    note = f"{summary['n']} pair{'s' if summary['n'] != 1 else ''} compared"
    if summary["n_missing"]:
        note += f", {summary['n_missing']} with a tag missing from the map"
    lines.append(note)
    return lines


def csv_rows(
    rows: list[dict[str, Any]], pairs: list[Pair] | None, summary: dict[str, Any] | None
) -> pd.DataFrame:
    """Both tables in one frame of :data:`CSV_COLUMNS`; ``table`` says which a row is of. The
    distance table's statistics are rows with ``metric`` = mean/max/min (abs and rel error)."""
    out: list[dict[str, Any]] = [{"table": TABLE_ERRORS, **r} for r in rows]
    if pairs is not None and summary is not None:
        for p in pairs:
            d = p.as_dict()
            d.pop("missing")
            out.append({"table": TABLE_DISTANCES, "metric": "pair", **d})
        for stat in ("mean", "max", "min"):
            out.append(
                {
                    "table": TABLE_DISTANCES,
                    "metric": stat,
                    "abs_error_m": summary["abs_error_m"][stat],
                    "rel_error_pct": summary["rel_error_pct"][stat],
                }
            )
    df = pd.DataFrame(out, columns=list(CSV_COLUMNS))
    for col in ("n", "source_tag", "target_tag"):
        df[col] = df[col].astype("Int64")
    return df


# --- the command ------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``eval`` arguments to ``parser`` (returned)."""
    parser.epilog = EXAMPLES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("-p", "--pipeline", default="pipeline.yaml", help="pipeline file")
    parser.add_argument("--dataset", default=None, help="dataset (default: the reference)")
    parser.add_argument(
        "-S",
        "--set",
        action="append",
        metavar="STAGE.PARAM=VALUE",
        help="the parameter overrides the run was made with (repeatable)",
    )
    parser.add_argument(
        "--distances",
        type=Path,
        default=None,
        metavar="CSV",
        help="tape-measured tag-centre distances: source_tag,target_tag,measured_m (Table A.1)",
    )
    out = parser.add_mutually_exclusive_group()
    out.add_argument(
        "--csv",
        type=Path,
        default=None,
        metavar="FILE",
        help="also write the table(s) to FILE (column `table`: errors, distances)",
    )
    out.add_argument("--json", action="store_true", help="print JSON instead of text")
    return parser


def build_parser() -> argparse.ArgumentParser:
    return add_arguments(
        argparse.ArgumentParser(
            prog="tagtrail eval",
            description="The paper's evaluation tables from the up-to-date artifacts of a run.",
        )
    )


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """Run from parsed arguments (or an argv list); 0 on success, the error's exit code else."""
    from tagtrail.cli import run_command

    ns = args if isinstance(args, argparse.Namespace) else build_parser().parse_args(args)
    return run_command(lambda: _main(ns))


def _run_hint(ns: argparse.Namespace, stage: str) -> str:
    words = ["tagtrail", "run", stage]
    if str(ns.pipeline) != "pipeline.yaml":
        words += ["-p", str(ns.pipeline)]
    for s in ns.set or ():
        words += ["-S", s]
    return " ".join(words)


def _artifact(runner: Any, ns: argparse.Namespace, stage: str, dataset: str, output: str) -> Any:
    """The up-to-date artifact ``stage.output`` of ``dataset``; else a one-line SpecError."""
    from tagtrail.runner.dag import Node

    why = runner.graph.skipped.get(Node(stage, dataset))
    if why is not None:
        raise SpecError(f"{stage} [{dataset}] does not run: {why}")
    key = runner.key_of(stage, dataset)
    if key is None:
        raise SpecError(
            f"{stage} [{dataset}] is not up to date: run `{_run_hint(ns, stage)}` first"
        )
    return runner.store.load(stage, key, output)


def _main(ns: argparse.Namespace) -> int:
    from tagtrail.io.layouts import atomic_write_text
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import did_you_mean, load_pipeline
    from tagtrail.stages import REGISTRY

    if ns.csv is not None and ns.csv.is_dir():
        raise SpecError(f"--csv {ns.csv}: is a folder; name the CSV file to write")
    pairs = read_distances(ns.distances) if ns.distances is not None else None
    pipe = load_pipeline(Path(ns.pipeline), REGISTRY, ns.set or ())
    dataset = ns.dataset if ns.dataset is not None else pipe.reference
    if dataset not in pipe.datasets:
        raise SpecError(f"unknown dataset {dataset!r}{did_you_mean(dataset, pipe.datasets)}")
    has_gt = pipe.datasets[dataset].ground_truth is not None
    if not has_gt and pairs is None:
        raise SpecError(
            f"dataset {dataset} has no ground truth (no ground_truth folder): "
            "give --distances CSV for the tag-distance table"
        )
    runner = Runner(pipe)
    evaluation = _artifact(runner, ns, "eval", dataset, "evaluation") if has_gt else None
    rows = error_rows(evaluation) if evaluation is not None else []
    summary = None
    if pairs is not None:
        pairs = match_distances(pairs, _artifact(runner, ns, "optimize", dataset, "tag_map"))
        summary = distance_summary(pairs)

    if ns.json:
        doc = {
            "dataset": dataset,
            "errors": rows if evaluation is not None else None,
            "evaluation": _as_dict(evaluation) if evaluation is not None else None,
            "distances": None
            if pairs is None
            else {
                "file": str(ns.distances),
                "pairs": [p.as_dict() for p in pairs],
                **(summary or {}),
            },
        }
        print(json.dumps(doc, indent=2))
        return 0
    blocks = []
    if evaluation is not None:
        blocks.append(errors_text(evaluation, dataset))
    if pairs is not None and summary is not None:
        blocks.append(distances_text(pairs, summary, dataset, ns.distances))
    print("\n\n".join("\n".join(b) for b in blocks))
    if ns.csv is not None:
        df = csv_rows(rows, pairs, summary)
        atomic_write_text(ns.csv, df.to_csv(index=False))
        print(f"\nwrote {ns.csv} ({len(df)} rows)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
