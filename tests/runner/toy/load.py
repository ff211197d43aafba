"""Toy stage: read the dataset's CSV source."""

from __future__ import annotations

import pandas as pd

from tagtrail.stages.base import StageParams

INPUTS = {"source": "dataset"}
OUTPUTS = ("table",)


class Params(StageParams):
    column: str = "value"


def run(source, params: Params) -> dict:
    df = pd.read_csv(source.source)
    return {"table": df[[params.column]].rename(columns={params.column: "value"})}
