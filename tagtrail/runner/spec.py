"""Load and validate ``pipeline.yaml`` against the stage registry.

Every user mistake becomes one :class:`SpecError` naming the file and the offending key, with a
did-you-mean for misspelt stage, dataset and parameter names.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from tagtrail.errors import SpecError, abbreviate, short_repr
from tagtrail.io.camera_files import split_camera_path
from tagtrail.runner.stage import InputRef, StageSpec, stage_spec
from tagtrail.schemas.pipeline import DatasetConfig, PipelineConfig
from tagtrail.schemas.ranges import check_expansion
from tagtrail.schemas.stage import PARAMS, StageParams


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f" — did you mean {close[0]!r}?" if close else ""


def _fmt_validation(where: str, err: ValidationError, fields: Iterable[str] = ()) -> str:
    e = err.errors()[0]
    loc = ".".join(str(p) for p in e["loc"])
    if e["type"] == "extra_forbidden":
        key = str(e["loc"][-1])
        return f"{where}: unknown key {loc!r}{did_you_mean(key, fields)}"
    got = (
        f" (got {short_repr(e['input'])})"
        if "input" in e and not isinstance(e["input"], dict)
        else ""
    )
    msg = abbreviate(str(e["msg"]).removeprefix("Value error, "))
    if e["type"] == "value_error":
        got = ""
    return f"{where}.{loc}: {msg}{got}" if loc else f"{where}: {msg}"


@dataclass(frozen=True)
class Pipeline:
    """A validated pipeline: datasets (paths absolute), stages with their validated params."""

    path: Path
    root: Path
    config: PipelineConfig
    stages: dict[str, StageSpec]
    params: dict[str, StageParams]
    dataset_params: dict[tuple[str, str], StageParams]

    def params_for(self, stage: str, dataset: str) -> StageParams:
        """The stage's parameters for one dataset (its ``params:`` overrides applied)."""
        return self.dataset_params.get((stage, dataset), self.params[stage])

    @property
    def datasets(self) -> dict[str, DatasetConfig]:
        return self.config.datasets

    @property
    def reference(self) -> str:
        return self.config.reference

    @property
    def artifacts(self) -> Path:
        return self.root / "artifacts"

    @property
    def outputs(self) -> Path:
        return self.root / "outputs"


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key written twice in one mapping (YAML says "last one wins")."""


def _unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> Any:
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *defaults` may be overridden
            continue
        key = loader.construct_object(key_node, deep=True)
        line = key_node.start_mark.line + 1
        try:
            first = seen.get(key)
            seen[key] = line
        except TypeError:  # an unhashable key: the base constructor reports it
            continue
        if first is not None:
            raise yaml.constructor.ConstructorError(
                None,
                None,
                f"key {key!r} written twice (lines {first} and {line})",
                key_node.start_mark,
            )
    return loader.construct_mapping(node, deep=deep)


# YAML 1.2 reads `1e-3` as a number; PyYAML (YAML 1.1) would read it as the string "1e-3".
_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)
_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


def load_yaml(text: str, where: str) -> Any:
    """Parse YAML (duplicate keys refused); errors are one :class:`SpecError` line."""
    try:
        doc = yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader subclass: safe
        return check_expansion(doc)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = f" line {mark.line + 1}:" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise SpecError(f"{where}:{line} invalid YAML: {abbreviate(problem)}") from err
    except RecursionError as err:
        raise SpecError(f"{where}: invalid YAML: nested too deeply") from err
    except ValueError as err:
        raise SpecError(f"{where}: refused: {err}") from err


def parse_override(text: str) -> tuple[str, list[str], Any]:
    """``stage.param[.key]=value`` → (stage, key path, YAML-parsed value)."""
    if "=" not in text:
        raise SpecError(f"bad override {short_repr(text)}: expected stage.param=value")
    lhs, rhs = text.split("=", 1)
    parts = lhs.strip().split(".")
    if len(parts) < 2 or not all(parts):
        raise SpecError(f"bad override {short_repr(text)}: expected stage.param=value")
    value = load_yaml(rhs, f"bad override -S {short_repr(text)}") if rhs.strip() else None
    return parts[0], parts[1:], value


def _resolve_dataset(name: str, ds: DatasetConfig, root: Path, check: bool) -> DatasetConfig:
    def absolute(p: Path | None) -> Path | None:
        return None if p is None else (p if p.is_absolute() else (root / p)).resolve()

    source = absolute(ds.source)
    assert source is not None
    if not check:  # only the parameters are wanted (a live node on a machine without the data)
        gt = absolute(ds.ground_truth)
        return ds.model_copy(
            update={"source": source, "camera": absolute(ds.camera), "ground_truth": gt}
        )
    if not source.exists():
        raise SpecError(f"dataset {name!r}: source {source} does not exist")
    camera = absolute(ds.camera)
    if camera is not None and not split_camera_path(camera)[0].is_file():
        raise SpecError(f"dataset {name!r}: camera file {camera} does not exist")
    gt = absolute(ds.ground_truth)
    if gt is None and source.is_dir() and (source / "ground_truth").is_dir():
        gt = source / "ground_truth"
    elif gt is not None and not gt.is_dir():
        raise SpecError(f"dataset {name!r}: ground_truth folder {gt} does not exist")
    return ds.model_copy(update={"source": source, "camera": camera, "ground_truth": gt})


def _origin(
    path: Path, given: Mapping[tuple[str, str], str], stage: str, err: ValidationError
) -> str:
    """Where a bad parameter came from: the ``-S`` that set it, else the pipeline file."""
    loc = err.errors()[0]["loc"]
    text = given.get((stage, str(loc[0]))) if loc else None
    return f"-S {short_repr(text, 120)[1:-1]}: " if text is not None else f"{path}: "


def _check_kind(
    path: Path, dataset: str, key: str, ref: InputRef, stages: Mapping[str, StageSpec]
) -> None:
    """A rewired input must name an artifact that exists and is of the kind the stage's input
    takes (the output name of its default wiring: a ``tag_map``, a ``trajectory``, …): else
    the stage would fail deep inside on a missing column."""
    stage, _, arg = key.partition(".")
    default = stages[stage].inputs[arg]
    where = f"{path}: datasets.{dataset}.inputs: {key}: {short_repr(str(ref), 80)}"
    if ref.special is not None or default.special is not None:
        if ref.special != default.special:
            raise SpecError(f"{where}: {stage}'s input {arg} takes {default} only")
        return
    assert ref.stage is not None and ref.output is not None
    if ref.stage not in stages:
        raise SpecError(f"{where}: unknown stage {ref.stage!r}{did_you_mean(ref.stage, stages)}")
    if ref.output not in stages[ref.stage].outputs:
        outs = ", ".join(stages[ref.stage].outputs)
        raise SpecError(f"{where}: stage {ref.stage} has no output {ref.output!r} (it has {outs})")
    if ref.output != default.output:
        raise SpecError(
            f"{where}: {stage}'s input {arg} takes a {default.output} artifact "
            f"(e.g. {default}); {ref.stage}.{ref.output} is not one"
        )


def check_declarations(stages: Mapping[str, StageSpec]) -> None:
    """What the stages declare for sweeps and exports, checked across the registry: each
    metric and export name once, each export input an output of a registered stage."""
    owner: dict[str, str] = {}
    exports: dict[str, str] = {}
    for name, spec in stages.items():
        for m in spec.metrics:
            if m.name in owner:
                raise SpecError(
                    f"metric {m.name!r} is declared by both stage {owner[m.name]} and stage {name}"
                )
            owner[m.name] = name
        for e in spec.exports:
            if e.name in exports:
                raise SpecError(
                    f"export {e.name!r} is declared by both stage {exports[e.name]} "
                    f"and stage {name}"
                )
            exports[e.name] = name
            for arg, text in e.inputs.items():
                if text.startswith(PARAMS):
                    if text.removeprefix(PARAMS) not in stages:
                        raise SpecError(
                            f"stage {name}: export {e.name!r} input {arg} refers to "
                            f"{text!r}, which is no registered stage"
                        )
                    continue
                ref = InputRef.parse(text)
                spec_of = stages.get(ref.stage or "")
                if spec_of is None or ref.output not in spec_of.outputs:
                    raise SpecError(
                        f"stage {name}: export {e.name!r} input {arg} refers to "
                        f"{text!r}, which no registered stage outputs"
                    )


def load_pipeline(
    path: Path,
    registry: Mapping[str, Any],
    overrides: Iterable[str] = (),
    check_sources: bool = True,
) -> Pipeline:
    """Read, validate and resolve a pipeline file; apply ``-S stage.param=value`` overrides.

    ``check_sources=False`` skips checking that the datasets' files exist (for callers that
    only need the parameters, like the live nodes)."""
    path = Path(path)
    if not path.is_file():
        raise SpecError(f"{path}: pipeline file not found (create one with `tagtrail init`)")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise SpecError(f"{path}: cannot read the pipeline file ({err})") from err
    doc = load_yaml(text, str(path))
    if not isinstance(doc, dict):
        raise SpecError(f"{path}: expected a mapping with 'datasets:' and 'stages:'")
    try:
        config = PipelineConfig.model_validate(doc)
    except ValidationError as err:
        raise SpecError(_fmt_validation(str(path), err, PipelineConfig.model_fields)) from err
    if not config.datasets:
        raise SpecError(f"{path}: no datasets declared")
    if config.reference not in config.datasets:
        raise SpecError(
            f"{path}: reference dataset {config.reference!r} is not declared"
            f"{did_you_mean(config.reference, config.datasets)}"
        )

    stages = {name: stage_spec(name, mod) for name, mod in registry.items()}
    check_declarations(stages)
    raw: dict[str, dict[str, Any]] = {k: dict(v or {}) for k, v in config.stages.items()}
    given: dict[tuple[str, str], str] = {}  # (stage, param) -> the -S that set it
    for text in overrides:
        stage, keys, value = parse_override(text)
        given[(stage, keys[0])] = text
        node = raw.setdefault(stage, {})
        for k in keys[:-1]:
            node = node.setdefault(k, {})
            if not isinstance(node, dict):
                raise SpecError(f"override -S {stage}.{'.'.join(keys)}: {k} is not a mapping")
        node[keys[-1]] = value
    for name in raw:
        if name not in stages:
            by = next((t for (st, _), t in given.items() if st == name), None)
            src = (
                str(path)
                if name in config.stages or by is None
                else f"-S {short_repr(by, 120)[1:-1]}"
            )
            raise SpecError(f"{src}: unknown stage {name!r}{did_you_mean(name, stages)}")
    root = path.resolve().parent
    ctx = {"root": root}  # files named by parameters (optimize.survey.file) are taken from here
    params: dict[str, StageParams] = {}
    for name, spec in stages.items():
        try:
            params[name] = spec.params_model.model_validate(raw.get(name, {}), context=ctx)
        except ValidationError as err:
            where = f"{_origin(path, given, name, err)}stages.{name}"
            raise SpecError(_fmt_validation(where, err, spec.params_model.model_fields)) from err

    dataset_params: dict[tuple[str, str], StageParams] = {}
    for ds_name, ds in config.datasets.items():
        for name, extra in ds.params.items():
            if name not in stages:
                raise SpecError(
                    f"{path}: datasets.{ds_name}.params: unknown stage {name!r}"
                    f"{did_you_mean(name, stages)}"
                )
            merged = {**raw.get(name, {}), **(extra or {})}
            try:
                dataset_params[(name, ds_name)] = stages[name].params_model.model_validate(
                    merged, context=ctx
                )
            except ValidationError as err:
                where = f"{_origin(path, given, name, err)}datasets.{ds_name}.params.{name}"
                fields = stages[name].params_model.model_fields
                raise SpecError(_fmt_validation(where, err, fields)) from err

    datasets = {
        n: _resolve_dataset(n, ds, root, check_sources) for n, ds in config.datasets.items()
    }
    for n, ds in datasets.items():
        for key, ref in ds.inputs.items():
            stage, _, arg = key.partition(".")
            if stage not in stages or arg not in stages[stage].inputs:
                raise SpecError(
                    f"{path}: datasets.{n}.inputs: {key!r} is not '<stage>.<input>'"
                    f"{did_you_mean(key, (f'{s}.{a}' for s in stages for a in stages[s].inputs))}"
                )
            _check_kind(path, n, key, InputRef.parse(ref), stages)
    config = config.model_copy(update={"datasets": datasets})
    return Pipeline(
        path=path,
        root=root,
        config=config,
        stages=stages,
        params=params,
        dataset_params=dataset_params,
    )
