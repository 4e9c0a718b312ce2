"""DiffSHEG for Blender: speech audio in, keyed body, hand, head and face animation out.

A client of `diffsheg_core` (bundled beside this package in the installable zip,
under lib/): generation runs through `diffsheg_core.generate`; this package matches
rigs, keys the result and adds the sound. Its layers, each using only those below it:
ui/ (panel, properties, preferences, operators), features/ (generate, regenerate, live,
strips, exports), scene/ (bake, keying, takes, retarget, ...), environment.py (is the
runtime there), then diffsheg_core. `bl_info` describes the legacy add-on (the zip
for Blender 3.4 to 4.1); 4.2+ read blender_manifest.toml instead.
"""

import sys
from pathlib import Path

bl_info = {
    "name": "DiffSHEG: Generate from audio",
    "author": "diffsheg_core contributors",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),  # the oldest Blender it runs on (Debian's 3.4, Python 3.11 without numpy)
    "location": "View3D > Sidebar > DiffSHEG",
    "description": "Co-speech body, hand, head and face animation from a speech recording (DiffSHEG)",
    "category": "Animation",
}

_LIB = Path(__file__).resolve().parent / "lib"
if _LIB.is_dir() and str(_LIB) not in sys.path:
    sys.path.insert(0, str(_LIB))

from .ui import operators, panel, preferences, properties  # noqa: E402  (needs lib/ on sys.path)

_MODULES = (preferences, properties, operators, panel)


def register() -> None:
    for module in _MODULES:
        module.register()


def unregister() -> None:
    for module in reversed(_MODULES):
        module.unregister()
