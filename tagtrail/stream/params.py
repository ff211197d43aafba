"""The live nodes' stage parameters: a pipeline file's, else the stages' defaults.

``--pipeline FILE`` (default ``pipeline.yaml`` of the working folder, when there is one) is loaded
and validated as ``tagtrail run`` does (:func:`tagtrail.runner.spec.load_pipeline`), and the
parameters of ``--dataset`` (default: the pipeline's reference) are taken with that dataset's
``params:`` overrides (:meth:`~tagtrail.runner.spec.Pipeline.params_for`). Without a pipeline
file, each stage's ``Params()`` defaults apply (with a ``--profile``'s parameters over them: a
profile is pipeline-file defaults). Command-line flags override either
(:func:`override`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

from pydantic import ValidationError

from tagtrail.errors import SpecError
from tagtrail.stages.base import StageParams

log = logging.getLogger("tagtrail.stream")
DEFAULT_PIPELINE = Path("pipeline.yaml")
P = TypeVar("P", bound=StageParams)


def stage_params(
    stages: Sequence[str],
    pipeline: Path | None = None,
    dataset: str | None = None,
    profile: str | None = None,
) -> dict[str, StageParams]:
    """``{stage: params}`` for ``stages`` from ``pipeline`` (module docstring); without a
    pipeline file, ``profile``'s parameters (:mod:`tagtrail.schemas.profiles`) over the
    defaults."""
    from tagtrail.schemas.profiles import get_profile
    from tagtrail.stages import REGISTRY

    if pipeline is None and DEFAULT_PIPELINE.is_file():
        pipeline = DEFAULT_PIPELINE
    if pipeline is None:
        if dataset is not None:
            raise SpecError(
                f"--dataset {dataset}: there is no pipeline file (no "
                f"{DEFAULT_PIPELINE} here); name one with --pipeline FILE"
            )
        prof = get_profile(profile)
        given = prof.stages if prof is not None else {}
        return {s: REGISTRY[s].Params(**given.get(s, {})) for s in stages}
    from tagtrail.runner.spec import did_you_mean, load_pipeline

    pipe = load_pipeline(Path(pipeline), REGISTRY, check_sources=False)
    name = pipe.reference if dataset is None else dataset
    if name not in pipe.datasets:
        raise SpecError(
            f"--dataset {name}: {pipeline} has no such dataset"
            f"{did_you_mean(name, pipe.datasets)} (datasets: "
            f"{', '.join(pipe.datasets)})"
        )
    log.info("parameters of dataset %s from %s", name, pipeline)
    return {s: pipe.params_for(s, name) for s in stages}


def override(params: P, flags: dict[str, tuple[str, Any]]) -> P:
    """``params`` with the fields of ``flags`` (``{field: (flag, value)}``) whose value is not
    None replaced, validated by the stage's model (a bad value is a :class:`SpecError` naming
    the flag)."""
    given = {f: v for f, (_, v) in flags.items() if v is not None}
    if not given:
        return params
    try:
        return type(params).model_validate({**params.model_dump(), **given})
    except ValidationError as err:
        e = err.errors()[0]
        flag = flags[str(e["loc"][0])][0] if e["loc"] and e["loc"][0] in flags else "a flag"
        raise SpecError(f"{flag}: {str(e['msg']).removeprefix('Value error, ')}") from err
