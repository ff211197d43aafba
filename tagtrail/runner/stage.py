"""Stage specs: a stage module checked against the contract of ``tagtrail.schemas.stage``."""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import inspect
import os
import re
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from tagtrail.errors import SpecError
from tagtrail.schemas.stage import PARAMS, Export, Metric, StageParams

_NAME = r"[a-z_][a-z0-9_]*"
_REF = re.compile(rf"^(?:(?P<ds>reference):)?(?P<stage>{_NAME})\.(?P<out>{_NAME})$")
SPECIAL_INPUTS = ("source", "ground_truth", "dataset")
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
    code_modules: dict[str, str]
    metrics: tuple[Metric, ...] = ()
    metrics_help: str = ""
    exports: tuple[Export, ...] = ()

    @property
    def code_fingerprint(self) -> str:
        return fingerprint(self.code_modules)

    def run(self, params: StageParams, **inputs: Any) -> dict[str, Any]:
        return self.module.run(**inputs, params=params)  # type: ignore[no-any-return]


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    """Drop module, class and function docstrings (comments are not in the AST at all)."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if (
                body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
    return tree


@functools.lru_cache(maxsize=512)
def _parse(path: str, mtime_ns: int, size: int) -> tuple[str, tuple[tuple[str, str | None], ...]]:
    """(hash of the code, its imports as (module, name taken from it or None)) of one source
    file; cached per file version. Relative modules keep their leading dots."""
    with open(path, "rb") as f:
        tree = ast.parse(f.read(), filename=path)
    digest = hashlib.sha256(ast.dump(_strip_docstrings(tree)).encode()).hexdigest()
    imports: list[tuple[str, str | None]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imports += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = "." * node.level + (node.module or "")
            imports += [(module, a.name) for a in node.names]
    return digest, tuple(imports)


@functools.lru_cache(maxsize=1024)
def _origin(name: str) -> str | None:
    """The source file of an importable module, or None (not a module, or no source)."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    origin = spec.origin if spec is not None else None
    return origin if origin is not None and origin.endswith(".py") else None


def _absolute(name: str, importer: str, is_package: bool) -> str:
    if not name.startswith("."):
        return name
    level = len(name) - len(name.lstrip("."))
    parts = importer.split(".")
    base = parts if is_package else parts[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join([*base, *([name.lstrip(".")] if name.lstrip(".") else [])])


def code_closure(module: ModuleType) -> dict[str, str]:
    """Hash of every first-party module ``module`` imports, directly or not (lazy imports in
    functions included), by module name; the module itself is ``"."``. A module's hash covers
    its code, not its docstrings, comments or layout. First party = ``tagtrail`` and the
    module's own top-level package. ``from pkg import sub`` follows the submodule ``pkg.sub``;
    a package's ``__init__`` counts only where a name is taken from it."""
    first_party = {"tagtrail", module.__name__.split(".")[0]}
    path = inspect.getsourcefile(module)
    if path is None:
        raise SpecError(f"module {module.__name__} has no source file to fingerprint")
    out: dict[str, str] = {}
    todo: list[tuple[str, str]] = [(module.__name__, path)]
    seen = {module.__name__}
    while todo:
        name, file = todo.pop()
        st = os.stat(file)
        digest, imports = _parse(file, st.st_mtime_ns, st.st_size)
        out["." if name == module.__name__ else name] = digest
        is_package = os.path.basename(file) == "__init__.py"
        for mod, attr in imports:
            target = _absolute(mod, name, is_package)
            if target.split(".")[0] not in first_party:
                continue
            if attr is not None and _origin(f"{target}.{attr}") is not None:
                target = f"{target}.{attr}"  # a submodule, not a name of the package
            if target in seen or (origin := _origin(target)) is None:
                continue
            seen.add(target)
            todo.append((target, origin))
    return dict(sorted(out.items()))


def fingerprint(closure: dict[str, str]) -> str:
    """sha256 over a :func:`code_closure`: changes exactly when code the module runs changes."""
    text = "".join(f"{name}\0{digest}\n" for name, digest in sorted(closure.items()))
    return hashlib.sha256(text.encode()).hexdigest()


def code_fingerprint(module: ModuleType) -> str:
    return fingerprint(code_closure(module))


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
    metrics = _metrics(module, tuple(outputs), bad)
    help_text = getattr(module, "METRICS_HELP", None) or ", ".join(m.name for m in metrics)
    if not isinstance(help_text, str):
        raise bad("METRICS_HELP must be a string")
    return StageSpec(
        name=name,
        module=module,
        params_model=params_model,
        inputs=inputs,
        outputs=tuple(outputs),
        scope=scope,
        code_modules=code_closure(module),
        metrics=metrics,
        metrics_help=help_text,
        exports=_exports(module, bad),
    )


_METRIC_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.]*$")
_FILE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")


def _metrics(module: ModuleType, outputs: tuple[str, ...], bad: Any) -> tuple[Metric, ...]:
    """The stage's ``METRICS``, checked: each a :class:`Metric` on one of its outputs."""
    metrics = getattr(module, "METRICS", ())
    if not isinstance(metrics, tuple) or not all(isinstance(m, Metric) for m in metrics):
        raise bad("METRICS must be a tuple of Metric")
    names: set[str] = set()
    for m in metrics:
        where = f"metric {m.name!r}"
        if not isinstance(m.name, str) or not _METRIC_NAME.match(m.name) or m.name in names:
            raise bad(f"{where}: a name of letters, digits, '_' and '.', declared once")
        names.add(m.name)
        if m.output not in outputs:
            raise bad(f"{where}: output {m.output!r} is not one of OUTPUTS {list(outputs)}")
        if not (isinstance(m.path, tuple) and m.path and all(isinstance(k, str) for k in m.path)):
            raise bad(f"{where}: path must be a non-empty tuple of keys")
        if m.better not in ("lower", "higher") or m.datasets not in ("reference", "all"):
            raise bad(f"{where}: better is 'lower' or 'higher', datasets 'reference' or 'all'")
        if not isinstance(m.unit, str) or not isinstance(m.default, int) or m.default < 0:
            raise bad(f"{where}: unit must be a string and default an int >= 0")
    return metrics


def _exports(module: ModuleType, bad: Any) -> tuple[Export, ...]:
    """The stage's ``EXPORTS``, checked: artifact inputs that match ``make``'s arguments."""
    exports = getattr(module, "EXPORTS", ())
    if not isinstance(exports, tuple) or not all(isinstance(e, Export) for e in exports):
        raise bad("EXPORTS must be a tuple of Export")
    names: set[str] = set()
    for e in exports:
        where = f"export {e.name!r}"
        if not isinstance(e.name, str) or not re.fullmatch(_NAME, e.name) or e.name in names:
            raise bad(f"{where}: a name of lower-case letters, digits and '_', declared once")
        names.add(e.name)
        if not (
            isinstance(e.files, tuple)
            and e.files
            and all(isinstance(f, str) and _FILE_NAME.match(f) for f in e.files)
        ):
            raise bad(f"{where}: files must be a non-empty tuple of plain file names")
        if "dataset" in e.inputs:
            raise bad(f"{where}: 'dataset' names the dataset, not an input")
        for arg, ref in e.inputs.items():
            if ref.startswith(PARAMS) and re.fullmatch(_NAME, ref.removeprefix(PARAMS)):
                continue
            try:
                parsed = InputRef.parse(ref)
            except SpecError as err:
                raise bad(f"{where}: input {arg}: {err}") from None
            if parsed.special is not None:
                raise bad(f"{where}: input {arg} must be an artifact, not {ref!r}")
        if not callable(e.make):
            raise bad(f"{where}: make must be a function")
        args = set(inspect.signature(e.make).parameters) - {"dataset"}
        if args != set(e.inputs):
            raise bad(
                f"{where}: make() takes {sorted(args)} but its inputs are "
                f"{sorted(e.inputs)} (and optionally dataset)"
            )
    return exports
