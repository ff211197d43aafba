"""Toy stage: a JSON summary."""

from __future__ import annotations

from tagtrail.stages.base import StageParams

INPUTS = {"table": "scale.table"}
OUTPUTS = ("summary",)


class Params(StageParams):
    pass


def run(table, params: Params) -> dict:
    return {"summary": {"sum": float(table["value"].sum()), "n": len(table)}}
