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
- ``METRICS: tuple[Metric, ...]`` (optional) — the numbers of its JSON outputs a
  ``tagtrail sweep`` can rank points by (:class:`Metric`); ``METRICS_HELP`` — one line that
  sums them up for error messages (default: their names).
- ``EXPORTS: tuple[Export, ...]`` (optional) — the files it writes into ``outputs/<dataset>/``
  after a run, and how they are made from artifacts (:class:`Export`).

The code fingerprint in the cache key is computed by the runner from the module's first-party
import closure (``runner.stage.code_closure``): no hand-kept list of dependencies. The contract
lives here, in ``schemas``, so the runner can check it without importing any stage module;
stage modules import it as ``tagtrail.stages.base``.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, Protocol

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
    model_config = ConfigDict(
        extra="forbid", frozen=True, strict=True, allow_inf_nan=False, use_attribute_docstrings=True
    )
    EXECUTION_ONLY: ClassVar[frozenset[str]] = frozenset()

    @model_validator(mode="before")
    @classmethod
    def _yaml_lists_as_tuples(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        fields = cls.model_fields
        return {
            k: tuple(v)
            if isinstance(v, list) and k in fields and _is_tuple(fields[k].annotation)
            else v
            for k, v in data.items()
        }

    def key_dump(self) -> dict[str, object]:
        """The parameters that enter the cache key, as JSON-able values."""
        return self.model_dump(mode="json", exclude=set(self.EXECUTION_ONLY))


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


@dataclass(frozen=True)
class Metric:
    """A number a sweep can rank points by, declared by the stage whose output holds it.

    ``name`` is what ``tagtrail sweep --metric NAME`` takes (unique over the registry);
    ``output`` the stage's JSON output and ``path`` the keys down to the number in its
    serialised form (``documents.dump``; a missing block or a non-finite value reads as no
    value); ``unit`` its unit (``m``, ``deg``, ``px``, ``1`` for a plain number); ``better``
    which way is better; ``datasets`` the datasets it is read from by default (``reference``,
    or every dataset the stage runs on: ``all``); ``default`` > 0 makes it a default column of
    a sweep without ``--metric``, in increasing order (the first ranks the points)."""

    name: str
    output: str
    path: tuple[str, ...]
    unit: str
    better: Literal["lower", "higher"] = "lower"
    datasets: Literal["reference", "all"] = "reference"
    default: int = 0


PARAMS = "params:"  # an export input "params:<stage>": that stage's Params for the dataset
ExportFiles = Mapping[str, tuple[str, Any] | None]
"""What an :class:`Export` makes: file name → (format, value) to write, or None: the file does
not apply this time (a copy left by an earlier run is removed)."""


@dataclass(frozen=True)
class Export:
    """Files a stage writes into ``outputs/<dataset>/`` after a run, made from artifacts.

    ``inputs``: ``make``'s argument → ``"<stage>.<output>"`` or ``"reference:<stage>.<output>"``
    (the up-to-date artifact of this dataset or of the reference; None where there is none), or
    ``"params:<stage>"`` (that stage's parameters for the dataset: what a file is drawn with;
    they enter the export's stamp, so a change redraws it).
    ``make(**inputs)`` is pure (the stage does no I/O; a ``dataset`` argument, if it has one,
    gets the dataset's name): it returns None when the export does not apply to the dataset,
    else :data:`ExportFiles`. A format names a writer of
    :mod:`tagtrail.io.outputs` (``trajectory_csv``, ``json``, ``map_png``, …), which turns the
    value into the file's bytes. ``files`` lists every file ``make`` may name (a multi-file
    format writes the SPEC files it documents). ``name`` names the export in messages and in
    the crash-test point ``export:<name>``."""

    name: str
    files: tuple[str, ...]
    inputs: Mapping[str, str]
    make: Callable[..., ExportFiles | None]
