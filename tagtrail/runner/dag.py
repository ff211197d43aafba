"""The node graph: one node per (stage, dataset) that applies, edges from input references."""

from __future__ import annotations

import graphlib
from dataclasses import dataclass, field

from tagtrail.errors import SpecError
from tagtrail.runner.spec import Pipeline, did_you_mean
from tagtrail.runner.stage import InputRef


@dataclass(frozen=True, order=True)
class Node:
    stage: str
    dataset: str

    def __str__(self) -> str:
        return f"{self.stage} [{self.dataset}]"


@dataclass
class Graph:
    """Nodes in topological order, each with its resolved inputs (arg → ref, producing node)."""

    order: list[Node]
    inputs: dict[Node, dict[str, tuple[InputRef, Node | None]]] = field(default_factory=dict)
    skipped: dict[Node, str] = field(default_factory=dict)

    def deps(self, node: Node) -> set[Node]:
        return {n for _, n in self.inputs[node].values() if n is not None}

    def ancestors_and_self(self, targets: set[Node]) -> set[Node]:
        out: set[Node] = set()
        todo = list(targets)
        while todo:
            n = todo.pop()
            if n not in out:
                out.add(n)
                todo.extend(self.deps(n))
        return out


def inputs_for(pipe: Pipeline, stage: str, dataset: str) -> dict[str, InputRef]:
    """The stage's declared inputs with the dataset's rewiring applied."""
    spec = pipe.stages[stage]
    rewired = pipe.datasets[dataset].inputs
    return {
        arg: InputRef.parse(rewired[f"{stage}.{arg}"]) if f"{stage}.{arg}" in rewired else ref
        for arg, ref in spec.inputs.items()
    }


def build_graph(pipe: Pipeline) -> Graph:
    """Resolve every (stage, dataset) node; nodes whose inputs cannot exist are skipped."""
    graph = Graph(order=[])
    resolved: dict[Node, dict[str, tuple[InputRef, Node | None]] | None] = {}
    visiting: set[Node] = set()

    def resolve(node: Node) -> bool:
        if node in resolved:
            return resolved[node] is not None
        if node in visiting:
            raise SpecError(f"{pipe.path}: input wiring has a cycle through {node}")
        visiting.add(node)
        spec = pipe.stages[node.stage]
        why = None
        ins: dict[str, tuple[InputRef, Node | None]] = {}
        if spec.scope == "query" and node.dataset == pipe.reference:
            why = "runs on query datasets only"
        for arg, ref in inputs_for(pipe, node.stage, node.dataset).items():
            if why:
                break
            if ref.special == "ground_truth" and pipe.datasets[node.dataset].ground_truth is None:
                why = "dataset has no ground truth"
            elif ref.special:
                ins[arg] = (ref, None)
            else:
                assert ref.stage is not None and ref.output is not None
                if ref.stage not in pipe.stages:
                    raise SpecError(
                        f"stage {node.stage}: input {arg} refers to unknown stage {ref.stage!r}"
                        f"{did_you_mean(ref.stage, pipe.stages)}"
                    )
                if ref.output not in pipe.stages[ref.stage].outputs:
                    raise SpecError(
                        f"stage {node.stage}: input {arg} refers to {ref}, but {ref.stage} "
                        f"outputs {list(pipe.stages[ref.stage].outputs)}"
                    )
                up = Node(ref.stage, pipe.reference if ref.from_reference else node.dataset)
                if not resolve(up):
                    why = f"needs {up}, which does not run ({graph.skipped[up]})"
                ins[arg] = (ref, up)
        visiting.discard(node)
        resolved[node] = None if why else ins
        if why:
            graph.skipped[node] = why
        return why is None

    nodes = [Node(s, d) for d in pipe.datasets for s in pipe.stages]
    for n in nodes:
        resolve(n)
    live = {n: ins for n, ins in resolved.items() if ins is not None}
    sorter = graphlib.TopologicalSorter(
        {n: {u for _, u in ins.values() if u is not None} for n, ins in live.items()}
    )
    rank = {n: i for i, n in enumerate(nodes)}
    sorter.prepare()
    while sorter.is_active():
        ready = sorted(sorter.get_ready(), key=rank.__getitem__)
        graph.order.extend(ready)
        sorter.done(*ready)
    graph.inputs = {n: live[n] for n in graph.order}
    return graph


def select(pipe: Pipeline, graph: Graph, stages: list[str]) -> set[Node]:
    """The nodes to run for ``tagtrail run STAGE…`` (all when empty): targets + ancestors."""
    for s in stages:
        if s not in pipe.stages:
            raise SpecError(f"unknown stage {s!r}{did_you_mean(s, pipe.stages)}")
    targets = {n for n in graph.order if not stages or n.stage in stages}
    return graph.ancestors_and_self(targets)


def mermaid(graph: Graph) -> str:
    lines = ["flowchart LR"]
    ids = {n: f"n{i}" for i, n in enumerate(graph.order)}
    for n in graph.order:
        lines.append(f'  {ids[n]}["{n.stage}<br/>{n.dataset}"]')
    for n in graph.order:
        for u in sorted(graph.deps(n)):
            lines.append(f"  {ids[u]} --> {ids[n]}")
    return "\n".join(lines)


def text(graph: Graph) -> str:
    lines = []
    for n in graph.order:
        deps = ", ".join(str(u) for u in sorted(graph.deps(n)))
        lines.append(f"{n}" + (f"  <- {deps}" if deps else "  <- source"))
    for n, why in sorted(graph.skipped.items()):
        lines.append(f"({n} skipped: {why})")
    return "\n".join(lines)
