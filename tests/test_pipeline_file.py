"""The repo's default pipeline.yaml is the demo DAG on demo/data and validates."""

from __future__ import annotations

from pathlib import Path

import yaml

from tagtrail.commands.demo import template

REPO = Path(__file__).resolve().parents[1]


def test_default_pipeline_is_the_demo_dag() -> None:
    root = yaml.safe_load((REPO / "pipeline.yaml").read_text())
    demo = yaml.safe_load(template())
    assert root["stages"] == demo["stages"] and root["reference"] == demo["reference"]
    for name, ds in demo["datasets"].items():
        assert root["datasets"][name]["source"] == "demo/" + ds["source"]
        assert root["datasets"][name].get("inputs") == ds.get("inputs")
