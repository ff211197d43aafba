"""Toy projects for the runner's tests: a pipeline file over CSV datasets, and what ran."""

from __future__ import annotations

from pathlib import Path

import yaml


def write_project(root: Path, stages: dict | None = None, **datasets: str) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    datasets = datasets or {"reference": "value\n1\n2\n3\n", "query": "value\n4\n5\n"}
    for name, text in datasets.items():
        (root / f"{name}.csv").write_text(text)
    doc = {
        "datasets": {n: {"source": f"{n}.csv"} for n in datasets},
        "stages": stages or {"scale": {"factor": 2.0}},
    }
    (root / "pipeline.yaml").write_text(yaml.safe_dump(doc))
    return root / "pipeline.yaml"


def executed(states) -> set[tuple[str, str]]:
    return {(s.stage, s.dataset) for s in states if s.status == "ran"}


def cached(states) -> set[tuple[str, str]]:
    return {(s.stage, s.dataset) for s in states if s.status == "cached"}


ALL = {
    (s, d)
    for s in ("load", "scale", "slow", "total", "compare")
    for d in ("reference", "query")
    if not (s == "compare" and d == "reference")
}
