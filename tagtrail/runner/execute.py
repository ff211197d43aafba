"""Plan and execute a pipeline: cache keys, make-style reruns, parallel stages, the run log."""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from tagtrail.errors import SourceError, StageError, TagtrailError, storage_error
from tagtrail.io.layouts import atomic_write_text
from tagtrail.io.sources import source_kind
from tagtrail.runner.cache import (
    SourceHasher,
    Store,
    canonical_json,
    pretty_json,
    sha256_text,
)
from tagtrail.runner.dag import Graph, Node, build_graph, select
from tagtrail.runner.executors import (
    NodeTask,
    open_executor,
    run_node,
    run_remote,
    timed_call,
)
from tagtrail.runner.inputs import reader_closure
from tagtrail.runner.paths import RUN_LOG, check_project, clear_obstacles, inside
from tagtrail.runner.spec import Pipeline
from tagtrail.schemas.artifacts import VERSION as ARTIFACT_SCHEMA_VERSION

log = logging.getLogger("tagtrail.runner")


@dataclass
class NodeState:
    """What happened (or would happen) to one node: ``cached``, ``stale``, ``ran``, ``failed``."""

    stage: str
    dataset: str
    status: str
    reason: str = ""
    key: str | None = None
    seconds: float = 0.0
    rows: int | None = None

    def line(self) -> str:
        node = f"{self.stage} [{self.dataset}]"
        if self.status == "cached":
            return f"{node:<28} cached  {(self.key or '')[:12]}"
        rows = f"  {self.rows:,} rows" if self.rows is not None else ""
        took = f"  {self.seconds:6.2f}s" if self.status in ("ran", "failed") else ""
        return f"{node:<28} {self.status:<7}{took}{rows}  ({self.reason})"


MAX_VALUE = 40  # characters of one value in a change line; a mapping is summarised
MAX_DIFF = 200  # characters of the whole list of changed parameters


def _short(v: Any) -> str:
    """A value for a change line: a mapping (a known-poses block, tag sizes) by its keys, any
    value cut to :data:`MAX_VALUE` characters."""
    text = "{" + ", ".join(map(str, v)) + "}" if isinstance(v, dict) else repr(v)
    return text if len(text) <= MAX_VALUE else text[: MAX_VALUE - 1] + "…"


def _param_diff(
    old: dict[str, Any], new: dict[str, Any], prefix: str = "", limit: int = MAX_DIFF
) -> str:
    """The changed parameters, nested ones by their dotted name (a file's tag sizes or known
    poses: ``tag_sizes_from.sizes.2: 0.16 → 0.2``, not the whole block twice); each value at
    most :data:`MAX_VALUE` characters, the list at most ``limit`` (then ``… and N more``)."""
    parts = _param_changes(old, new, prefix)
    shown: list[str] = []
    for i, part in enumerate(parts):
        rest = len(parts) - i - 1
        tail = f", … and {rest} more" if rest else ""
        if len(", ".join([*shown, part])) + len(tail) > limit and shown:
            return ", ".join(shown) + f", … and {len(parts) - i} more"
        shown.append(part)
    return ", ".join(shown)


def _param_changes(old: dict[str, Any], new: dict[str, Any], prefix: str) -> list[str]:
    parts = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            parts += _param_changes(a, b, f"{prefix}{k}.")
        else:
            parts.append(f"{prefix}{k}: {_short(a)} → {_short(b)}")
    return parts


def _check_shape(source: Path) -> None:
    """Refuse, before hashing it, a source folder that is no recording and holds folders (``/usr``
    or a home folder would be hashed for minutes): the one-line reason of ``source_kind``."""
    if source.is_dir():
        try:
            source_kind(source)
        except SourceError:
            if any(e.is_dir() for e in os.scandir(source)):
                raise


def _reader_changes(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """Why a node is stale because the code that reads one of its special inputs changed:
    ``code changed: tagtrail.io.layouts (reads source)``."""
    out = []
    for special in sorted(set(old) | set(new)):
        a, b = old.get(special) or {}, new.get(special) or {}
        names = sorted(m for m in set(a) | set(b) if a.get(m) != b.get(m))
        if names and a and b:
            out.append(f"code changed: {', '.join(names)} (reads {special})")
        elif names:  # a record from before readers were part of the key, or no reader now
            out.append(f"code changed: the reader of {special}")
    return out


class Runner:
    """Executes a validated pipeline against its artifact store.

    ``executor``: ``local`` (``jobs`` nodes at once in threads) or ``dask`` (``jobs`` local
    worker processes, or the workers of ``scheduler``; see :mod:`tagtrail.runner.executors`)."""

    def __init__(
        self,
        pipe: Pipeline,
        jobs: int = 1,
        echo: Callable[[str], None] | None = None,
        executor: str = "local",
        scheduler: str | None = None,
    ) -> None:
        self.pipe = pipe
        self.graph: Graph = build_graph(pipe)
        self.store = Store(pipe.artifacts)
        self.hasher = SourceHasher(pipe.artifacts / "sources.json")
        self.jobs = max(1, jobs)
        self.echo = echo or (lambda s: None)
        self.executor = executor
        self.scheduler = scheduler
        self._source_fp: dict[tuple[str, str], str] = {}

    # --- keys -------------------------------------------------------------------------------

    def _special_fp(self, dataset: str, special: str) -> str:
        memo = (dataset, special)
        if memo not in self._source_fp:
            ds = self.pipe.datasets[dataset]
            if special in ("source", "dataset"):
                _check_shape(ds.source)
                doc = {
                    "source": self.hasher.hash(ds.source),
                    "topics": ds.topics.model_dump(mode="json"),
                    "camera": self.hasher.hash_camera(ds.camera) if ds.camera else None,
                }
                self._source_fp[memo] = sha256_text(canonical_json(doc))
            else:
                assert ds.ground_truth is not None
                self._source_fp[memo] = self.hasher.hash(ds.ground_truth)
        return self._source_fp[memo]

    def record_for(self, node: Node, keys: dict[Node, str]) -> dict[str, Any] | None:
        """The cache record of ``node`` given its upstream keys, or None if one is unknown."""
        spec = self.pipe.stages[node.stage]
        inputs: dict[str, str] = {}
        readers: dict[str, dict[str, str]] = {}
        for arg, (ref, up) in self.graph.inputs[node].items():
            if up is None:
                assert ref.special is not None
                inputs[arg] = self._special_fp(node.dataset, ref.special)
                if reader := reader_closure(ref.special):
                    readers[ref.special] = reader
                continue
            if up not in keys:
                return None
            manifest = self.store.lookup(up.stage, keys[up])
            if manifest is None:
                return None
            inputs[arg] = manifest["outputs"][ref.output]["sha256"]
        record = {
            "stage": node.stage,
            "code": spec.code_fingerprint,
            "code_modules": spec.code_modules,
            "schema": ARTIFACT_SCHEMA_VERSION,
            "params": self.pipe.params_for(node.stage, node.dataset).key_dump(),
            "inputs": inputs,
        }
        if readers:  # the code that reads a source or ground truth: part of the key
            record["readers"] = readers
        return record

    def why_stale(self, node: Node, record: dict[str, Any]) -> str:
        last = self.store.last_record(node.dataset, node.stage)
        if last is None:
            return "never run"
        reasons = []
        if last.get("code") != record["code"]:
            old, new = last.get("code_modules") or {}, record["code_modules"]
            names = sorted(m for m in set(old) | set(new) if old.get(m) != new.get(m))
            stage_module = self.pipe.stages[node.stage].module.__name__
            shown = ", ".join(stage_module if m == "." else m for m in names)
            reasons.append(f"code changed: {shown}" if old and shown else "code changed")
        reasons += _reader_changes(last.get("readers") or {}, record.get("readers") or {})
        if last.get("params") != record["params"]:
            reasons.append("params changed: " + _param_diff(last["params"], record["params"]))
        old_inputs = last.get("inputs", {})
        changed = [a for a in record["inputs"] if old_inputs.get(a) != record["inputs"][a]]
        if changed:
            refs = self.graph.inputs[node]
            reasons.append("input changed: " + ", ".join(f"{a} ({refs[a][0]})" for a in changed))
        if last.get("schema") != record["schema"]:
            reasons.append("schema version changed")
        return "; ".join(reasons) or "artifact missing or corrupt"

    # --- status / dry run -------------------------------------------------------------------

    def plan(self, stages: list[str] | None = None, force: bool = False) -> list[NodeState]:
        """What ``run`` would do, without running anything (``status``, ``--dry-run``)."""
        chosen = select(self.pipe, self.graph, stages or [])
        keys: dict[Node, str] = {}
        states = []
        for node in (n for n in self.graph.order if n in chosen):
            record = self.record_for(node, keys)
            if record is None:
                ups = sorted(str(u) for u in self.graph.deps(node) if u not in keys)
                states.append(
                    NodeState(
                        node.stage, node.dataset, "stale", f"upstream out of date: {', '.join(ups)}"
                    )
                )
                continue
            key = sha256_text(canonical_json(record))
            if not force and self.store.lookup(node.stage, key) is not None:
                keys[node] = key
                states.append(NodeState(node.stage, node.dataset, "cached", "up to date", key))
            else:
                why = "forced" if force else self.why_stale(node, record)
                states.append(NodeState(node.stage, node.dataset, "stale", why, key))
        return states  # writes nothing (`status`, `show`): the hashes are saved by `run`

    # --- run --------------------------------------------------------------------------------

    def _task(
        self, node: Node, key: str, record: dict[str, Any], keys: dict[Node, str]
    ) -> NodeTask:
        """What an executor needs to run ``node`` (picklable, for workers in other processes)."""
        specials: dict[str, str] = {}
        upstream: dict[str, tuple[str, str, str]] = {}
        for arg, (ref, up) in self.graph.inputs[node].items():
            if up is None:
                assert ref.special is not None
                specials[arg] = ref.special
            else:
                assert ref.output is not None
                upstream[arg] = (up.stage, keys[up], ref.output)
        module = self.pipe.stages[node.stage].module
        return NodeTask(
            stage=node.stage,
            dataset=node.dataset,
            module=module.__name__,
            module_file=getattr(module, "__file__", None),
            params=self.pipe.params_for(node.stage, node.dataset),
            config=self.pipe.datasets[node.dataset],
            key=key,
            record=record,
            specials=specials,
            upstream=upstream,
            artifacts=self.store.root.resolve(),
            log_level=logging.getLogger("tagtrail").getEffectiveLevel(),
        )

    def _submit(self, pool: cf.Executor, task: NodeTask) -> cf.Future[tuple[int | None, float]]:
        """Submit a node; its future gives (rows written, seconds the node took to compute)."""
        if getattr(pool, "remote", False):  # another process: it rebuilds the stage from names
            return pool.submit(timed_call, run_remote, task)
        return pool.submit(timed_call, run_node, task, self.pipe.stages[task.stage], self.store)

    def run(self, stages: list[str] | None = None, force: bool = False) -> list[NodeState]:
        """Bring the selected nodes up to date; raise the first failure after others finish."""
        chosen = select(self.pipe, self.graph, stages or [])
        order = [n for n in self.graph.order if n in chosen]
        keys: dict[Node, str] = {}
        states: dict[Node, NodeState] = {}
        failure: BaseException | None = None
        check_project(self.pipe, ("artifacts",))  # before any work: no symlink leads out
        with (
            self.store.lock(),
            open_executor(
                self.executor, self.jobs, self.scheduler, self.echo, self.store.root.resolve()
            ) as pool,
        ):
            clear_obstacles(self.pipe, ("artifacts",))
            running: dict[cf.Future[tuple[int | None, float]], tuple[Node, NodeState, float]] = {}
            pending = list(order)
            while pending or running:
                progressed = True
                while progressed and failure is None:
                    progressed = False
                    for node in list(pending):
                        if not self.graph.deps(node) <= set(keys):
                            continue
                        pending.remove(node)
                        progressed = True
                        record = self.record_for(node, keys)
                        assert record is not None
                        key = sha256_text(canonical_json(record))
                        if not force and self.store.lookup(node.stage, key) is not None:
                            keys[node] = key
                            st = NodeState(node.stage, node.dataset, "cached", "up to date", key)
                            states[node] = st
                            self.echo(st.line())
                            continue
                        why = "forced" if force else self.why_stale(node, record)
                        st = NodeState(node.stage, node.dataset, "ran", why, key)
                        t0 = time.perf_counter()  # a failure's seconds (no timing comes back)
                        fut = self._submit(pool, self._task(node, key, record, keys))
                        running[fut] = (node, st, t0)
                if not running:
                    break
                done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
                for fut in done:
                    node, st, t0 = running.pop(fut)
                    st.seconds = time.perf_counter() - t0
                    states[node] = st
                    try:
                        st.rows, st.seconds = fut.result()
                        keys[node] = st.key or ""
                    except Exception as err:  # noqa: BLE001 - reported below, with context
                        # (Ctrl-C is no stage's failure: KeyboardInterrupt goes straight up)
                        st.status = "failed"
                        st.reason = f"{type(err).__name__}: {err}"
                        failure = failure or self._wrap(node, err)
                    self.echo(st.line())
            self.hasher.save()  # under the lock: another run's clean-up never sees its temp
            result = [states[n] for n in order if n in states]
            self._save_run_log(result)
        if failure is not None:
            raise failure
        return result

    def _wrap(self, node: Node, err: BaseException) -> BaseException:
        if isinstance(err, TagtrailError) and not isinstance(err, StageError):
            new = type(err)(f"{node}: {err}")
            new.__cause__ = err
            return new
        if isinstance(err, OSError) and (refused := storage_error(err, str(node))) is not None:
            refused.__cause__ = err
            return refused
        wrapped = StageError(node.stage, node.dataset, err)
        name = f"error-{time.strftime('%Y%m%d-%H%M%S')}-{node.stage}-{node.dataset}.log"
        try:
            path = inside(self.pipe.artifacts / "logs", name)
            atomic_write_text(path, "".join(traceback.format_exception(err)))
            wrapped.log_path = path  # type: ignore[attr-defined]
        except OSError:
            pass  # the failure itself is still reported, without its log
        return wrapped

    def _save_run_log(self, states: list[NodeState]) -> None:
        atomic_write_text(
            inside(self.pipe.artifacts / "runs", RUN_LOG), pretty_json([asdict(s) for s in states])
        )

    def key_of(self, stage: str, dataset: str) -> str | None:
        """The key of the up-to-date artifact of a node, if there is one (for ``show``)."""
        target = Node(stage, dataset)
        if target not in self.graph.inputs:
            return None
        for st in self.plan([stage]):
            if (st.stage, st.dataset) == (stage, dataset):
                return st.key if st.status == "cached" else None
        return None
