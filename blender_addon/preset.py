"""Rig presets (JSON in presets/): which bone and shape key each model channel drives.

A preset maps the canonical channels of a model layout (joint names of
`diffsheg_core.rigs`, ARKit or expression names) to a rig's bone and shape-key names,
and may carry shape-key aliases, a jaw driven from a face weight, rest alignment and
custom properties to set on the rig. Standard library only, so the add-on can list
presets before its Python dependencies are installed.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from diffsheg_core.errors import DiffshegError

PRESET_DIRS: tuple[Path, ...] = (
    Path(__file__).resolve().parent / "presets",          # inside the installed add-on
    Path(__file__).resolve().parent.parent / "presets",   # repository checkout
)


MAX_JAW_DEGREES = 90.0


@dataclass(frozen=True)
class JawDrive:
    """Drive a jaw bone from a face weight (for layouts with no jaw joint)."""

    bone: str
    source: str = "jawOpen"
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    degrees: float = 25.0

    def __post_init__(self):
        for name in ("bone", "source"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                raise ValueError(f'"jaw"."{name}" must be a name (text), got {getattr(self, name)!r}')
        axis = self.axis
        if (not isinstance(axis, (list, tuple)) or len(axis) != 3
                or not all(_is_number(a) for a in axis)):
            raise ValueError(f'"jaw"."axis" must be three numbers such as [1, 0, 0], got {axis!r}')
        if sum(float(a) ** 2 for a in axis) < 1e-12:
            raise ValueError('"jaw"."axis" is zero: give the axis the jaw opens about, e.g. [1, 0, 0]')
        if not _is_number(self.degrees) or not 0 < abs(float(self.degrees)) <= MAX_JAW_DEGREES:
            raise ValueError(f'"jaw"."degrees" must be a number of degrees between 0 and '
                             f'{MAX_JAW_DEGREES:g} (how far the jaw opens), got {self.degrees!r}')
        object.__setattr__(self, "axis", tuple(float(a) for a in axis))
        object.__setattr__(self, "degrees", float(self.degrees))


def _is_number(value) -> bool:
    """A finite int or float (not a bool, a string or NaN)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _names(section: str, value) -> dict:
    """A {name: name} table of the preset (bones of one layout, custom properties)."""
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise ValueError(f'"{section}" must be a table of names, got {type(value).__name__}')
    return dict(value)


@dataclass(frozen=True)
class Preset:
    name: str
    description: str = ""
    bones: dict = field(default_factory=dict)            # layout -> {joint: bone}
    shape_key_aliases: dict = field(default_factory=dict)  # canonical -> [alias, ...]
    jaw: JawDrive | None = None
    align_rest: bool = False
    properties: dict = field(default_factory=dict)        # bone -> {custom prop: value}

    def joint_map(self, layout: str) -> dict[str, str]:
        if layout not in self.bones:
            raise DiffshegError(
                f"preset '{self.name}' has no bone map for the '{layout}' layout of this "
                f"model: add a \"{layout}\" section to its \"bones\" or pick another preset")
        return dict(self.bones[layout])


def available_presets() -> list[str]:
    names = {p.stem for d in PRESET_DIRS if d.is_dir() for p in d.glob("*.json")}
    return sorted(names)


def load_preset(name_or_path: str) -> Preset:
    """A preset by name (presets/<name>.json) or by path to a JSON file."""
    path = Path(name_or_path)
    if path.suffix.lower() != ".json":
        found = [d / f"{name_or_path}.json" for d in PRESET_DIRS if (d / f"{name_or_path}.json").is_file()]
        if not found:
            raise DiffshegError(
                f"no rig preset '{name_or_path}': choose one of {', '.join(available_presets())} "
                f"or give the path of a preset .json file")
        path = found[0]
    if not path.is_file():
        raise DiffshegError(f"{path}: rig preset file not found")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError("the file must hold one JSON object")
        jaw = data.get("jaw")
        if jaw is not None and not isinstance(jaw, dict):
            raise ValueError('"jaw" must be a table such as {"bone": "jaw", "degrees": 25}')
        for bones in data.get("bones", {}).values():
            for joint, bone in _names("bones", bones).items():
                if not isinstance(bone, str):
                    raise ValueError(f'"bones": joint {joint!r} must map to a bone name, got {bone!r}')
        return Preset(
            name=data.get("name", path.stem),
            description=data.get("description", ""),
            bones={k: _names(f"bones.{k}", v) for k, v in _names("bones", data.get("bones", {})).items()},
            shape_key_aliases={k: list(v) for k, v in data.get("shape_key_aliases", {}).items()},
            jaw=JawDrive(**jaw) if jaw else None,
            align_rest=bool(data.get("align_rest", False)),
            properties={k: _names(f"properties.{k}", v)
                        for k, v in _names("properties", data.get("properties", {})).items()},
        )
    except (ValueError, TypeError, AttributeError) as exc:
        raise DiffshegError(f"rig preset {path}: {exc}; fix the file (compare it with "
                            "presets/beat.json)") from None


# ---------------------------------------------------------------- name matching

def normalise_name(name: str) -> str:
    """Case-, separator- and prefix-insensitive key: 'A25_Jaw_Open', 'jaw_open',
    'JawOpen' and 'mixamorig:Hips' -> 'jawopen', 'jawopen', 'jawopen', 'hips'."""
    name = name.rsplit(":", 1)[-1]
    name = re.sub(r"^[Aa]\d\d_", "", name)
    return re.sub(r"[^0-9a-z]", "", name.lower())


def find_name(wanted: list[str], available) -> str | None:
    """First of `wanted` present in `available`, exactly or by `normalise_name`."""
    available = list(available)
    for name in wanted:
        if name in available:
            return name
    by_key = {normalise_name(a): a for a in available}
    for name in wanted:
        if normalise_name(name) in by_key:
            return by_key[normalise_name(name)]
    return None
