"""The add-on as a new user gets it: installed into a Blender that holds nothing but what
Blender ships (tools/test_fresh_blender.py), and registered with the heavy packages
unimportable, where the panel and Generate say what is missing instead of failing."""

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

# Runs in a subprocess: the blocked packages cannot be imported there (None in sys.modules).
WITHOUT_PACKAGES = r"""
import json, os, sys
BLOCKED = sys.argv[1].split(",")
for name in BLOCKED:
    sys.modules[name] = None
sys.path.insert(0, sys.argv[2])
fake_checkpoint, audio = sys.argv[3], sys.argv[4]
import bpy

import blender_addon
blender_addon.register()
HEAVY = ("torch", "scipy", "librosa", "numba", "soundfile", "onnxruntime", "soxr", "safetensors")
at_register = [n for n in HEAVY if sys.modules.get(n) is not None]
from blender_addon.panel import DIFFSHEG_PT_generate


class Layout:
    def __init__(self, texts):
        self.texts = texts
    def label(self, text="", **kw):
        self.texts.append(text)
    def __getattr__(self, name):  # box, row, column, prop, operator, template_list, ...
        return lambda *a, **kw: self
    active = True


def panel_texts():
    texts = []
    DIFFSHEG_PT_generate.draw(type("Self", (), {"layout": Layout(texts)})(), bpy.context)
    return texts


def generate_error():
    try:
        bpy.ops.diffsheg.generate()
    except RuntimeError as exc:
        return str(exc)
    return None


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
