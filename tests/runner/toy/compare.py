"""Toy stage on query datasets: compares with the reference dataset."""

from __future__ import annotations

from tagtrail.stages.base import StageParams

INPUTS = {"total": "total.summary", "ref_total": "reference:total.summary"}
OUTPUTS = ("diff",)
SCOPE = "query"


class Params(StageParams):
    pass


def run(total, ref_total, params: Params) -> dict:
    return {"diff": {"delta": total["sum"] - ref_total["sum"]}}
