"""The add-on's layers, read from its paths: ui/ (panel, properties, preferences, operators,
widgets) on top of features/ (generate, regenerate, live, strips, exports) on top of scene/
(bake, keying, takes, retarget, ...), with environment.py (is the runtime, the GPU support,
the microphone there) beside scene/. Every import, inside functions too, goes down: nothing
below ui/ imports it, scene/ imports neither ui/ nor features/, environment.py imports no
other module of the add-on, and no module imports itself through a cycle. The studio
driver sits outside the add-on, beside batch_render.py. No bpy needed: the files are parsed."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from import_graph import assert_no_cycle, modules_below

REPO = Path(__file__).resolve().parents[1]
ADDON = REPO / "blender_addon"
PACKAGE = "blender_addon"


MODULES = modules_below(ADDON)


def imported(module: str) -> set[str]:
    """The add-on's modules `module` imports anywhere in its file (relative imports resolved;
    `from .scene import takes` is scene.takes)."""
    path = MODULES[module]
    package = module.split(".") if module else []
    if path.name != "__init__.py":
        package = package[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                base = (node.module or "").split(".")
            else:
                assert node.level - 1 <= len(package), (module, ast.dump(node))
                base = package[: len(package) - (node.level - 1)] + (node.module.split(".") if node.module else [])
                base = [PACKAGE, *base]
            names = [".".join([*base, alias.name]) for alias in node.names] + [".".join(base)]
        else:
            continue
        for name in names:
            if name != PACKAGE and not name.startswith(PACKAGE + "."):
                continue
            inner = name[len(PACKAGE) + 1:]
            while inner and inner not in MODULES:  # a name imported from a module: the module
                inner = inner.rpartition(".")[0]
            found.add(inner)
    found.discard(module)
    return found


def layer(module: str) -> str:
    return module.split(".")[0] if "." in module else module


def test_the_layers_are_the_folders():
    assert {layer(m) for m in MODULES} == {"", "ui", "features", "scene", "environment"}
    assert {"ui.panel", "ui.properties", "ui.preferences", "ui.operators", "ui.widgets"} <= set(MODULES)
    assert {"features.generate", "features.regenerate", "features.live", "features.strips",
            "features.exports"} <= set(MODULES)
    assert {"scene.bake", "scene.keying", "scene.takes", "scene.retarget", "scene.preset", "scene.feet",
            "scene.visemes", "scene.sound", "scene.report"} <= set(MODULES)
    assert "studio" not in MODULES and (REPO / "studio.py").is_file()  # beside batch_render.py


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_go_down_the_layers(module):
    below = {
        "": {"ui"},                                      # __init__.py registers the UI, nothing else
        "ui": {"ui", "features", "scene", "environment"},
        "features": {"features", "scene", "environment"},
        "scene": {"scene"},
        "environment": set(),
    }[layer(module)]
    wrong = sorted(m for m in imported(module) if layer(m) not in below and m not in ("ui", "features", "scene"))
    assert not wrong, f"{module} imports {wrong}"


def test_no_module_imports_itself_through_a_cycle():
    graph = {m: imported(m) for m in MODULES}
    assert_no_cycle(graph)


def test_the_add_on_never_imports_its_drivers():
    """batch_render.py and studio.py use the add-on; the add-on never imports them."""
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        names = {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
        names |= {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.level == 0}
        assert not names & {"studio", "batch_render"}, module
