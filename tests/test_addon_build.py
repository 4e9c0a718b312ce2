"""build_addon.py: the built zips install and enable in headless Blender (bpy) and
register the panel and the operator, using the diffsheg_core bundled in the zip."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile

import pytest

from addon_fixtures import REPO, exit_before_blender_teardown  # noqa: F401 (fixture)

import build_addon

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
    "presets": sys.modules[module + ".preset"].available_presets(),
}), flush=True)
os._exit(0)  # skip Blender's exit-time teardown: the bpy modules before 5.0 crash or hang in it
"""


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    return build_addon.build(tmp_path_factory.mktemp("dist"))


def test_zips_hold_the_addon_core_and_presets(built):
    extension, legacy = built
    names = set(zipfile.ZipFile(extension).namelist())
    assert {"blender_manifest.toml", "__init__.py", "operators.py", "presets/rigify.json",
            "lib/diffsheg_core/__init__.py", "lib/diffsheg_core/beat_skeleton.json"} <= names
    assert not any("__pycache__" in n for n in names)
    legacy_names = set(zipfile.ZipFile(legacy).namelist())
    assert "diffsheg/__init__.py" in legacy_names and "diffsheg/blender_manifest.toml" not in legacy_names


@pytest.mark.parametrize("mode", ["extension", "legacy"])
def test_built_zip_installs_and_enables(built, mode, tmp_path):
    path = built[0] if mode == "extension" else built[1]
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
