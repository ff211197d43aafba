"""Real pipelines for the stage tests: write one, run stages, read an artifact."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import yaml

from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import load_pipeline
from tagtrail.stages import REGISTRY


def pipeline_file(tmp_path: Path, dataset: str, stages: dict) -> Path:
    path = tmp_path / "pipeline.yaml"
    path.write_text(
        yaml.safe_dump({"datasets": {"reference": yaml.safe_load(dataset)}, "stages": stages})
    )
    return path


def run_stages(path: Path, *stages: str) -> Runner:
    runner = Runner(load_pipeline(path, REGISTRY))
    runner.run(list(stages))
    return runner


def artifact(runner: Runner, stage: str, output: str) -> pd.DataFrame:
    key = next(s.key for s in runner.plan([stage]) if s.stage == stage)
    out: pd.DataFrame = runner.store.load(stage, key, output)
    return out
