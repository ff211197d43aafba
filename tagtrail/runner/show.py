"""``tagtrail show``: a stage artifact's schema, row count, head and statistics; CSV export."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from tagtrail.errors import SpecError
from tagtrail.io.layouts import atomic_write_text
from tagtrail.runner.execute import Runner
from tagtrail.runner.spec import did_you_mean
from tagtrail.schemas import documents


def csv_frame(df: pd.DataFrame) -> pd.DataFrame:
    """Human CSV layout: ``t_ns`` → ``stamp_sec, stamp_nanosec`` first, internal indices dropped."""
    out = df.drop(columns=[c for c in ("frame_idx",) if c in df.columns])
    if "t_ns" in out.columns:
        sec, nsec = np.divmod(out["t_ns"].to_numpy(np.int64), 1_000_000_000)
        out = out.drop(columns="t_ns")
        out.insert(0, "stamp_nanosec", nsec)
        out.insert(0, "stamp_sec", sec)
    return out


def show(
    runner: Runner,
    stage: str,
    dataset: str | None,
    output: str | None,
    csv: Path | None,
    rows: int = 10,
) -> int:
    pipe = runner.pipe
    if stage not in pipe.stages:
        raise SpecError(f"unknown stage {stage!r}{did_you_mean(stage, pipe.stages)}")
    spec = pipe.stages[stage]
    if dataset is None:
        candidates = [n.dataset for n in runner.graph.order if n.stage == stage]
        if not candidates:
            raise SpecError(f"stage {stage} runs on no dataset of this pipeline")
        dataset = pipe.reference if pipe.reference in candidates else candidates[0]
    elif dataset not in pipe.datasets:
        raise SpecError(f"unknown dataset {dataset!r}{did_you_mean(dataset, pipe.datasets)}")
    primary = getattr(spec.module, "PRIMARY", spec.outputs[0])
    names = [output] if output else list(spec.outputs)
    for name in names:
        if name not in spec.outputs:
            raise SpecError(
                f"stage {stage} has no output {name!r} (outputs: {', '.join(spec.outputs)})"
            )
    key = runner.key_of(stage, dataset)
    if key is None:
        raise SpecError(f"{stage} [{dataset}] is not up to date: run `tagtrail run {stage}` first "
                        "(with the same -S overrides, if any)")
    print(f"{stage} [{dataset}]  artifact {key[:12]}  ({runner.store.entry(stage, key)})")
    for name in names:
        value = runner.store.load(stage, key, name)
        print(f"\n== {stage}.{name}")
        if not isinstance(value, pd.DataFrame):  # a JSON document
            print(json.dumps(documents.dump(f"{stage}.{name}", value), indent=2, sort_keys=True))
            continue
        print(f"rows: {len(value):,}   columns: {len(value.columns)}")
        print("schema:")
        for col, dtype in value.dtypes.items():
            print(f"  {col:<20} {dtype}")
        with pd.option_context("display.width", 160, "display.max_columns", 20):
            print("head:")
            print(value.head(rows).to_string(index=False) if len(value) else "  (empty)")
            numeric = value.select_dtypes("number")
            if len(value) and not numeric.empty:
                print("summary:")
                print(numeric.describe().T[["mean", "std", "min", "50%", "max"]].to_string())
    if csv is not None:
        name = output or primary
        value = runner.store.load(stage, key, name)
        if not isinstance(value, pd.DataFrame):
            raise SpecError(f"{stage}.{name} is not a table; --csv exports tables")
        atomic_write_text(csv, csv_frame(value).to_csv(index=False))
        print(f"\nwrote {csv} ({len(value):,} rows of {stage}.{name})")
    return 0
