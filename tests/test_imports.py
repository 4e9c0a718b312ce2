"""The runtime imports light and apart from the tooling: `import diffsheg_core` and everything
generation runs need only the standard library, numpy and the wheels the add-on bundles; the
runtime never imports the training tooling; torch (and transformers) are imported by the torch
layer (diffsheg_core/torch_layer/) and the tooling alone, and the runtime reaches the torch
layer only inside functions, when torch is asked for; its modules import each other without
cycles."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from import_graph import assert_no_cycle, modules_below

PACKAGE = Path(__file__).resolve().parents[1] / "diffsheg_core"
TORCH_LAYER = "torch_layer"  # the modules that import torch (the tooling aside): networks, backend, HuBERT...
TOOLING = "training"
TORCH_PACKAGES = ("torch", "transformers")  # imported by the torch layer and the tooling alone
HEAVY = ("torch", "scipy", "librosa", "numba", "transformers", "onnx", "matplotlib", "tqdm")
BUNDLED = ("onnxruntime", "soundfile", "soxr", "safetensors", "threadpoolctl")
RUNTIME_ENTRY_POINTS = ("pipeline", "live.session", "runtime.backends", "checkpoints", "audio")


def runtime_modules() -> dict[str, Path]:
    """The runtime's modules: all but the tooling and the torch layer."""
    return {m: p for m, p in modules_below(PACKAGE).items() if m.split(".")[0] not in (TOOLING, TORCH_LAYER)}


def torch_layer_modules() -> dict[str, Path]:
    return {m: p for m, p in modules_below(PACKAGE).items() if m.split(".")[0] == TORCH_LAYER}


def imports(path: Path, module: str, top_level_only: bool) -> set[str]:
    """Absolute names `path` imports (relative imports resolved against `module`)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    package = ["diffsheg_core"] + (module.split(".") if module else [])
    if path.name != "__init__.py":
        package = package[:-1]
    found = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                found.add(node.module)
                continue
            base = package[: len(package) - (node.level - 1)]
            target = ".".join(base + ([node.module] if node.module else []))
            found.add(target)
            if not node.module:  # from . import x
                found.update(f"{target}.{alias.name}" for alias in node.names)
    return found


def test_the_runtime_never_imports_the_tooling_or_the_torch_layer_at_import_time():
    for module, path in runtime_modules().items():
        everywhere = imports(path, module, top_level_only=False)
        assert not [m for m in everywhere if m.startswith(f"diffsheg_core.{TOOLING}")], module
        top = imports(path, module, top_level_only=True)
        assert not [m for m in top if m.split(".")[0] in HEAVY], (module, top)
        assert not [m for m in top if m.startswith(f"diffsheg_core.{TORCH_LAYER}")], (module, top)


def _imported_by_name(path: Path) -> set[str]:
    """Modules `path` imports through importlib.import_module("...") or __import__("...")."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            called = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", None)
            if called in ("import_module", "__import__"):
                found.add(node.args[0].value)
    return found


def test_only_the_torch_layer_and_the_tooling_import_torch():
    """Anywhere in a module, inside functions too: the rest of the package reaches torch only
    through the torch layer (and may ask importlib.util.find_spec whether torch is there)."""
    for module, path in runtime_modules().items():
        found = imports(path, module, top_level_only=False) | _imported_by_name(path)
        assert not [m for m in found if m.split(".")[0] in TORCH_PACKAGES], (module, found)
    for module, path in torch_layer_modules().items():  # and the layer holds nothing else
        if path.name != "__init__.py":
            assert "torch" in {m.split(".")[0] for m in imports(path, module, top_level_only=True)}, module


def test_the_torch_layer_never_imports_the_tooling():
    for module, path in torch_layer_modules().items():
        found = imports(path, module, top_level_only=False)
        assert not [m for m in found if m.startswith(f"diffsheg_core.{TOOLING}")], module


def test_runtime_modules_import_each_other_without_cycles():
    modules = {**runtime_modules(), **torch_layer_modules()}
    graph = {}
    for module, path in modules.items():
        targets = set()
        for name in imports(path, module, top_level_only=True):
            inner = name.removeprefix("diffsheg_core").lstrip(".")
            while inner and inner not in modules:
                inner = inner.rpartition(".")[0]
            if (inner in modules) and inner != module and name.startswith("diffsheg_core"):
                targets.add(inner)
        graph[module] = targets
    assert_no_cycle(graph)


BLOCK = """
import sys
for name in {names!r}:
    sys.modules[name] = None  # makes `import name` fail, as where it is not installed
"""


def run_python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          cwd=PACKAGE.parent)


def test_import_diffsheg_core_needs_only_numpy():
    code = BLOCK.format(names=HEAVY + BUNDLED) + """
import diffsheg_core
from diffsheg_core import Motion, DiffshegError, generate
import diffsheg_core.errors, diffsheg_core.motion, diffsheg_core.rigs, diffsheg_core.rotations
print("ok", sorted(m for m in sys.modules if m.split(".")[0] in {names!r} and sys.modules[m]))
""".format(names=HEAVY + BUNDLED)
    result = run_python(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok []"


def test_importing_the_runtime_leaves_torch_out():
    """Every module of the runtime, the entry points among them, imported where torch and
    transformers are installed: neither is loaded."""
    modules = [m for m in runtime_modules() if m and m != "__main__"]
    assert set(RUNTIME_ENTRY_POINTS) <= set(modules)
    code = f"""
import importlib, sys
for name in {modules!r}:
    importlib.import_module("diffsheg_core." + name)
print("ok", sorted(m for m in sys.modules if m.split(".")[0] in {TORCH_PACKAGES!r}))
"""
    result = run_python(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok []"


@pytest.fixture(scope="module")
def short_speech(data_dir, tmp_path_factory):
    import soundfile as sf

    samples, rate = sf.read(data_dir / "audio" / "2_scott_0_4_4.wav", dtype="float32")
    path = tmp_path_factory.mktemp("speech") / "three_seconds.wav"
    sf.write(path, samples[: 3 * rate], rate)
    return path


def test_generation_with_the_bundled_model_never_imports_torch_scipy_or_librosa(short_speech, tmp_path):
    code = BLOCK.format(names=HEAVY) + f"""
import diffsheg_core
from diffsheg_core.bvh import write_bvh
from diffsheg_core.motion import resample_motion, write_arkit_json
motion = diffsheg_core.generate({str(short_speech)!r}, seed=1, steps=3)
resampled = resample_motion(motion, 24.0)
write_bvh(motion, {str(tmp_path / "m.bvh")!r}); write_arkit_json(motion, {str(tmp_path / "m.json")!r})
print(motion.meta["backend"], motion.n_frames, resampled.n_frames)
"""
    result = run_python(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["onnx", "45", "72"]


def test_an_official_checkpoint_without_torch_says_what_to_install(tmp_path):
    fake = tmp_path / "beat_ckpt.pth"
    fake.write_bytes(b"PK\x03\x04 a torch zip pickle would follow")
    code = BLOCK.format(names=("torch",)) + f"""
from diffsheg_core.checkpoints import load_model
from diffsheg_core.errors import CheckpointError
try:
    load_model({str(fake)!r})
except CheckpointError as exc:
    print(exc)
"""
    result = run_python(code)
    assert result.returncode == 0, result.stderr
    assert "need torch" in result.stdout and "pip install torch==2.13.0" in result.stdout
    assert "Install GPU support" in result.stdout


def test_tooling_commands_without_torch_say_what_to_install():
    code = BLOCK.format(names=("torch",)) + """
from diffsheg_core.cli import main
raise SystemExit(main(["train", "--config", "train.toml"]))
"""
    result = run_python(code)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert "error: 'train' needs the tooling of diffsheg_core" in result.stderr
    assert "no module named 'torch'" in result.stderr and 'pip install -e ".[train]"' in result.stderr
