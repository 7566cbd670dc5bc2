"""The stage graph: topological order, cycle detection, Mermaid and Graphviz renderings."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from runner.config import Pipeline


class CycleError(Exception):
    """The graph has a cycle; ``cycle`` lists its nodes in order (each depends on the previous,
    the first on the last)."""

    def __init__(self, cycle: list[str]):
        self.cycle = cycle
        super().__init__(" -> ".join([*cycle, cycle[0]]))


def topological_order(nodes: list[str], edges: list[tuple[str, str]]) -> list[str]:
    """Nodes ordered so that every edge ``(a, b)`` has ``a`` before ``b``; ties keep the order of
    ``nodes`` (the file's order), so the result is deterministic.

    Raises
    ------
    CycleError
        Naming one cycle.
    """
    remaining = {n: sum(1 for a, b in edges if b == n) for n in nodes}
    order: list[str] = []
    while len(order) < len(nodes):
        ready = next((n for n in nodes if remaining.get(n) == 0), None)
        if ready is None:
            raise CycleError(_find_cycle([n for n in nodes if n in remaining], edges))
        order.append(ready)
        del remaining[ready]
        for a, b in edges:
            if a == ready:
                remaining[b] -= 1
    return order


def _find_cycle(nodes: list[str], edges: list[tuple[str, str]]) -> list[str]:
    """One cycle among ``nodes`` (all of which lie on or downstream of a cycle)."""
    upstream = {n: [a for a, b in edges if b == n and a in nodes] for n in nodes}
    path, node = [], nodes[0]
    while node not in path:
        path.append(node)
        node = upstream[node][0]
    cycle = path[path.index(node) :][::-1]
    first = min(range(len(cycle)), key=lambda i: nodes.index(cycle[i]))  # start where the file does
    return cycle[first:] + cycle[:first]


def to_mermaid(pipeline: Pipeline) -> str:
    """A Mermaid flowchart: pipeline inputs as rounded nodes, stages as boxes, edges labelled
    with the port they feed."""
    lines = ["flowchart LR"]
    for name, decl in pipeline.inputs.items():
        lines.append(f'    in_{_safe(name)}(["{name}: {decl.type}"])')
    for name, stage in pipeline.stages.items():
        lines.append(f'    st_{_safe(name)}["{name}<br/>{stage.uses}"]')
    for name, stage in pipeline.stages.items():
        for port, ref in stage.inputs.items():
            source = f"st_{_safe(ref.stage)}" if ref.stage else f"in_{_safe(ref.port)}"
            label = f"{ref.port} → {port}" if ref.stage else port
            lines.append(f'    {source} -->|"{label}"| st_{_safe(name)}')
    return "\n".join(lines) + "\n"


def to_dot(pipeline: Pipeline) -> str:
    """A Graphviz digraph of the same graph as :func:`to_mermaid`."""
    lines = ["digraph pipeline {", "    rankdir=LR;", "    node [shape=box];"]
    for name, decl in pipeline.inputs.items():
        lines.append(f'    "in:{name}" [shape=ellipse, label="{name}: {decl.type}"];')
    for name, stage in pipeline.stages.items():
        lines.append(f'    "{name}" [label="{name}\\n{stage.uses}"];')
    for name, stage in pipeline.stages.items():
        for port, ref in stage.inputs.items():
            source = ref.stage if ref.stage else f"in:{ref.port}"
            label = f"{ref.port} → {port}" if ref.stage else port
            lines.append(f'    "{source}" -> "{name}" [label="{label}"];')
    lines.append("}")
    return "\n".join(lines) + "\n"


def _safe(name: str) -> str:
    return name.replace("-", "_")
