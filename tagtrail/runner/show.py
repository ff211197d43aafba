"""``tagtrail show``: a stage artifact's schema, row count, head and statistics; CSV export.

The artifact shown is the one the pipeline's current parameters (with the same ``-S`` as the
run) make; when that one does not exist, the node's most recent artifact, with a one-line note
of the parameters it was made with.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from tagtrail.errors import SpecError
from tagtrail.io.layouts import atomic_write_text
from tagtrail.runner.cache import canonical_json, sha256_text
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


def _value(v: object) -> str:
    return json.dumps(v, sort_keys=True, separators=(",", ": "))


def most_recent(runner: Runner, stage: str, dataset: str) -> tuple[str, str]:
    """(key, one-line note) of the node's most recent artifact, when the current parameters'
    one does not exist: the note names the parameters it was made with that differ now."""
    last = runner.store.last_record(dataset, stage)
    key = sha256_text(canonical_json(last)) if last is not None else None
    if last is None or key is None or runner.store.lookup(stage, key) is None:
        raise SpecError(
            f"{stage} [{dataset}] is not up to date: run `tagtrail run {stage}` first "
            "(with the same -S overrides, if any)"
        )
    made = last.get("params") or {}
    now = runner.pipe.params_for(stage, dataset).key_dump()
    diff = [
        f"-S {stage}.{k}={_value(made.get(k))}"
        for k in sorted(set(made) | set(now))
        if made.get(k) != now.get(k)
    ]
    why = (
        f"made with {' '.join(diff)}"
        if diff
        else "made with the same parameters, before its code or inputs changed"
    )
    return key, f"note: not up to date; showing the most recent artifact, {why}"


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
    note = None
    if key is None:
        key, note = most_recent(runner, stage, dataset)
    print(f"{stage} [{dataset}]  artifact {key[:12]}  ({runner.store.entry(stage, key)})")
    if note:
        print(note)
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
