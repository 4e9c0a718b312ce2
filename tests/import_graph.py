"""A check the import tests share: no module of a graph imports itself through others."""

from __future__ import annotations


def assert_no_cycle(graph: dict[str, set[str]]) -> None:
    """AssertionError naming the first cycle found in `graph` (module -> the modules it
    imports); an empty name (the package root, imported first by everything) is not followed."""
    done: set[str] = set()
    active: list[str] = []

    def visit(node: str) -> None:
        if node in active:
            raise AssertionError("import cycle: " + " -> ".join(active[active.index(node):] + [node]))
        if node in done:
            return
        active.append(node)
        for target in sorted(graph[node]):
            if target:
                visit(target)
        active.pop()
        done.add(node)

    for module in graph:
        visit(module)
