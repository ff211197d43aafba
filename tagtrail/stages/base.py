"""The stage contract: what a stage module exposes so the runner can wire, cache and run it.

A stage module defines, at module level:

- ``class Params(StageParams)`` — validated parameters (pydantic, unknown keys rejected, frozen).
- ``INPUTS: dict[str, str]`` — ``run`` argument name → reference:
    ``"source"``             the dataset's validated ``DatasetConfig`` (schemas.pipeline)
    ``"ground_truth"``       the dataset's ground-truth folder (the stage is skipped without one)
    ``"<stage>.<output>"``   an artifact of the same dataset
    ``"reference:<stage>.<output>"``  an artifact of the reference dataset
- ``OUTPUTS: tuple[str, ...]`` — names of the values ``run`` returns (a dict with exactly these
  keys); a ``pandas.DataFrame`` is stored as Parquet, a ``dict`` as JSON.
- ``SCOPE`` — ``"all"`` (every dataset, default) or ``"query"`` (datasets other than the reference).
- ``DEPENDS: tuple[str, ...]`` — modules whose source also enters the code fingerprint.
- ``PRIMARY`` — the output ``tagtrail show STAGE --csv`` exports (default: the first).
- ``def run(<inputs...>, params: Params) -> dict[str, DataFrame | dict]`` — a pure function:
  no artifact I/O, no global state; the same inputs and params give the same outputs.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import BaseModel, ConfigDict


class StageParams(BaseModel):
    """Base of every stage's parameters: strict, immutable, hashable as canonical JSON.

    ``EXECUTION_ONLY`` names fields that change how a stage runs but not what it computes
    (e.g. worker counts); they are left out of the cache key.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    EXECUTION_ONLY: ClassVar[frozenset[str]] = frozenset()

    def key_dump(self) -> dict[str, object]:
        """The parameters that enter the cache key, as JSON-able values."""
        return self.model_dump(mode="json", exclude=set(self.EXECUTION_ONLY))
