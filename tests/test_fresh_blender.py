"""The add-on as a new user gets it: installed into a Blender that holds nothing but what
Blender ships (tools/test_fresh_blender.py), and registered with the heavy packages, or
numpy, unimportable, where the panel and Generate say what is missing instead of failing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.blender


def test_fresh_blender_installs_the_extension_generates_and_batches():
    """Builds the linux-x64 zip, installs it into a venv with only bpy 5.0.1, keys a
    Rigify rig and the ARKit face with bpy.ops.diffsheg.generate() without torch, and
    runs the installed batch_render.py (see the script's docstring)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the fresh-Blender check installs the linux-x64 extension")
    if sys.version_info[:2] != (3, 11) and "PYTHON" not in os.environ:
        pytest.skip("the bpy wheels need CPython 3.11: set PYTHON=/path/to/python3.11")
    proc = subprocess.run([sys.executable, str(REPO / "tools" / "test_fresh_blender.py")],
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, (proc.stdout[-3000:] + proc.stderr[-3000:])
    assert "fresh Blender: passed" in proc.stdout


BLOCKED = ("torch", "scipy", "librosa", "soundfile", "onnxruntime")

# The start of the scripts below: blocks the packages named in argv[1] (None in sys.modules,
# so `import name` fails, as where it is not installed), registers the add-on of the
# checkout in argv[2], and draws with a layout that records labels and operator buttons.
REGISTER_WITHOUT = r"""
import json, os, sys
BLOCKED = sys.argv[1].split(",")
for name in BLOCKED:
    sys.modules[name] = None
sys.path.insert(0, sys.argv[2])
import bpy

import blender_addon
blender_addon.register()
from blender_addon.ui.panel import DIFFSHEG_PT_generate, DIFFSHEG_PT_keys, DIFFSHEG_PT_sampling


class Layout:
    def __init__(self, texts):
        self.texts = texts
    def label(self, text="", **kw):
        self.texts.append(text)
    def operator(self, idname, **kw):
        self.texts.append(f"[{idname}]")
        return self
    def __getattr__(self, name):  # box, row, column, prop, template_list, ...
        return lambda *a, **kw: self
    active = True


def drawn(cls, **attrs):
    texts = []
    cls.draw(type("Self", (), {"layout": Layout(texts), **attrs})(), bpy.context)
    return texts


def panel_texts():  # the panel and its sub-panels
    return [t for cls in (DIFFSHEG_PT_generate, DIFFSHEG_PT_sampling, DIFFSHEG_PT_keys) for t in drawn(cls)]


def generate_error():
    try:
        bpy.ops.diffsheg.generate()
    except RuntimeError as exc:
        return str(exc)
    return None
"""

# Runs in a subprocess: the heavy packages cannot be imported there.
WITHOUT_PACKAGES = REGISTER_WITHOUT + r"""
fake_checkpoint, audio = sys.argv[3], sys.argv[4]
HEAVY = ("torch", "scipy", "librosa", "numba", "soundfile", "onnxruntime", "soxr", "safetensors")
at_register = [n for n in HEAVY if sys.modules.get(n) is not None]

s = bpy.context.scene.diffsheg
s.audio_path = audio
face = bpy.data.objects.new("Face", bpy.data.meshes.new("Face"))
bpy.context.scene.collection.objects.link(face)
face.shape_key_add(name="Basis")
s.face_meshes.add().object = face
out = {"at_register": at_register, "panel": panel_texts(), "missing_error": generate_error()}

# soundfile and onnxruntime back; torch still missing: official checkpoints and the GPU say so
for name in ("soundfile", "onnxruntime"):
    del sys.modules[name]
s.model_path = fake_checkpoint
out["checkpoint_error"] = generate_error()
s.model_path = ""
s.device = "GPU"
out["gpu_error"] = generate_error()
out["device_label"] = [t for t in panel_texts() if t.startswith("Runs on")]
out["imported"] = [n for n in ("torch", "scipy", "librosa") if sys.modules.get(n) is not None]
print("RESULT", json.dumps(out), flush=True)
os._exit(0)
"""


def test_addon_registers_without_the_heavy_packages_and_says_what_is_missing(tmp_path):
    checkpoint = tmp_path / "beat_ckpt.pth"  # torch.save writes a zip archive
    with zipfile.ZipFile(checkpoint, "w") as zf:
        zf.writestr("archive/data.pkl", b"\x80\x02}q\x00.")
    audio = REPO.parent / "shared" / "data" / "audio" / "12_zhao_2_3_3.wav"
    script = tmp_path / "without.py"
    script.write_text(WITHOUT_PACKAGES)
    proc = subprocess.run([sys.executable, str(script), ",".join(BLOCKED), str(REPO), str(checkpoint), str(audio)],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    lines = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-3000:]
    got = json.loads(lines[0][len("RESULT "):])

    assert got["at_register"] == []  # registration needs the standard library, numpy and bpy only
    assert "Missing Python packages: onnxruntime, soundfile" in got["panel"]
    assert any("Install dependencies" in t for t in got["panel"])  # a checkout registers as a legacy add-on
    error = got["missing_error"]
    assert error and "missing Python packages: onnxruntime, soundfile" in error and "Traceback" not in error

    error = got["checkpoint_error"]
    assert error and "beat_ckpt.pth" in error and "official DiffSHEG checkpoint" in error
    assert "Install GPU support" in error and "Traceback" not in error
    error = got["gpu_error"]
    assert error and "torch with CUDA" in error and "Install GPU support" in error
    assert got["device_label"] == ["Runs on: GPU needs GPU support: see the add-on's preferences"]
    assert got["imported"] == []


# Runs in a subprocess: numpy cannot be imported there, as in Debian's Blender 3.4 (the
# system's Python); bpy 5.0 says which of its parts need it and goes on.
WITHOUT_NUMPY = REGISTER_WITHOUT + r"""
from pathlib import Path

from blender_addon import environment
from blender_addon.ui import preferences
from blender_addon.ui.properties import _style_items

out = {"preferences": drawn(preferences.DIFFSHEG_AP_preferences, install_status="", torch_build="CPU"),
       "panel": panel_texts(), "error": generate_error(),
       "menu": _style_items(bpy.context.scene.diffsheg, bpy.context),
       "pip": preferences.runtime_pip_commands(Path("modules"))[0][-1]}
environment.ADDON_PACKAGE = "bl_ext.user_default.diffsheg"  # installed as an extension
out["extension"] = drawn(preferences.DIFFSHEG_AP_preferences, install_status="", torch_build="CPU")
print("RESULT", json.dumps(out), flush=True)
os._exit(0)
"""


def test_addon_registers_without_numpy_and_its_preferences_offer_to_install_it(tmp_path):
    script = tmp_path / "without_numpy.py"
    script.write_text(WITHOUT_NUMPY)
    proc = subprocess.run([sys.executable, str(script), "numpy", str(REPO)], capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    lines = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-3000:]
    got = json.loads(lines[0][len("RESULT "):])

    install = "Install them with Edit > Preferences > Add-ons > DiffSHEG > Install dependencies"
    why = "This Blender's Python lacks numpy (a Linux distribution's build; Blender's own has it)"
    assert got["preferences"][:4] == ["Missing Python packages: numpy", why, install,
                                      "[diffsheg.install_dependencies]"]
    assert got["panel"][:3] == got["preferences"][:3]
    assert got["error"] == f"Error: missing Python packages: numpy; {install[0].lower()}{install[1:]}\n"
    assert got["menu"] == [["__default__", "Default", "the model's default style"], ["0", "Style 0", ""]]
    assert got["pip"] == "numpy>=1.26"  # no numpy of Blender's to keep
    assert got["extension"][:4] == got["preferences"][:4]  # no extension zip brings numpy
