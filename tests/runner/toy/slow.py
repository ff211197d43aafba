"""Toy stage: sleeps (to be killed mid-run), then writes a large-ish table."""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from tagtrail.stages.base import StageParams

INPUTS = {"table": "scale.table"}
OUTPUTS = ("table",)


class Params(StageParams):
    seconds: float = 0.0


def run(table, params: Params) -> dict:
    time.sleep(params.seconds)
    rep = np.repeat(table["value"].to_numpy(), 1000)
    return {"table": pd.DataFrame({"value": rep, "i": np.arange(len(rep))})}
