"""The runtime imports light and apart from the tooling: `import diffsheg_core` and everything
generation runs need only the standard library, numpy and the wheels the add-on bundles; the
runtime never imports the training tooling; its modules import each other without cycles."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "diffsheg_core"
TORCH_LAYER = {"model", "export", "devices"}  # the networks as torch modules, their ONNX export
HEAVY = ("torch", "scipy", "librosa", "numba", "transformers", "onnx", "matplotlib", "tqdm")
BUNDLED = ("onnxruntime", "soundfile", "soxr", "safetensors")


def runtime_modules() -> dict[str, Path]:
    """Dotted names (below diffsheg_core) of the runtime's modules: all but the tooling."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        if parts[0] == "training" or parts[0] in TORCH_LAYER:
            continue
        out[".".join(p for p in parts if p != "__init__") or ""] = path
    return out


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
        assert not [m for m in everywhere if m.startswith("diffsheg_core.training")], module
        top = imports(path, module, top_level_only=True)
        assert not [m for m in top if m.split(".")[0] in HEAVY], (module, top)
        assert not [m for m in top if m.removeprefix("diffsheg_core.") in TORCH_LAYER], (module, top)


def test_the_torch_layer_never_imports_the_tooling():
    for name in TORCH_LAYER:
        found = imports(PACKAGE / f"{name}.py", name, top_level_only=False)
        assert not [m for m in found if m.startswith("diffsheg_core.training")], name


def test_runtime_modules_import_each_other_without_cycles():
    modules = runtime_modules()
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
    done, active = set(), []

    def visit(node: str) -> None:
        if node in active:
            raise AssertionError("import cycle: " + " -> ".join(active[active.index(node):] + [node]))
        if node in done:
            return
        active.append(node)
        for target in sorted(graph[node]):
            if target:  # everything imports the package root first; the root imports light
                visit(target)
        active.pop()
        done.add(node)

    for module in graph:
        visit(module)


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
