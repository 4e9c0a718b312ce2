"""build_addon.py: one extension zip per platform with the runtime's wheels and a valid
manifest, a legacy zip; the built zips install and enable in headless Blender (bpy) and
register the panel and the operator, using the diffsheg_core bundled in the zip."""

from __future__ import annotations

import ast
import hashlib
import importlib.util
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from addon_fixtures import REPO, bpy, exit_before_blender_teardown  # noqa: F401 (fixture)

import build_addon

tomllib = pytest.importorskip("tomllib")  # Python 3.11+, as bpy

INSTALL = r"""
import json, os, sys, bpy, addon_utils
mode, path = sys.argv[1], sys.argv[2]
if mode == "extension":
    bpy.ops.extensions.package_install_files(filepath=path, repo="user_default", enable_on_install=True)
    module = "bl_ext.user_default.diffsheg"
else:
    bpy.ops.preferences.addon_install(filepath=path)
    module = "diffsheg"
    addon_utils.enable(module, default_set=True)
import diffsheg_core
print("RESULT", json.dumps({
    "enabled": module in bpy.context.preferences.addons.keys(),
    "panel": hasattr(bpy.types, "DIFFSHEG_PT_generate"),
    "operator": bpy.ops.diffsheg.generate.get_rna_type().identifier,
    "settings": hasattr(bpy.context.scene, "diffsheg"),
    "core": diffsheg_core.__file__,
    "presets": sys.modules[module + ".scene.preset"].available_presets(),
    "wheels_dir": next((p for p in sys.path if os.path.isdir(os.path.join(p, "onnxruntime"))
                        and "extensions" in p), ""),
}), flush=True)
os._exit(0)  # skip Blender's exit-time teardown: the bpy modules before 5.0 crash or hang in it
"""


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    return build_addon.build(tmp_path_factory.mktemp("dist"))


def test_one_zip_per_platform_and_a_legacy_zip(built):
    v = build_addon.version()
    assert {p: z.name for p, z in built.items()} == {
        **{p: f"diffsheg-{v}-{p}.zip" for p in ("windows-x64", "macos-arm64", "macos-x64", "linux-x64")},
        "legacy": f"diffsheg-{v}-legacy.zip"}


def _tooling_or_cache(name: str) -> bool:
    return ("__pycache__" in name or name.endswith(".pyc") or "diffsheg_core/training/" in name
            or name.endswith("diffsheg_core/torch_layer/export.py"))


@pytest.mark.parametrize("platform", list(build_addon.PLATFORMS))
def test_extension_zip_holds_the_addon_the_runtime_and_its_wheels(built, platform):
    with zipfile.ZipFile(built[platform]) as zf:
        names = set(zf.namelist())
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        record = json.loads(zf.read("wheels/wheels.json"))
        digests = {n: hashlib.sha256(zf.read(n)).hexdigest() for n in names if n.endswith(".whl")}
    assert {"__init__.py", "ui/operators.py", "scene/bake.py", "features/generate.py", "environment.py",
            "batch_render.py", "studio.py", "presets/rigify.json",
            "lib/diffsheg_core/__init__.py", "lib/diffsheg_core/beat_skeleton.json",
            "lib/diffsheg_core/weights/default.safetensors", "lib/diffsheg_core/runtime/backends.py"} <= names
    assert not [n for n in names if _tooling_or_cache(n)]
    assert manifest["platforms"] == [platform]
    assert manifest["id"] == "diffsheg" and manifest["version"] == build_addon.version()
    # every listed wheel is in the zip, recorded with its hash, and nothing else is bundled
    wheels = {w[len("./"):] for w in manifest["wheels"]}
    assert wheels == set(digests)
    assert {f"wheels/{w['file']}": w["sha256"] for w in record["wheels"]} == digests
    assert record["platform"] == platform and record["pins"] == build_addon.pins(platform)
    dists = {Path(w).name.split("-")[0].lower() for w in wheels}
    assert dists == {"onnxruntime", "soundfile", "cffi", "typing_extensions", "soxr", "safetensors",
                     "sounddevice", "python_osc", "threadpoolctl"}
    for w in wheels:
        name, version = Path(w).name.split("-")[:2]
        assert build_addon.pins(platform)[name.replace("_", "-")] == version
        assert "cp311" in w or "abi3" in w or "-none-" in w


def _blender_ext():
    """Blender's own extension tool (bl_pkg/cli/blender_ext.py), for its manifest validation."""
    path = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    spec = importlib.util.spec_from_file_location("blender_ext", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("platform", list(build_addon.PLATFORMS))
def test_extension_manifest_passes_blenders_strict_validation(built, platform):
    with zipfile.ZipFile(built[platform]) as zf:
        result = _blender_ext().pkg_manifest_from_zipfile_and_validate_all_errors(zf, "", strict=True)
    assert not isinstance(result, list), result
    assert result.platforms == [platform] and len(result.wheels) == len(build_addon.WHEELS)


def test_legacy_zip_has_the_addon_in_a_folder_and_no_wheels(built):
    names = set(zipfile.ZipFile(built["legacy"]).namelist())
    assert {"diffsheg/__init__.py", "diffsheg/ui/panel.py", "diffsheg/batch_render.py", "diffsheg/studio.py",
            "diffsheg/lib/diffsheg_core/__init__.py"} <= names
    assert "diffsheg/blender_manifest.toml" not in names
    assert not [n for n in names if n.endswith(".whl") or _tooling_or_cache(n)]


def test_legacy_zip_claims_the_oldest_blender_it_runs_on(built):
    """Blender before 4.2 reads bl_info (4.2+ the manifest): the legacy add-on runs from 3.4
    on (checked in Debian's Blender 3.4, whose Python lacks numpy)."""
    source = zipfile.ZipFile(built["legacy"]).read("diffsheg/__init__.py").decode()
    bl_info = next(ast.literal_eval(node.value) for node in ast.parse(source).body
                   if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) == "bl_info")
    assert bl_info["blender"] == (3, 4, 0)


@pytest.fixture(scope="module")
def shipped_core(built, tmp_path_factory):
    """The lib/ folder of the linux-x64 extension: the diffsheg_core users get."""
    folder = tmp_path_factory.mktemp("shipped")
    with zipfile.ZipFile(built["linux-x64"]) as zf:
        zf.extractall(folder, [n for n in zf.namelist() if n.startswith("lib/")])
    return folder / "lib"


@pytest.mark.parametrize("command", ["train", "evaluate", "train-autoencoder", "train-phonetic", "export-onnx",
                                     "add-face"])
def test_the_shipped_core_says_where_the_tooling_commands_are(shipped_core, command, tmp_path):
    # -S: no site-packages, where the checkout's editable install would bring the missing tooling back
    proc = subprocess.run([sys.executable, "-S", "-m", "diffsheg_core", command, "--help"], cwd=tmp_path,
                          env=dict(os.environ, PYTHONPATH=str(shipped_core)), capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith(f"error: '{command}' needs the tooling of diffsheg_core")
    assert "no module named 'diffsheg_core." in proc.stderr and 'pip install -e ".[train]" (see README)' in proc.stderr


def test_source_manifest_stays_the_template():
    text = (REPO / "blender_addon" / "blender_manifest.toml").read_text()
    manifest = tomllib.loads(text)
    assert "wheels" not in manifest and "platforms" not in manifest


def test_build_only_some_platforms_and_print_sizes(tmp_path):
    proc = subprocess.run([sys.executable, str(REPO / "build_addon.py"), "--out", str(tmp_path),
                           "--platform", "windows-x64", "--no-legacy"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert [p.name for p in tmp_path.glob("*.zip")] == [f"diffsheg-{build_addon.version()}-windows-x64.zip"]
    assert "diffsheg-0.1.0-windows-x64.zip (" in proc.stdout and " MB)" in proc.stdout


@pytest.mark.parametrize("mode", ["extension", "legacy"])
def test_built_zip_installs_and_enables(built, mode, tmp_path):
    path = built["linux-x64" if mode == "extension" else "legacy"]
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    script = tmp_path / "install.py"
    script.write_text(INSTALL)
    proc = subprocess.run([sys.executable, str(script), mode, str(path)], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    line = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
    assert proc.returncode == 0 and line, proc.stderr[-2000:]
    result = json.loads(line[0][len("RESULT "):])
    assert result["enabled"] and result["panel"] and result["settings"]
    assert result["operator"] == "DIFFSHEG_OT_generate"
    assert result["core"].startswith(str(tmp_path / "user"))  # the bundled copy, not the checkout
    assert {"beat", "smplx", "rigify", "metahuman", "mixamo"} <= set(result["presets"])
    assert str(REPO) not in result["core"]
    if mode == "extension":  # Blender installed the bundled wheels beside its extensions
        assert "/extensions/.local/lib/python3.11/site-packages" in result["wheels_dir"]


def test_gpu_support_pip_installs_torch_alone_with_blenders_numpy_pinned(tmp_path):
    import numpy

    from blender_addon.environment import RUNTIME
    from blender_addon.ui.preferences import runtime_pip_commands, torch_pip_commands

    (command,) = torch_pip_commands("CUDA", tmp_path)
    assert command[command.index("--target") + 1] == str(tmp_path)
    assert command[command.index("--index-url") + 1].startswith("https://download.pytorch.org/whl/cu")
    assert command[-2:] == ["torch>=2.1", f"numpy=={numpy.__version__}"]
    (command,) = torch_pip_commands("PYPI", tmp_path)
    assert "--index-url" not in command
    (command,) = runtime_pip_commands(tmp_path)  # the legacy add-on's "Install dependencies"
    assert command[-len(RUNTIME) - 1:-1] == list(RUNTIME.values()) and "torch>=2.1" not in command
