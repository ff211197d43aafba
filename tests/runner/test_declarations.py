"""Stages declare their sweep metrics and exports (issue 27); the runner only reads the
declarations: a toy stage's metric ranks a sweep and its export is written, bad declarations are
one SpecError at load, and the real stages declare every metric name `sweep --metric` took."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from tagtrail.errors import SpecError
from tagtrail.runner import sweep as sw
from tagtrail.runner.execute import Runner
from tagtrail.runner.export import export_outputs
from tagtrail.runner.spec import load_pipeline
from tagtrail.runner.stage import stage_spec
from tagtrail.stages import REGISTRY
from tests.runner.toy import copy_stages, load_registry

DECLARED = """

from tagtrail.stages.base import Export, Metric

METRICS = (Metric("toy.sum", "summary", ("sum",), "1", better="{better}", default=1),
           Metric("toy.n", "summary", ("n",), "1"))


def _files(summary):
    return None if summary is None else {{"total.json": ("json", dict(summary))}}


EXPORTS = (Export("{export}", ("total.json",), {{"summary": "{ref}"}}, _files),)
"""


def project(
    tmp_path: Path, better: str = "higher", export: str = "totals", ref: str = "total.summary"
) -> tuple[Path, dict]:
    stages = copy_stages(tmp_path / "stages")
    with open(stages / "total.py", "a") as f:
        f.write(DECLARED.format(better=better, export=export, ref=ref))
    root = tmp_path / "proj"
    root.mkdir()
    (root / "reference.csv").write_text("value\n1\n2\n3\n")
    doc = {
        "datasets": {"reference": {"source": "reference.csv"}},
        "stages": {"scale": {"factor": 2.0}},
    }
    (root / "pipeline.yaml").write_text(yaml.safe_dump(doc))
    return root / "pipeline.yaml", load_registry(stages)


def test_a_toy_stage_exports_its_declared_file(tmp_path: Path) -> None:
    pipe_file, reg = project(tmp_path)
    runner = Runner(load_pipeline(pipe_file, reg))
    runner.run()
    written = export_outputs(runner)
    doc = json.loads((written["reference"] / "total.json").read_text())
    assert doc == {"n": 3, "sum": 12.0}  # (1 + 2 + 3) * factor 2


@pytest.mark.parametrize(("better", "factor"), [("higher", "3"), ("lower", "1")])
def test_the_first_metric_ranks_the_points_its_declared_way(
    tmp_path: Path, better: str, factor: str
) -> None:
    pipe_file, reg = project(tmp_path, better=better)
    points = sw.make_points(["scale.factor=1,3,2"])
    sweep = sw.prepare(pipe_file, reg, points)
    assert [c.name for c in sweep.columns] == ["toy.sum[reference]"]  # the declared default
    sweep.run()
    best = sweep.best()
    assert best is not None and best.point.values == {"scale.factor": factor}
    with pytest.raises(SpecError, match=r"unknown metric 'toy.nn' — did you mean 'toy.n'\?"):
        sw.prepare(pipe_file, reg, points, ["toy.nn"])


def test_bad_declarations_are_one_spec_error(tmp_path: Path) -> None:
    pipe_file, reg = project(tmp_path / "a", ref="total.nothing")
    with pytest.raises(SpecError, match="export 'totals' input summary refers to 'total.nothing'"):
        load_pipeline(pipe_file, reg)
    pipe_file, reg = project(tmp_path / "b", export="Bad-Name")
    with pytest.raises(SpecError, match=r"stage total \(.*\): export 'Bad-Name'"):
        load_pipeline(pipe_file, reg)
    pipe_file, reg = project(tmp_path / "c")
    reg["total"].METRICS = (*reg["total"].METRICS, reg["total"].METRICS[0])
    with pytest.raises(SpecError, match="metric 'toy.sum': a name .* declared once"):
        load_pipeline(pipe_file, reg)
    reg["total"].METRICS = reg["total"].METRICS[:2]
    reg["compare"].METRICS = (dataclasses.replace(reg["total"].METRICS[0], output="diff"),)
    with pytest.raises(SpecError, match="metric 'toy.sum' is declared by both stage"):
        load_pipeline(pipe_file, reg)


def test_the_stages_declare_every_metric_sweep_took() -> None:
    blocks = ("trajectory", "trajectory_raw", "tags", "gauge_free.trajectory", "gauge_free.tags")
    names = [
        f"{b}.{s}_{u}"
        for b in blocks
        for s in ("mean", "median", "rmse", "p95", "max", "min")
        for u in ("m", "deg")
    ]
    for s in ("mean", "median", "p90", "p95", "max", "rmse"):
        names += [f"D.{s}_m", f"abs_phi.{s}_deg"]
    names += [
        "alignment.rms_m",
        "map.rms_t_m",
        "map.rms_r_deg",
        "map.rms_px",
        "map.cost",
        "map.nfev",
    ]
    pipe = SimpleNamespace(stages={n: stage_spec(n, m) for n, m in REGISTRY.items()})
    assert list(sw.declared_metrics(pipe)) == names  # type: ignore[arg-type]
    assert sw.default_metrics(pipe) == [
        "trajectory.rmse_m",
        "tags.rmse_m",
        "D.mean_m",  # type: ignore[arg-type]
        "abs_phi.mean_deg",
        "map.rms_t_m",
    ]
    assert sw.metric_help(pipe).startswith("BLOCK.STAT_m and BLOCK.STAT_deg")  # type: ignore[arg-type]
