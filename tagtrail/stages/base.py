"""The stage contract: what a stage module exposes so the runner can wire, cache and run it.

A stage module defines, at module level:

- ``class Params(StageParams)`` — validated parameters (pydantic, unknown keys rejected, frozen).
- ``INPUTS: dict[str, str]`` — ``run`` argument name → reference:
    ``"source"``             the dataset's recording, opened (``schemas.inputs.Source``)
    ``"ground_truth"``       its ground truth, read (``schemas.inputs.GroundTruth``; the stage
                             is skipped for datasets without one)
    ``"dataset"``            the validated ``DatasetConfig`` (for stages that read files
                             themselves, e.g. plugins and tests)
    ``"<stage>.<output>"``   an artifact of the same dataset
    ``"reference:<stage>.<output>"``  an artifact of the reference dataset
- ``OUTPUTS: tuple[str, ...]`` — names of the values ``run`` returns (a dict with exactly these
  keys); a ``pandas.DataFrame`` is stored as Parquet, a ``dict`` as JSON.
- ``SCOPE`` — ``"all"`` (every dataset, default) or ``"query"`` (datasets other than the reference).
- ``PRIMARY`` — the output ``tagtrail show STAGE --csv`` exports (default: the first).
- ``def run(<inputs...>, params: Params) -> dict[str, DataFrame | dict]`` — a pure function:
  no artifact I/O, no global state; the same inputs and params give the same outputs.

The code fingerprint in the cache key is computed by the runner from the module's first-party
import closure (``runner.stage.code_closure``): no hand-kept list of dependencies.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Protocol

from pydantic import BaseModel, ConfigDict, model_validator


def _is_tuple(annotation: Any) -> bool:
    if typing.get_origin(annotation) is tuple:
        return True
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(_is_tuple(a) for a in typing.get_args(annotation))
    return False


class StageParams(BaseModel):
    """Base of every stage's parameters: strict, immutable, hashable as canonical JSON.

    Strict types: a number field takes a number (``true`` or ``"0.16"`` is refused, an int is
    fine for a float), finite only (``.inf``, ``1e400`` and ``.nan`` are refused); a bool field
    takes a bool. YAML lists are accepted for tuple fields.
    ``EXECUTION_ONLY`` names fields that change how a stage runs but not what it computes
    (e.g. worker counts); they are left out of the cache key.
    """

    # use_attribute_docstrings: each field's docstring is its description (docs/PARAMETERS.md)
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False,
                              use_attribute_docstrings=True)
    EXECUTION_ONLY: ClassVar[frozenset[str]] = frozenset()

    @model_validator(mode="before")
    @classmethod
    def _yaml_lists_as_tuples(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        fields = cls.model_fields
        return {k: tuple(v) if isinstance(v, list) and k in fields
                and _is_tuple(fields[k].annotation) else v for k, v in data.items()}

    def key_dump(self) -> dict[str, object]:
        """The parameters that enter the cache key, as JSON-able values."""
        return self.model_dump(mode="json", exclude=set(self.EXECUTION_ONLY))


def refuse_old_keys(stage: str, data: Any, moved: Mapping[str, str]) -> Any:
    """``data`` (a stage's raw parameters) unchanged unless it holds a key of ``moved`` (a name
    that was once a setting -> where it is now): then a ValueError in one line naming it."""
    if isinstance(data, dict):
        for old, new in moved.items():
            if old in data:
                raise ValueError(f"{stage}.{old} is no longer a setting: {new}")
    return data


class StageModule(Protocol):
    """What a stage module exposes (checked at load time by ``runner.stage.stage_spec``)."""

    @property
    def Params(self) -> type[StageParams]: ...
    @property
    def INPUTS(self) -> Mapping[str, str]: ...
    @property
    def OUTPUTS(self) -> tuple[str, ...]: ...
    @property
    def run(self) -> Callable[..., Mapping[str, Any]]: ...
