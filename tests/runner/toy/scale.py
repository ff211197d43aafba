"""Toy stage: multiply by a factor."""

from __future__ import annotations

from pydantic import Field

from tagtrail.stages.base import StageParams

INPUTS = {"table": "load.table"}
OUTPUTS = ("table",)


class Params(StageParams):
    factor: float = Field(2.0, gt=0)


def run(table, params: Params) -> dict:
    return {"table": table.assign(value=table["value"] * params.factor)}
