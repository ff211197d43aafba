"""Stage specs: a stage module checked against the contract of ``tagtrail.stages.base``."""

from __future__ import annotations

import hashlib
import importlib
import inspect
import re
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from tagtrail.errors import SpecError
from tagtrail.stages.base import StageParams

_NAME = r"[a-z_][a-z0-9_]*"
_REF = re.compile(rf"^(?:(?P<ds>reference):)?(?P<stage>{_NAME})\.(?P<out>{_NAME})$")
SPECIAL_INPUTS = ("source", "ground_truth")
SCOPES = ("all", "query")


@dataclass(frozen=True)
class InputRef:
    """Where one ``run`` argument comes from: a special input or ``[reference:]stage.output``."""

    special: str | None = None
    stage: str | None = None
    output: str | None = None
    from_reference: bool = False

    @classmethod
    def parse(cls, text: str) -> InputRef:
        if text in SPECIAL_INPUTS:
            return cls(special=text)
        m = _REF.match(text)
        if m is None:
            raise SpecError(
                f"bad input reference {text!r}: expected 'source', 'ground_truth', "
                "'<stage>.<output>' or 'reference:<stage>.<output>'"
            )
        return cls(stage=m["stage"], output=m["out"], from_reference=m["ds"] is not None)

    def __str__(self) -> str:
        if self.special:
            return self.special
        return f"{'reference:' if self.from_reference else ''}{self.stage}.{self.output}"


@dataclass(frozen=True)
class StageSpec:
    """A validated stage module: its parameters model, wiring and code fingerprint."""

    name: str
    module: ModuleType
    params_model: type[StageParams]
    inputs: dict[str, InputRef]
    outputs: tuple[str, ...]
    scope: str
    schema_version: int
    code_fingerprint: str

    def run(self, params: StageParams, **inputs: Any) -> dict[str, Any]:
        return self.module.run(**inputs, params=params)  # type: ignore[no-any-return]


def _source_bytes(mod: ModuleType) -> bytes:
    path = inspect.getsourcefile(mod)
    if path is None:
        raise SpecError(f"stage module {mod.__name__} has no source file to fingerprint")
    with open(path, "rb") as f:
        return f.read()


def code_fingerprint(module: ModuleType, depends: tuple[str, ...] = ()) -> str:
    """sha256 of the stage module's source plus the sources of the modules it declares."""
    h = hashlib.sha256(_source_bytes(module))
    for name in sorted(depends):
        h.update(name.encode())
        h.update(_source_bytes(importlib.import_module(name)))
    return h.hexdigest()


def stage_spec(name: str, module: ModuleType) -> StageSpec:
    """Check ``module`` against the stage contract (signature, outputs, scope) and wrap it."""

    def bad(msg: str) -> SpecError:
        return SpecError(f"stage {name} ({module.__name__}): {msg}")

    params_model = getattr(module, "Params", None)
    if not (isinstance(params_model, type) and issubclass(params_model, StageParams)):
        raise bad("needs `class Params(StageParams)`")
    raw_inputs = getattr(module, "INPUTS", None)
    outputs = getattr(module, "OUTPUTS", None)
    if not isinstance(raw_inputs, dict) or not isinstance(outputs, tuple) or not outputs:
        raise bad("needs INPUTS (dict) and a non-empty OUTPUTS tuple")
    scope = getattr(module, "SCOPE", "all")
    if scope not in SCOPES:
        raise bad(f"SCOPE must be one of {SCOPES}, not {scope!r}")
    run = getattr(module, "run", None)
    if not callable(run):
        raise bad("needs a run() function")
    sig = set(inspect.signature(run).parameters)
    expected = set(raw_inputs) | {"params"}
    if sig != expected:
        raise bad(f"run() takes {sorted(sig)} but INPUTS + params are {sorted(expected)}")
    inputs = {arg: InputRef.parse(ref) for arg, ref in raw_inputs.items()}
    return StageSpec(
        name=name,
        module=module,
        params_model=params_model,
        inputs=inputs,
        outputs=tuple(outputs),
        scope=scope,
        schema_version=int(getattr(module, "SCHEMA_VERSION", 1)),
        code_fingerprint=code_fingerprint(module, tuple(getattr(module, "DEPENDS", ()))),
    )
