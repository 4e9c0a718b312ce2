"""What the add-on runs on, and whether it is there: the runtime's Python packages (and how
this kind of install brings them back), torch (the optional GPU support) and Live's
microphone. The panel, the preferences and Generate ask here; nothing here draws.

Nothing here imports those packages at import time: their presence is looked up with
`find_spec`, so the add-on registers with nothing but the standard library and bpy.
"""

from __future__ import annotations

import importlib
import importlib.util
import platform
import sys
import time
from pathlib import Path

from diffsheg_core.errors import DiffshegError

ADDON_PACKAGE = __package__  # the add-on's package: blender_addon, diffsheg, bl_ext.user_default.diffsheg

# import name -> pip requirement: what `diffsheg_core.generate` runs on (the onnx backend)
RUNTIME: dict[str, str] = {
    "onnxruntime": "onnxruntime>=1.17",
    "soundfile": "soundfile>=0.12",
    "soxr": "soxr>=0.3",
    "safetensors": "safetensors>=0.4",
    "threadpoolctl": "threadpoolctl>=3.1",
}
# import name -> pip requirement: what Live uses besides those (the microphone, VMC out); the
# extension zips bring them, the legacy add-on's "Install dependencies" installs them too
LIVE: dict[str, str] = {
    "sounddevice": "sounddevice>=0.4",
    "pythonosc": "python-osc>=1.8",
}
NUMPY_MISSING = "This Blender's Python lacks numpy (a Linux distribution's build; Blender's own has it)"
INSTALL_GPU_HINT = "Edit > Preferences > Add-ons > DiffSHEG > Install GPU support"
MIC_STATUS_EVERY_S = 5.0   # the microphone's state is looked up at most this often (panel redraws)


def is_extension() -> bool:
    """Installed as a Blender 4.2+ extension (its wheels bring the runtime packages)."""
    return (ADDON_PACKAGE or "").startswith("bl_ext.")


def blender_platform() -> str:
    """This machine in the extension platforms' names: linux-x64, macos-arm64, ..."""
    machine = platform.machine().lower()
    arch = "arm64" if machine in ("arm64", "aarch64") else "x64"
    system = {"win32": "windows", "darwin": "macos"}.get(sys.platform, sys.platform.rstrip("0123456789"))
    return f"{system}-{arch}"


def addon_version() -> str:
    info = getattr(sys.modules.get(ADDON_PACKAGE or ""), "bl_info", {})
    return ".".join(str(v) for v in info.get("version", (0, 1, 0)))


def missing_runtime() -> list[str]:
    """Import names of the runtime packages Blender's Python cannot find, numpy first."""
    return [name for name in ("numpy", *RUNTIME) if importlib.util.find_spec(name) is None]


def pip_installs_runtime() -> bool:
    """The runtime comes from the "Install dependencies" button: in the legacy add-on, and
    wherever numpy is missing (no extension zip brings it)."""
    return not is_extension() or importlib.util.find_spec("numpy") is None


def torch_installed() -> bool:
    return importlib.util.find_spec("torch") is not None


def runtime_fix() -> str:
    """What brings the runtime packages back, for this kind of install."""
    if not pip_installs_runtime():
        return (f"they come with the extension: install diffsheg-{addon_version()}-{blender_platform()}.zip "
                "again (Edit > Preferences > Get Extensions > Install from Disk)")
    return "install them with Edit > Preferences > Add-ons > DiffSHEG > Install dependencies"


def runtime_problems() -> list[str]:
    """What the panel and the preferences say while runtime packages are missing ([]: none)."""
    missing = missing_runtime()
    if not missing:
        return []
    fix = runtime_fix()
    return [f"Missing Python packages: {', '.join(missing)}", *([NUMPY_MISSING] if "numpy" in missing else []),
            fix[0].upper() + fix[1:]]


def check_runtime() -> None:
    """The runtime packages are there and import (e.g. a wheel for a newer OS fails here)."""
    missing = missing_runtime()
    if missing:
        raise DiffshegError(f"missing Python packages: {', '.join(missing)}; {runtime_fix()}")
    for name in RUNTIME:
        try:
            importlib.import_module(name)
        except Exception as exc:  # ImportError, or an OSError from a shared library
            needs = bundled_wheels_need()
            raise DiffshegError(f"the Python package {name} is installed but does not load "
                                f"({type(exc).__name__}: {exc}); "
                                + (f"the bundled wheels need {needs} or newer; " if needs else "")
                                + runtime_fix()) from None


def bundled_wheels_need() -> str | None:
    """The OS release the extension's wheels ask for (wheels/wheels.json, see build_addon.py)."""
    import json

    record = Path(__file__).resolve().parent / "wheels" / "wheels.json"
    try:
        return json.loads(record.read_text(encoding="utf-8")).get("requires_os")
    except (OSError, ValueError):
        return None


_mic_status: dict = {"at": None, "status": None}


def microphone_problem() -> str | None:
    """Why the microphone cannot be used (sounddevice or the system's PortAudio library
    missing, no input device), or None; looked up at most every MIC_STATUS_EVERY_S seconds
    (the panel asks on every redraw). None also where the runtime packages are missing: the
    panel says that already."""
    now = time.monotonic()
    if _mic_status["at"] is None or now - _mic_status["at"] > MIC_STATUS_EVERY_S:
        try:
            from diffsheg_core.live.sources import microphone_status
        except ImportError:
            status = None
        else:
            try:
                status = microphone_status()
            except Exception as exc:  # a draw must never raise
                status = f"the microphone cannot be used ({type(exc).__name__}: {exc})"
        _mic_status.update(at=now, status=status)
    return _mic_status["status"]
