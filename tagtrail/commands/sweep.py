"""``tagtrail sweep``: run a grid (or a list) of parameter overrides on the artifact cache and
tabulate each point's metrics.

Each point is an ordinary run with its ``-S`` overrides, so only the stages a point changes rerun
(an ``optimize.*`` sweep never reruns extract) and a finished point costs nothing the next time:
an interrupted sweep, run again, resumes where it stopped. The grid/metric logic is
:mod:`tagtrail.runner.sweep`; this shell parses, prints the progress (stderr) and the table, and
draws ``sweep.png``. ``tagtrail show STAGE --point N [--sweep NAME]`` opens a point's artifacts.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tagtrail.runner.sweep import Sweep

PLOT = "sweep.png"
MAX_PLOTTED_METRICS = 6
EXAMPLES = """examples:
  tagtrail sweep -S optimize.loss=linear,soft_l1,huber -S optimize.f_scale=0.05,0.1,0.2
  tagtrail sweep -S extract.quad_decimate=1,2 --metric trajectory.rmse_m --metric map.rms_px
  tagtrail sweep -S optimize.f_scale=0.05,0.1 --metric D.mean_m --dataset query_1
  tagtrail sweep --points points.csv --name my-sweep
  tagtrail sweep -S optimize.f_scale=0.05,0.1 --executor dask -j 2   # on a local Dask cluster
  tagtrail show optimize --point 4            # point 4's artifacts (the newest sweep)

values: -S stage.param=v1,v2,... splits at the commas outside [] {} and quotes; each piece is
one YAML value, as for `run -S`: -S pnp.tag_sizes={1: 0.1, 2: 0.2} is one value,
-S pnp.tag_sizes={1: 0.1},{1: 0.2} two. A -S with one value applies to every point.
--points FILE: a CSV whose header names the parameters (one row per point, an empty cell =
no override) or a YAML list of mappings (- {optimize.loss: huber, optimize.f_scale: 0.1}),
crossed with the -S grid.

metrics (declared by the stages; all lower is better; a column NAME[DATASET] each; default:
trajectory.rmse_m, tags.rmse_m, D.mean_m, abs_phi.mean_deg, map.rms_t_m where they exist):
  BLOCK.STAT_m, BLOCK.STAT_deg   errors vs ground truth (eval); BLOCK: trajectory,
                                 trajectory_raw, tags, gauge_free.trajectory, gauge_free.tags;
                                 STAT: mean, median, rmse, p95, max, min
  D.STAT_m, abs_phi.STAT_deg     relocalization (report, query datasets); STAT: mean, median,
                                 p90, p95, max, rmse; alignment.rms_m
  map.rms_t_m, map.rms_r_deg, map.rms_px, map.cost, map.nfev   the map's fit (optimize)
The best point (lowest first metric, averaged over its datasets) is marked.
Writes sweeps/<name>/ next to the pipeline file: sweep.csv (a row per point as it finishes:
parameters, metrics, best, status, per-stage seconds, cache keys), sweep.png, sweep.json
(every point's overrides), runs.json (this invocation's run log per point).
"""


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``sweep`` arguments to ``parser`` (returned)."""
    parser.epilog = EXAMPLES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("-p", "--pipeline", default="pipeline.yaml", help="pipeline file")
    parser.add_argument(
        "-S",
        "--set",
        action="append",
        metavar="STAGE.PARAM=V1,V2,…",
        help="a grid dimension: the values one parameter takes (repeatable; the "
        "points are every combination)",
    )
    parser.add_argument(
        "--points",
        type=Path,
        default=None,
        metavar="FILE",
        help="an explicit list of points: CSV (header = stage.param names) or a "
        "YAML list of mappings",
    )
    parser.add_argument(
        "--metric",
        action="append",
        metavar="NAME",
        help="a metric to tabulate (repeatable; the first picks the best point)",
    )
    parser.add_argument(
        "--dataset",
        action="append",
        metavar="NAME",
        help="read the metrics from this dataset (repeatable; only these and the reference run)",
    )
    parser.add_argument(
        "--name",
        default=None,
        help="the sweep's folder under sweeps/ (default: from the swept params)",
    )
    parser.add_argument(
        "-j",
        "--jobs",
        type=int,
        default=1,
        help="stages run in parallel (dask: worker processes of the local cluster)",
    )
    parser.add_argument(
        "--executor",
        choices=("local", "dask"),
        default=None,
        help="where stages run: local threads (default) or one Dask cluster for "
        "every point (pip install 'tagtrail[dask]')",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="an existing Dask scheduler (tcp://host:8786; implies --executor "
        "dask; default: start a local cluster)",
    )
    parser.add_argument(
        "--dry-run", action="store_true", help="list the points and metric columns; run nothing"
    )
    return parser


def build_parser() -> argparse.ArgumentParser:
    return add_arguments(
        argparse.ArgumentParser(
            prog="tagtrail sweep",
            description="Run a grid of parameter overrides on the cache and tabulate the metrics.",
        )
    )


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """Run from parsed arguments (or an argv list); 0 on success, 1 if a point failed, the
    error's exit code else."""
    from tagtrail.cli import run_command

    ns = args if isinstance(args, argparse.Namespace) else build_parser().parse_args(args)
    return run_command(lambda: _main(ns))


def _main(ns: argparse.Namespace) -> int:
    from tagtrail.runner import sweep as sw
    from tagtrail.stages import REGISTRY

    rows = sw.read_points(ns.points) if ns.points is not None else None
    points = sw.make_points(ns.set or (), rows)
    executor = ns.executor or ("dask" if ns.scheduler else "local")
    sweep = sw.prepare(
        Path(ns.pipeline),
        REGISTRY,
        points,
        ns.metric or (),
        ns.dataset or (),
        ns.name,
        ns.points,
        ns.jobs,
        executor,
        ns.scheduler,
    )
    if ns.dry_run:
        print(f"sweep {sweep.name}: {len(points)} points into {sweep.folder}")
        for p in points:
            print(f"  point {p.index}: {p.label or '(no overrides)'}")
        print("metrics: " + ", ".join(c.name for c in sweep.columns))
        print("stages run: " + ", ".join(sweep.stages))
        return 0

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    verbose = bool(getattr(ns, "verbose", False))
    echo = (lambda s: print("    " + s, file=sys.stderr)) if verbose else None
    progress(
        f"sweep {sweep.name}: {len(points)} points, metrics "
        f"{', '.join(c.name for c in sweep.columns)} -> {sweep.folder}"
    )
    quiet = logging.getLogger("tagtrail")
    level = quiet.level
    if not verbose:  # nine points of stage INFO lines drown the progress; warnings still show
        quiet.setLevel(logging.WARNING)
    try:
        results = sweep.run(progress, echo)
    finally:
        quiet.setLevel(level)
    plot = write_plot(sweep, sweep.folder / PLOT)
    print("\n".join(table(sweep)))
    print("\n" + best_line(sweep))
    failed = [r for r in results if r.status != "ok"]
    print(
        f"wrote {sweep.folder / sw.TABLE} ({len(results)} rows)"
        + (f", {plot}" if plot is not None else "")
    )
    print(f"open a point's artifacts: tagtrail show STAGE --point N --sweep {sweep.name}")
    if failed:
        print(
            f"{len(failed)} point(s) failed: " + ", ".join(str(r.point.index) for r in failed),
            file=sys.stderr,
        )
        return 1
    return 0


WIDTH = 100  # the printed table's lines fit this many columns
MAX_CELL = 24  # a parameter value longer than this is cut (sweep.csv has it whole)


def best_line(sweep: Sweep) -> str:
    """The line under the table: the best point, or why there is none (a tie within the
    metric's noise, or no point with the metric)."""
    from tagtrail.runner.sweep import NOISE_REL

    first = sweep.columns[0].metric
    over = f" (mean of {len(sweep.first)} datasets)" if len(sweep.first) > 1 else ""
    best, leaders = sweep.best(), sweep.leaders()
    if best is not None:
        way = "lowest" if sweep.better == "lower" else "highest"
        return (
            f"best ({way} {first}{over}): point {best.point.index}: "
            f"{best.point.label or '(no overrides)'}"
        )
    if not leaders:
        return f"best: none (no point has {first})"
    value = sweep.score(leaders[0])
    return (
        f"best: none: points {', '.join(str(r.point.index) for r in leaders)} give the same "
        f"{first}{over} ({digits([value])[0]}) within its noise (relative {NOISE_REL:g})"
    )


def digits(values: Sequence[float | None], least: int = 4, most: int = 7) -> list[str]:
    """``values`` to as few significant digits (``least`` … ``most``) as tell apart every two
    that differ beyond the metric's noise; values the same within noise print the same."""
    from tagtrail.runner.sweep import within_noise

    real = [v for v in values if v is not None]
    for n in range(least, most + 1):
        text = {v: f"{v:.{n}g}" for v in real}
        if all(
            text[a] != text[b]
            for i, a in enumerate(real)
            for b in real[i + 1 :]
            if not within_noise(a, b)
        ):
            break
    return ["-" if v is None else f"{v:.{n}g}" for v in values]


def _cut(text: str) -> str:
    return text if len(text) <= MAX_CELL else text[: MAX_CELL - 1] + "…"


def table(sweep: Sweep, width: int = WIDTH) -> list[str]:
    """The printed table: point, parameters, metric columns, the best point starred; metric
    columns that do not fit ``width`` go to a further block (point and parameters repeated)."""
    from tagtrail.commands.eval import aligned

    best = sweep.best()
    results = sorted(sweep.results, key=lambda r: r.point.index)
    left = [["point", *sweep.params]] + [
        [str(r.point.index), *(_cut(r.point.values.get(p, "")) for p in sweep.params)]
        for r in results
    ]
    marks = ["*" if r is best else ("failed" if r.status != "ok" else "") for r in results]
    cols = [[c.name, *digits([r.metrics.get(c.name) for r in results])] for c in sweep.columns]
    left_w = sum(max(len(row[i]) for row in left) + 2 for i in range(len(left[0])))
    mark_w = max((len(m) for m in marks), default=0) + 2
    blocks: list[list[list[str]]] = [[]]
    used = left_w + mark_w
    for col in cols:
        w = max(len(cell) for cell in col) + 2
        if blocks[-1] and used + w > width:
            blocks.append([])
            used = left_w + mark_w
        blocks[-1].append(col)
        used += w
    lines: list[str] = []
    for k, block in enumerate(blocks):
        header = [*left[0], *(c[0] for c in block), ""]
        body = [[*left[i + 1], *(c[i + 1] for c in block), marks[i]] for i in range(len(results))]
        lines += ([""] if k else []) + aligned(
            header, body, text=(*range(1, len(left[0])), len(header) - 1)
        )
    return lines


def _number(text: str) -> float | None:
    import yaml

    try:
        v = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def denoised(ys: Sequence[float | None]) -> list[float | None]:
    """A metric's values as plotted: all one value (their mean) when every two agree within
    the metric's noise, so float noise draws a flat line, not a trend."""
    from tagtrail.runner.sweep import within_noise

    real = [y for y in ys if y is not None]
    if real and within_noise(min(real), max(real)):
        mean = sum(real) / len(real)
        return [None if y is None else mean for y in ys]
    return list(ys)


MIN_SPAN_REL = 1e-3  # a y axis spans at least this much of its values: short tick labels


def _y_range(ax: Any, ys: Sequence[float]) -> None:
    """Plain tick labels (no ``1e-16+1.48e-3`` offset) on an axis at least
    :data:`MIN_SPAN_REL` of its values wide, centred on them."""
    ax.ticklabel_format(axis="y", useOffset=False, style="plain")
    if not ys:
        return
    lo, hi = min(ys), max(ys)
    span = max(hi - lo, MIN_SPAN_REL * max(abs(lo), abs(hi)), 1e-12)
    mid = (lo + hi) / 2
    ax.set_ylim(mid - 0.55 * span, mid + 0.55 * span)


def write_plot(sweep: Sweep, path: Path) -> Path | None:
    """``sweep.png``: each metric (rows; averaged over its datasets) against each parameter that
    varies (columns): every point as a dot, the lowest over the other parameters as a line, the
    best point starred (when it is best beyond the metric's noise). Values that agree within
    the noise are drawn as one (:func:`denoised`), axes without offset notation. None when no
    point has a metric."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from tagtrail.io.layouts import atomic_write
    from tagtrail.runner.sweep import varied_params

    ok = [r for r in sweep.results if r.status == "ok"]
    metrics = list(dict.fromkeys(c.metric for c in sweep.columns))[:MAX_PLOTTED_METRICS]
    params = varied_params([r.point for r in sweep.results]) or sweep.params
    if not ok or not params:
        return None
    best = sweep.best()
    fig = Figure(
        figsize=(4.4 * len(params), 2.6 * len(metrics) + 0.6), dpi=100, layout="constrained"
    )
    axes = fig.subplots(len(metrics), len(params), squeeze=False)
    for i, metric in enumerate(metrics):
        cols = [c.name for c in sweep.columns if c.metric == metric]
        spec = next(c.spec for c in sweep.columns if c.metric == metric)
        top = max if spec is not None and spec.better == "higher" else min  # its declared way

        def mean(r: Any, cols: list[str] = cols) -> float | None:
            vals = [r.metrics.get(c) for c in cols]
            return None if any(v is None for v in vals) else sum(vals) / len(vals)

        plotted = dict(zip([id(r) for r in ok], denoised([mean(r) for r in ok]), strict=True))

        def value(r: Any, plotted: dict[int, float | None] = plotted) -> float | None:
            return plotted[id(r)]

        for j, param in enumerate(params):
            ax = axes[i][j]
            texts = [r.point.values.get(param, "") for r in ok]
            nums = [_number(t) for t in texts]
            numeric = all(n is not None for n in nums)
            order = list(dict.fromkeys(texts))
            xs = [
                float(n) if numeric and n is not None else float(order.index(t))
                for n, t in zip(nums, texts, strict=True)
            ]
            ys = [value(r) for r in ok]
            pts = [(x, y) for x, y in zip(xs, ys, strict=True) if y is not None]
            if pts:
                ax.scatter(
                    [x for x, _ in pts],
                    [y for _, y in pts],
                    s=14,
                    color="0.55",
                    zorder=2,
                    label="every point",
                )
                low: dict[float, float] = {}
                for x, y in pts:
                    low[x] = top(y, low.get(x, y))
                line = sorted(low.items())
                ax.plot(
                    [x for x, _ in line],
                    [y for _, y in line],
                    color="tab:blue",
                    marker="o",
                    markersize=4,
                    zorder=3,
                    label="lowest" if top is min else "highest",
                )
            if best is not None and best in ok and (yb := value(best)) is not None:
                xb = xs[ok.index(best)]
                ax.scatter(
                    [xb],
                    [yb],
                    marker="*",
                    s=160,
                    color="tab:red",
                    zorder=4,
                    label=f"best (point {best.point.index})",
                )
            if numeric:
                positive = [x for x in xs if x > 0]
                if len(positive) == len(xs) and max(xs) / min(xs) >= 20:
                    ax.set_xscale("log")
            else:
                ax.set_xticks(range(len(order)), order)
            _y_range(ax, [y for _, y in pts])
            ax.set_xlabel(param)
            over = f" (mean of {len(cols)})" if len(cols) > 1 else ""
            ax.set_ylabel(f"{metric}{over}" if len(cols) > 1 else cols[0])
            ax.grid(alpha=0.3)
            if i == 0 and j == 0:
                ax.legend(fontsize="small")
    fig.suptitle(f"sweep {sweep.name}: {len(ok)} points")
    FigureCanvasAgg(fig)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", metadata={"Software": None}))
    return path


if __name__ == "__main__":
    raise SystemExit(main())
