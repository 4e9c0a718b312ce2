"""Rig presets (JSON in presets/): which bone and shape key each model channel drives.

A preset maps the canonical channels of a model layout (joint names of
`diffsheg_core.rigs`, ARKit or expression names) to a rig's bone and shape-key names.
A joint maps to one bone, or to a chain of bones (parent first) that share its rotation
(a spine of three bones for the model's one). `bone_aliases` and `shape_key_aliases`
give other names of the same bone or key (the first present wins); `also_drives` lists
keys a face channel drives besides its own. A preset may also carry a jaw driven from a
face weight, rest alignment and custom properties to set on the rig (`joint_properties`: only
where a joint is keyed, as Rigify's legs switched to FK). Standard library
only, so the add-on can list presets before its Python dependencies are installed.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from diffsheg_core.errors import DiffshegError

PRESET_DIRS: tuple[Path, ...] = (
    Path(__file__).resolve().parents[1] / "presets",   # inside the installed add-on
    Path(__file__).resolve().parents[2] / "presets",   # repository checkout
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


def _bone_chain(joint: str, value) -> tuple[str, ...]:
    """A joint's bones: one name, or a list of names (a chain sharing the rotation)."""
    chain = [value] if isinstance(value, str) else value
    if not isinstance(chain, list) or not chain or not all(isinstance(b, str) and b for b in chain):
        raise ValueError(f'"bones": joint {joint!r} must map to a bone name or a list of bone names '
                         f'(a chain, parent first), got {value!r}')
    return tuple(chain)


def _name_lists(section: str, value) -> dict[str, list[str]]:
    """A {name: [other names]} table (aliases); a single name may stand for a list of one."""
    out = {}
    for name, names in _names(section, value).items():
        names = [names] if isinstance(names, str) else names
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError(f'"{section}": {name!r} must map to a list of names, got {names!r}')
        out[name] = list(names)
    return out


@dataclass(frozen=True)
class Preset:
    name: str
    description: str = ""
    bones: dict = field(default_factory=dict)            # layout -> {joint: [bone, ...]}
    bone_aliases: dict = field(default_factory=dict)      # bone -> [alias, ...]
    shape_key_aliases: dict = field(default_factory=dict)  # canonical -> [alias, ...]
    also_drives: dict = field(default_factory=dict)       # canonical -> [further key, ...]
    jaw: JawDrive | None = None
    align_rest: bool = False
    properties: dict = field(default_factory=dict)        # bone -> {custom prop: value}
    joint_properties: dict = field(default_factory=dict)  # joint -> {bone -> {custom prop: value}}, where keyed

    def properties_for(self, joints) -> dict:
        """{bone: {custom prop: value}} to set on the rig when `joints` are keyed: `properties`,
        and the `joint_properties` of those joints (Rigify's legs switched to FK only with legs)."""
        out = {bone: dict(props) for bone, props in self.properties.items()}
        for joint in joints:
            for bone, props in self.joint_properties.get(joint, {}).items():
                out.setdefault(bone, {}).update(props)
        return out

    def joint_map(self, layout: str) -> dict[str, list[str]]:
        """{joint: its bones, parent first} for a model layout."""
        if layout not in self.bones:
            raise DiffshegError(
                f"preset '{self.name}' has no bone map for the '{layout}' layout of this "
                f"model: add a \"{layout}\" section to its \"bones\" or pick another preset")
        return {joint: list(bones) for joint, bones in self.bones[layout].items()}

    def find_bone(self, bone: str, available) -> str | None:
        """The rig's name for one of the preset's bones (by name, then by its aliases)."""
        return find_name([bone] + self.bone_aliases.get(bone, []), available)


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
        data = _preset_data(path)
        jaw = data.get("jaw")
        if jaw is not None and not isinstance(jaw, dict):
            raise ValueError('"jaw" must be a table such as {"bone": "jaw", "degrees": 25}')
        return Preset(
            name=data.get("name", path.stem),
            description=data.get("description", ""),
            bones={layout: {joint: _bone_chain(joint, bones) for joint, bones in _names(f"bones.{layout}", v).items()}
                   for layout, v in _names("bones", data.get("bones", {})).items()},
            bone_aliases=_name_lists("bone_aliases", data.get("bone_aliases", {})),
            shape_key_aliases=_name_lists("shape_key_aliases", data.get("shape_key_aliases", {})),
            also_drives=_name_lists("also_drives", data.get("also_drives", {})),
            jaw=JawDrive(**jaw) if jaw else None,
            align_rest=bool(data.get("align_rest", False)),
            properties={k: _names(f"properties.{k}", v)
                        for k, v in _names("properties", data.get("properties", {})).items()},
            joint_properties={j: {k: _names(f"joint_properties.{j}.{k}", v)
                                  for k, v in _names(f"joint_properties.{j}", bones).items()}
                              for j, bones in _names("joint_properties", data.get("joint_properties", {})).items()},
        )
    except (ValueError, TypeError, AttributeError) as exc:
        raise DiffshegError(f"rig preset {path}: {exc}; fix the file (compare it with "
                            "presets/beat.json)") from None


def _preset_data(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    """The JSON object of a preset file, merged over the preset it "extends" (a name in
    the same folder): tables merge entry by entry (bones layout by layout), the rest is
    replaced."""
    data = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(data, dict):
        raise ValueError("the file must hold one JSON object")
    base_name = data.pop("extends", None)
    if base_name is None:
        return data
    base_path = path.with_name(f"{base_name}.json")
    if not isinstance(base_name, str) or not base_path.is_file():
        raise ValueError(f'"extends": {base_name!r} is not a preset beside this file')
    if base_path in seen:
        raise ValueError(f'"extends" goes round in a circle through {base_path.name}')
    merged = _preset_data(base_path, seen + (path,))
    merged.pop("name", None)
    for key, value in data.items():
        if key == "bones" and isinstance(value, dict) and isinstance(merged.get("bones"), dict):
            merged["bones"] = {**merged["bones"], **{k: {**merged["bones"].get(k, {}), **v}
                                                     if isinstance(v, dict) else v for k, v in value.items()}}
        elif isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return merged


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


# ---------------------------------------------------------------- choosing a preset

AUTO = "auto"


@dataclass(frozen=True)
class PresetFit:
    """How well a preset's names fit a rig: compared field by field, highest first."""

    bones: int        # joints (and the jaw) with a bone on the rig
    exact: int        # of those, found by their exact name (not by case or prefix)
    face: int         # shape keys found only by the preset's aliases, or its also_drives
    missing: int      # joints of the preset not on the rig

    def key(self) -> tuple[int, int, int, int]:
        return (self.bones, self.exact, self.face, -self.missing)


def preset_fit(preset: Preset, layout: str, bones, shape_keys) -> PresetFit | None:
    """The fit of `preset` to a rig with these bone and shape-key names (None: no map for `layout`)."""
    if layout not in preset.bones:
        return None
    bones, shape_keys = list(bones), list(shape_keys)
    found = exact = missing = 0
    for chain in preset.joint_map(layout).values():
        names = [preset.find_bone(b, bones) for b in chain]
        if any(names):
            found += 1
            exact += all(n in [b] + preset.bone_aliases.get(b, []) for b, n in zip(chain, names) if n)
        else:
            missing += 1
    if preset.jaw is not None:
        if preset.find_bone(preset.jaw.bone, bones) is None:
            missing += 1
        else:
            found += 1
    aliases = [[a for a in names if normalise_name(a) != normalise_name(channel)]
               for channel, names in preset.shape_key_aliases.items()]
    face = sum(find_name(names, shape_keys) is not None for names in (*aliases, *preset.also_drives.values()))
    return PresetFit(bones=found, exact=exact, face=face, missing=missing)


def choose_preset(layout: str, bones, shape_keys, fallback: str = "beat") -> tuple[Preset, str]:
    """The preset whose names fit the rig best, and a note saying which and why.

    With no bones (a face only) and no alias found, `fallback` (ARKit names).
    Raises DiffshegError when there are bones and no preset matches any of them.
    """
    fits = {}
    for name in available_presets():
        preset = load_preset(name)
        fit = preset_fit(preset, layout, bones, shape_keys)
        if fit is not None:
            fits[name] = (fit, preset)
    bones = list(bones)
    best = max(fits, key=lambda n: (fits[n][0].key(), n == fallback), default=None)
    if best is None or (bones and fits[best][0].bones == 0):
        raise DiffshegError(
            f"no rig preset fits this rig: none names any of its bones ({', '.join(bones[:4])}, ...) "
            f"for the '{layout}' layout: choose a preset, or write one (see presets/ for the format)")
    fit, preset = fits[best]
    if not bones:
        return (preset, f"preset Auto chose '{best}' for the face") if fit.face else (
            load_preset(fallback), f"preset Auto chose '{fallback}' (ARKit names) for the face")
    return preset, f"preset Auto chose '{best}' ({fit.bones} of {fit.bones + fit.missing} joints on the rig)"
