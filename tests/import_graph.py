"""What the import tests share: a package's modules by dotted name, and the check that no
module of a graph imports itself through others."""

from __future__ import annotations

from pathlib import Path


def modules_below(root: Path) -> dict[str, Path]:
    """Dotted names below the package folder `root` ("" for its __init__.py, "a" for
    a/__init__.py) of every module in it."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        out[".".join(p for p in parts if p != "__init__")] = path
    return out


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
