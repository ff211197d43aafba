"""Parameter sweeps on the artifact cache: a grid (or a list) of ``-S`` override sets, each point
brought up to date by a :class:`~tagtrail.runner.execute.Runner` — so only what a point changes
reruns (a sweep of ``optimize.*`` never reruns extract) and a finished point is free the next
time — and its metrics read back from the point's artifacts.

Value lists. ``-S stage.param=v1,v2,v3`` splits at the commas outside brackets (``[]``, ``{}``)
and quotes; each piece is one YAML value, read as ``run -S`` reads it. So
``-S pnp.tag_sizes={1: 0.1, 2: 0.2}`` is ONE value, ``-S pnp.tag_sizes={1: 0.1},{1: 0.2}`` two,
``-S extract.x=[1,2],[3,4]`` two lists and ``-S a.b="x,y"`` one string. A ``-S`` with one value
is a grid dimension of length one: it applies to every point. ``--points FILE`` gives an explicit
list (a CSV whose header names the parameters, or a YAML/JSON list of mappings); its rows are
crossed with the ``-S`` grid.

Metrics are what the stages declare (``METRICS`` of a stage module, a
:class:`~tagtrail.schemas.stage.Metric` each: where the number sits in one of its JSON outputs,
its unit, which way is better, its default datasets; the runner knows no stage): today errors
against ground truth from ``eval`` (``trajectory.rmse_m``, ``tags.max_deg``, …), the
relocalization statistics of ``report`` (``D.mean_m``, ``abs_phi.p95_deg``, ``alignment.rms_m``)
and the map's residuals from ``optimize`` (``map.rms_t_m``, ``map.rms_px``, …). A metric is a
column per dataset, ``NAME[DATASET]``: by default its declared datasets (the reference, or every
dataset its stage runs on), or the ``--dataset`` ones.

Files in ``sweeps/<name>/``, next to the pipeline file:
``sweep.json`` (the definition: every point's overrides, the columns; written first),
``sweep.csv`` (one row per finished point, the whole file rewritten atomically as each point
finishes, so a killed sweep leaves a valid CSV), ``runs.json`` (this invocation's run log: each
point's node states) and ``times.json`` (the seconds each artifact took to compute, by
``stage/key``, so a point served from the cache, also by another sweep, still reports its
stages' runtimes).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import itertools
import json
import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

from tagtrail import faults
from tagtrail.errors import DataError, SourceError, SpecError, StageError, one_line
from tagtrail.io.layouts import atomic_write_text
from tagtrail.runner.cache import SourceHasher, Store, pretty_json
from tagtrail.runner.dag import Graph, Node, build_graph, select
from tagtrail.runner.execute import NodeState, Runner
from tagtrail.runner.executors import KINDS, dask_session
from tagtrail.runner.paths import check_project, clear_obstacles, inside
from tagtrail.runner.spec import Pipeline, did_you_mean, load_pipeline, load_yaml, parse_override
from tagtrail.runner.stage import StageSpec
from tagtrail.schemas import documents
from tagtrail.schemas.stage import Metric

SWEEPS = "sweeps"
DEFINITION, TABLE, RUN_LOG, TIMES = "sweep.json", "sweep.csv", "runs.json", "times.json"
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")

# --- metrics ---------------------------------------------------------------------------------

# A metric's noise: two points whose values differ by no more than this (relative to the larger)
# are the same result. Metrics come out of iterative least-squares solves (tolerances ~1e-8) and
# float sums whose order changes with the data's order: runs that change nothing of substance
# differ by ~1e-7 relative (issue 30: three optimize.f_scale values all 0.1416, one marked best on
# a 1e-7 difference). 1e-6 is above that and far below any change worth a row in a table (a
# micrometre in a metre).
NOISE_REL = 1e-6
NOISE_ABS = 1e-12  # values at zero (a perfect fit): below this, equal


def within_noise(a: float, b: float) -> bool:
    """Whether two values of one metric are the same result (:data:`NOISE_REL`)."""
    return abs(a - b) <= max(NOISE_REL * max(abs(a), abs(b)), NOISE_ABS)


@dataclass(frozen=True)
class Column:
    """One metric column of the table: a metric (declared by ``stage``) read from one dataset."""

    metric: str
    dataset: str
    stage: str = field(default="", compare=False)
    spec: Metric | None = field(default=None, compare=False, repr=False)

    @property
    def name(self) -> str:
        return f"{self.metric}[{self.dataset}]"


def declared_metrics(pipe: Pipeline) -> dict[str, tuple[str, Metric]]:
    """Every metric the pipeline's stages declare (``METRICS``): name → (stage, declaration),
    in the order of :func:`metric_help` (names are unique: checked when the pipeline loads)."""
    return {m.name: (name, m) for name, spec in _by_default(pipe) for m in spec.metrics}


def _by_default(pipe: Pipeline) -> list[tuple[str, StageSpec]]:
    """The stages that declare metrics, those with the first default columns first."""
    have = [(name, spec) for name, spec in pipe.stages.items() if spec.metrics]
    return sorted(
        have, key=lambda t: min((m.default for m in t[1].metrics if m.default), default=math.inf)
    )


def metric_help(pipe: Pipeline) -> str:
    """The metrics in one line, from each stage's ``METRICS_HELP``."""
    return ", ".join(spec.metrics_help for _, spec in _by_default(pipe))


def default_metrics(pipe: Pipeline) -> list[str]:
    """The columns of a sweep without ``--metric``: the declared defaults, in their order."""
    found = [m for _, m in declared_metrics(pipe).values() if m.default]
    return [m.name for m in sorted(found, key=lambda m: m.default)]


def resolve_columns(
    pipe: Pipeline, graph: Graph, metrics: Sequence[str], datasets: Sequence[str]
) -> list[Column]:
    """The metric columns of a sweep. ``metrics`` empty: the defaults that exist here;
    ``datasets`` empty: each metric's default datasets. A bad name or a metric no chosen dataset
    has is one :class:`SpecError`."""
    known = declared_metrics(pipe)
    for name in metrics:
        if name not in known:
            raise SpecError(
                f"unknown metric {name!r}{did_you_mean(name, known)} (metrics: {metric_help(pipe)})"
            )
    if len(set(metrics)) != len(metrics):
        twice = next(m for m in metrics if list(metrics).count(m) > 1)
        raise SpecError(f"--metric {twice} given twice")
    columns: list[Column] = []
    for name in metrics or default_metrics(pipe):
        stage, m = known[name]
        live = [d for d in pipe.datasets if Node(stage, d) in graph.inputs]
        if datasets:
            wanted = list(datasets)
        elif m.datasets == "reference":
            wanted = [pipe.reference]
        else:
            wanted = list(pipe.datasets)
        chosen = [d for d in wanted if d in live]
        if not chosen and metrics:
            node = Node(stage, wanted[0])
            why = graph.skipped.get(node, "not in the pipeline")
            raise SpecError(
                f"metric {name}: no dataset of the sweep has it ({node} does not run: {why})"
            )
        columns += [Column(name, d, stage, m) for d in chosen]
    return columns


def metric_value(doc: Mapping[str, Any], path: Sequence[str]) -> float | None:
    """The number at ``path`` in a JSON document; None when a block is absent (no gauge-free
    fit, no joint solve) or the value is missing or not finite."""
    value: Any = doc
    for key in path:
        if not isinstance(value, Mapping) or value.get(key) is None:
            return None
        value = value[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


# --- points -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Point:
    """One set of overrides: parameter → its YAML text (as ``-S`` takes it), 1-based index."""

    index: int
    values: dict[str, str]

    @property
    def overrides(self) -> list[str]:
        return [f"{k}={v}" for k, v in self.values.items()]

    @property
    def label(self) -> str:
        return " ".join(self.overrides)


def split_values(text: str) -> list[str]:
    """``v1,v2,…`` → the values: split at the commas outside ``[]``/``{}`` and quotes (a quote
    opens a string only where a YAML scalar starts), each piece stripped."""
    parts: list[str] = []
    cur: list[str] = []
    depth = 0
    quote: str | None = None
    i = 0
    while i < len(text):
        c = text[i]
        if quote is not None:
            if c == "\\" and quote == '"' and i + 1 < len(text):
                cur.append(text[i : i + 2])
                i += 2
                continue
            if c == quote:
                quote = None
        elif c in "'\"" and (not "".join(cur).strip() or "".join(cur).rstrip()[-1] in "[{,:"):
            quote = c
        elif c in "[{":
            depth += 1
        elif c in "]}":
            depth = max(0, depth - 1)
        elif c == "," and depth == 0:
            parts.append("".join(cur).strip())
            cur = []
            i += 1
            continue
        cur.append(c)
        i += 1
    parts.append("".join(cur).strip())
    return parts


def _param(text: str, where: str) -> str:
    """A parameter path ``stage.param[.key]``, checked as ``run -S`` checks it."""
    param = text.strip()
    try:
        parse_override(f"{param}=0")
    except SpecError:
        raise SpecError(f"{where}: bad parameter {param!r} (expected stage.param)") from None
    return param


def parse_dimension(text: str) -> tuple[str, list[str]]:
    """``-S stage.param=v1,v2,…`` → (parameter, the values' YAML texts)."""
    if "=" not in text:
        raise SpecError(f"bad -S {text!r}: expected stage.param=v1,v2,…")
    lhs, rhs = text.split("=", 1)
    param = _param(lhs, f"-S {text!r}")
    if not rhs.strip():
        raise SpecError(f"-S {text!r}: no values (expected {param}=v1,v2,…)")
    values = split_values(rhs)
    if not all(values):
        raise SpecError(
            f"-S {text!r}: an empty value in the list (values are separated by "
            "commas; quote a value that contains one)"
        )
    parsed = [parse_override(f"{param}={v}")[2] for v in values]
    for i, v in enumerate(parsed):
        if v in parsed[:i]:
            raise SpecError(f"-S {text!r}: value {values[i]!r} given twice")
    return param, values


def yaml_text(value: Any) -> str:
    """A value as one line of YAML that ``-S`` reads back as the same value (JSON, itself
    YAML, where PyYAML's YAML 1.1 would not: the string ``"1e-3"``)."""
    text = yaml.safe_dump(value, default_flow_style=True, width=math.inf, sort_keys=False)
    text = text.strip().removesuffix("...").strip()
    if parse_override(f"x.y={text}")[2] != value:
        text = json.dumps(value)
    return text


def read_points(path: Path) -> list[dict[str, str]]:
    """The rows of a ``--points`` file: CSV (header = parameters, cells = YAML values, an empty
    cell = no override) or a YAML/JSON list of mappings ``{stage.param: value}``."""
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise SpecError(f"--points {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise SpecError(f"--points {path}: cannot read it: {one_line(err)}") from err
    rows: list[dict[str, str]] = []
    if Path(path).suffix.lower() == ".csv":
        reader = csv.reader(text.splitlines())
        header = next(reader, None)
        if header is None or not any(h.strip() for h in header):
            raise SpecError(
                f"--points {path}: empty file (expected a header of stage.param "
                "names and one row per point)"
            )
        params = [_param(h, f"--points {path}, header") for h in header]
        for row in reader:
            if not any(c.strip() for c in row):
                continue
            if len(row) > len(params):
                raise SpecError(
                    f"--points {path}, line {reader.line_num}: {len(row)} cells "
                    f"for {len(params)} columns"
                )
            rows.append({p: c.strip() for p, c in zip(params, row, strict=False) if c.strip()})
    else:
        doc = load_yaml(text, f"--points {path}")
        if not isinstance(doc, list) or not all(isinstance(r, dict) for r in doc):
            raise SpecError(
                f"--points {path}: expected a list of mappings "
                "(- {stage.param: value, …}) or a CSV file"
            )
        for r in doc:
            rows.append({_param(str(k), f"--points {path}"): yaml_text(v) for k, v in r.items()})
    if not rows:
        raise SpecError(f"--points {path}: no points")
    return rows


def make_points(sets: Sequence[str], rows: Sequence[dict[str, str]] | None = None) -> list[Point]:
    """The points of a sweep: the ``-S`` grid (first dimension slowest), crossed with the rows
    of a ``--points`` file when given."""
    dims = [parse_dimension(s) for s in sets]
    names = [p for p, _ in dims]
    for i, p in enumerate(names):
        if p in names[:i]:
            raise SpecError(f"-S {p} given twice (list its values in one -S: {p}=v1,v2,…)")
    file_rows = list(rows) if rows is not None else [{}]
    in_file = {p for r in file_rows for p in r}
    both = sorted(in_file & set(names))
    if both:
        raise SpecError(f"{both[0]} is given both in --points and with -S")
    if not dims and rows is None:
        raise SpecError("nothing to sweep: give -S stage.param=v1,v2,… or --points FILE")
    points: list[Point] = []
    for row in file_rows:
        for combo in itertools.product(*(vals for _, vals in dims)):
            points.append(Point(len(points) + 1, {**row, **dict(zip(names, combo, strict=True))}))
    parsed = [{k: parse_override(f"{k}={v}")[2] for k, v in p.values.items()} for p in points]
    for i, values in enumerate(parsed):
        if values in parsed[:i]:
            raise SpecError(
                f"points {parsed.index(values) + 1} and {i + 1} are the same "
                f"({points[i].label or 'no overrides'})"
            )
    return points


def swept_params(points: Sequence[Point]) -> list[str]:
    """Every parameter a point sets, in order of first appearance."""
    return list(dict.fromkeys(p for pt in points for p in pt.values))


def varied_params(points: Sequence[Point]) -> list[str]:
    """The parameters that take more than one value over the points."""
    return [p for p in swept_params(points) if len({pt.values.get(p) for pt in points}) > 1]


def check_name(name: str) -> str:
    if not _NAME.fullmatch(name) or name in (".", "..") or len(name) > 120:
        shown = name if len(name) <= 40 else f"{name[:37]}…"
        raise SpecError(
            f"sweep name {shown!r} is not allowed: use letters, digits, '_', '-' and "
            "'.', at most 120 (it names a folder under sweeps/)"
        )
    return name


def default_name(points: Sequence[Point], points_file: Path | None = None) -> str:
    """``sweeps/<name>``: the varied parameters joined by ``-`` (the points file's stem with
    ``--points``), characters a folder name should not have replaced by ``_``."""
    if points_file is not None:
        base = Path(points_file).stem
    else:
        base = "-".join(varied_params(points) or swept_params(points))
    base = re.sub(r"[^A-Za-z0-9_.-]", "_", base).strip(".") or "sweep"
    return base[:120]


# --- running ----------------------------------------------------------------------------------


@dataclass
class PointResult:
    """What one point gave: status ``ok`` or ``failed: …``, metric values by column name, the
    node states of its run, its wall time here, compute seconds per stage, keys per node."""

    point: Point
    status: str
    metrics: dict[str, float | None]
    states: list[NodeState]
    wall_s: float
    stage_s: dict[str, float | None]
    keys: dict[str, str]

    @property
    def ran(self) -> int:
        return sum(s.status == "ran" for s in self.states)

    @property
    def cached(self) -> int:
        return sum(s.status == "cached" for s in self.states)


@dataclass
class Sweep:
    """A validated sweep: its points (each with its loaded pipeline), metric columns, the stages
    run (``targets``: the metrics' stages; ``stages``/``nodes``: those and their ancestors)."""

    path: Path
    name: str
    points: list[Point]
    pipes: list[Pipeline]
    columns: list[Column]
    targets: list[str]
    stages: list[str]
    nodes: list[Node]
    jobs: int = 1
    executor: str = "local"  # as `run --executor`: local threads, or dask (one cluster for all)
    scheduler: str | None = None
    results: list[PointResult] = field(default_factory=list)

    @property
    def folder(self) -> Path:
        return inside(self.pipes[0].root / SWEEPS, self.name)

    @property
    def params(self) -> list[str]:
        return swept_params(self.points)

    @property
    def first(self) -> list[Column]:
        """The columns of the first metric (the one the best point is chosen by)."""
        return [c for c in self.columns if c.metric == self.columns[0].metric]

    @property
    def better(self) -> str:
        """``lower`` or ``higher``: which way the first metric is better (its declaration)."""
        spec = self.columns[0].spec
        return spec.better if spec is not None else "lower"

    def score(self, r: PointResult) -> float | None:
        """The first metric of a point, averaged over its datasets (None if one is missing)."""
        values = [r.metrics.get(c.name) for c in self.first]
        if r.status != "ok" or any(v is None for v in values):
            return None
        return sum(v for v in values if v is not None) / len(values)

    def leaders(self) -> list[PointResult]:
        """The points whose first metric is the best (the lowest, or the highest where its
        declaration says higher is better), within the metric's noise (:func:`within_noise`),
        in point order; empty when no point has it."""
        scored = [(s, r) for r in self.results if (s := self.score(r)) is not None]
        if not scored:
            return []
        top = (max if self.better == "higher" else min)(s for s, _ in scored)
        return sorted((r for s, r in scored if within_noise(s, top)), key=lambda r: r.point.index)

    def best(self) -> PointResult | None:
        """The point with the best first metric, when it is better than every other point's
        beyond the metric's noise; None when points tie (or none has the metric)."""
        leaders = self.leaders()
        return leaders[0] if len(leaders) == 1 else None

    # --- the table ---

    def header(self) -> list[str]:
        return [
            "point",
            *self.params,
            *(c.name for c in self.columns),
            "best",
            "status",
            "ran",
            "cached",
            "wall_s",
            *(f"time_s.{s}" for s in self.stages),
            *(f"key.{n.stage}[{n.dataset}]" for n in self.nodes),
        ]

    def rows(self) -> list[list[str]]:
        best = self.best()

        def num(v: float | None) -> str:
            return "" if v is None else repr(v)

        out = []
        for r in sorted(self.results, key=lambda r: r.point.index):
            out.append(
                [
                    str(r.point.index),
                    *(r.point.values.get(p, "") for p in self.params),
                    *(num(r.metrics.get(c.name)) for c in self.columns),
                    "true" if r is best else "false",
                    r.status,
                    str(r.ran),
                    str(r.cached),
                    f"{r.wall_s:.3f}",
                    *(num(r.stage_s.get(s)) for s in self.stages),
                    *(r.keys.get(f"{n.stage}[{n.dataset}]", "") for n in self.nodes),
                ]
            )
        return out

    def csv_text(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.header())
        w.writerows(self.rows())
        return buf.getvalue()

    def definition(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "pipeline": self.path.name,
            "params": self.params,
            "metrics": [c.name for c in self.columns],
            "stages": self.stages,
            "points": [
                {"point": p.index, "values": p.values, "overrides": p.overrides}
                for p in self.points
            ],
        }

    # --- the loop ---

    def run(
        self,
        progress: Callable[[str], None] = lambda s: None,
        echo: Callable[[str], None] | None = None,
    ) -> list[PointResult]:
        """Bring every point up to date in turn; the table and logs are rewritten after each.
        A point whose stage fails on its data (DataError, StageError, SourceError: e.g. a
        filter leaving no detection) is a ``failed`` row and the sweep goes on; any other error
        stops it (the finished rows stay). With the dask executor every point runs on one
        cluster (started once, or ``scheduler``'s)."""
        with contextlib.ExitStack() as stack:
            if self.executor == "dask":
                stack.enter_context(dask_session(self.scheduler, self.jobs, progress))
            elif self.scheduler is not None:
                raise SpecError("--scheduler needs --executor dask")
            return self._run(progress, echo)

    def _run(
        self, progress: Callable[[str], None], echo: Callable[[str], None] | None
    ) -> list[PointResult]:
        check_project(self.pipes[0], ("artifacts", "sweeps"), self.name)  # before any work
        folder = self.folder
        clear_obstacles(self.pipes[0], ("sweeps",), self.name)
        atomic_write_text(folder / DEFINITION, pretty_json(self.definition()))
        times = self._load_times(folder, self.pipes[0].artifacts)
        store = Store(self.pipes[0].artifacts)
        hasher = SourceHasher(self.pipes[0].artifacts / "sources.json")
        self.results = []
        run_log: list[dict[str, Any]] = []
        busy: list[float] = []  # wall times of the points that ran something
        n = len(self.points)
        for point, pipe in zip(self.points, self.pipes, strict=True):
            left = n - point.index + 1
            eta = f" … ETA {_duration(sum(busy) / len(busy) * left)}" if busy else ""
            progress(f"sweep: point {point.index}/{n} ({point.label or 'no overrides'}){eta}")
            runner = Runner(
                pipe, jobs=self.jobs, echo=echo, executor=self.executor, scheduler=self.scheduler
            )
            runner.store, runner.hasher = store, hasher  # verified entries stay verified
            t0 = time.perf_counter()
            status = "ok"
            try:
                states = runner.run(self.targets)
            except (DataError, SourceError, StageError) as err:
                status = f"failed: {one_line(err)}"
                states = _last_run(pipe)
            wall = time.perf_counter() - t0
            for s in states:
                if s.status == "ran" and s.key:
                    times[f"{s.stage}/{s.key}"] = s.seconds
            result = self._result(point, runner, status, states, wall, times)
            self.results.append(result)
            if result.ran:
                busy.append(wall)
            run_log.append(
                {
                    "point": point.index,
                    "overrides": point.overrides,
                    "status": status,
                    "wall_s": wall,
                    "nodes": [asdict(s) for s in states],
                }
            )
            atomic_write_text(folder / TIMES, pretty_json(times))
            atomic_write_text(folder / RUN_LOG, pretty_json(run_log))
            atomic_write_text(folder / TABLE, self.csv_text())
            progress(
                f"  {result.ran} ran, {result.cached} cached in {_duration(wall)}"
                + ("" if status == "ok" else f"; {status}")
            )
            faults.point(f"sweep:point-{point.index}")
        return self.results

    def _result(
        self,
        point: Point,
        runner: Runner,
        status: str,
        states: list[NodeState],
        wall: float,
        times: dict[str, float],
    ) -> PointResult:
        done = {
            Node(s.stage, s.dataset): s.key
            for s in states
            if s.status in ("ran", "cached") and s.key
        }
        docs: dict[tuple[str, str, str], dict[str, Any] | None] = {}
        metrics: dict[str, float | None] = {}
        for col in self.columns:
            m = col.spec
            assert m is not None
            memo = (col.stage, col.dataset, m.output)
            if memo not in docs:
                key = done.get(Node(col.stage, col.dataset))
                docs[memo] = (
                    None
                    if key is None
                    else documents.dump(
                        f"{col.stage}.{m.output}", runner.store.load(col.stage, key, m.output)
                    )
                )
            doc = docs[memo]
            metrics[col.name] = None if doc is None else metric_value(doc, m.path)
        stage_s: dict[str, float | None] = {}
        for stage in self.stages:
            secs = [times.get(f"{n.stage}/{done.get(n)}") for n in self.nodes if n.stage == stage]
            stage_s[stage] = (
                None if any(s is None for s in secs) else sum(s for s in secs if s is not None)
            )
        keys = {f"{n.stage}[{n.dataset}]": k for n, k in done.items() if k is not None}
        return PointResult(point, status, metrics, states, wall, stage_s, keys)

    @staticmethod
    def _load_times(folder: Path, artifacts: Path) -> dict[str, float]:
        """Compute seconds by ``stage/key``: the last plain run's, every sweep's of the project
        (this one's last, so its own measurements win)."""
        times: dict[str, float] = {}
        last = artifacts / "runs" / "last_run.json"
        others = sorted(p for p in folder.parent.glob(f"*/{TIMES}") if p.parent != folder)
        for f in (last, *others, folder / TIMES):
            try:
                doc = json.loads(f.read_text())
            except (OSError, ValueError):
                continue
            if isinstance(doc, list):  # a run log
                times.update(
                    {
                        f"{s['stage']}/{s['key']}": float(s["seconds"])
                        for s in doc
                        if isinstance(s, dict) and s.get("status") == "ran" and s.get("key")
                    }
                )
            elif isinstance(doc, dict):
                times.update(
                    {str(k): float(v) for k, v in doc.items() if isinstance(v, int | float)}
                )
        return times


def _last_run(pipe: Pipeline) -> list[NodeState]:
    """The node states of the run that just failed, from its run log."""
    try:
        doc = json.loads((pipe.artifacts / "runs" / "last_run.json").read_text())
        return [NodeState(**s) for s in doc]
    except (OSError, ValueError, TypeError):
        return []


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s" if seconds >= 10 else f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _restrict(pipe: Pipeline, datasets: Sequence[str]) -> Pipeline:
    """The pipeline with only ``datasets`` and the reference (whose map the others use); no
    cache key changes, since a node's key does not depend on the other datasets."""
    keep = {d: ds for d, ds in pipe.datasets.items() if d in datasets or d == pipe.reference}
    return dataclasses.replace(pipe, config=pipe.config.model_copy(update={"datasets": keep}))


def prepare(
    pipeline: Path,
    registry: Mapping[str, Any],
    points: list[Point],
    metrics: Sequence[str] = (),
    datasets: Sequence[str] = (),
    name: str | None = None,
    points_file: Path | None = None,
    jobs: int = 1,
    executor: str = "local",
    scheduler: str | None = None,
) -> Sweep:
    """Validate a sweep before anything runs: every point's pipeline (so a bad value in the
    last point fails now, not after the others ran), the datasets, the metrics, the name, the
    executor."""
    if executor not in KINDS:
        raise SpecError(f"unknown executor {executor!r} (choose from {', '.join(KINDS)})")
    if scheduler is not None and executor != "dask":
        raise SpecError("--scheduler needs --executor dask")
    pipes: list[Pipeline] = []
    for p in points:
        try:
            pipes.append(load_pipeline(Path(pipeline), registry, p.overrides))
        except SpecError as err:
            if len(points) == 1:
                raise
            raise SpecError(f"sweep point {p.index}/{len(points)} ({p.label}): {err}") from err
    for d in datasets:
        if d not in pipes[0].datasets:
            raise SpecError(f"--dataset {d}: unknown dataset{did_you_mean(d, pipes[0].datasets)}")
    if datasets:
        pipes = [_restrict(p, datasets) for p in pipes]
    graph = build_graph(pipes[0])  # the wiring does not depend on parameters
    columns = resolve_columns(pipes[0], graph, list(metrics), list(datasets))
    stages = list(dict.fromkeys(c.stage for c in columns))
    chosen = select(pipes[0], graph, stages)
    nodes = [n for n in graph.order if n in chosen]
    run_stages = list(dict.fromkeys(n.stage for n in nodes))
    sweep_name = check_name(name) if name is not None else default_name(points, points_file)
    return Sweep(
        Path(pipeline),
        sweep_name,
        points,
        pipes,
        columns,
        stages,
        run_stages,
        nodes,
        jobs,
        executor,
        scheduler,
    )


# --- reading a sweep back (``tagtrail show --point``) ---------------------------------------


def sweep_folders(root: Path) -> list[Path]:
    """The sweeps of a project (folders of ``sweeps/`` with a ``sweep.json``), newest last."""
    base = Path(root) / SWEEPS
    found = [p for p in base.iterdir() if (p / DEFINITION).is_file()] if base.is_dir() else []
    return sorted(found, key=lambda p: ((p / DEFINITION).stat().st_mtime_ns, p.name))


def point_overrides(pipeline: Path, point: int, sweep: str | None = None) -> tuple[str, list[str]]:
    """(sweep name, the ``-S`` overrides of its point ``point``) for ``show --point``; the
    newest sweep next to ``pipeline`` when ``sweep`` is None."""
    root = Path(pipeline).resolve().parent
    folders = sweep_folders(root)
    if not folders:
        raise SpecError(f"no sweep in {root / SWEEPS} (run `tagtrail sweep` first)")
    by_name = {p.name: p for p in folders}
    if sweep is None:
        folder = folders[-1]
    elif sweep in by_name:
        folder = by_name[sweep]
    else:
        raise SpecError(
            f"no sweep {sweep!r} in {root / SWEEPS}{did_you_mean(sweep, by_name)} "
            f"(sweeps: {', '.join(by_name)})"
        )
    try:
        doc = json.loads((folder / DEFINITION).read_text())
        listed = {int(p["point"]): [str(o) for o in p["overrides"]] for p in doc["points"]}
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise SpecError(
            f"{folder / DEFINITION}: unreadable sweep definition "
            f"({one_line(err)}); run the sweep again"
        ) from err
    if point not in listed:
        raise SpecError(f"sweep {folder.name} has points 1..{len(listed)}, not {point}")
    return folder.name, listed[point]


def read_table(path: Path) -> list[dict[str, str]]:
    """The rows of a ``sweep.csv`` (for tests and scripts)."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))
