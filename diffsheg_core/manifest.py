"""A manifest of dialogue lines: which audio, which character, which settings, which outputs.

One row per line, as CSV (a header row naming the columns) or JSON Lines (one object per
line; a file ending .jsonl or .ndjson). Columns (any but `id` and `audio` may be left out
or empty; an empty cell takes the default from the command line, `defaults`):

    id            the line's name, unique in the manifest; it names the line's output files
    audio         the speech file
    blend         the character's .blend (needed by the outputs blend, fbx_*, glb and mp4)
    armature      armature object name (default: the scene's only armature)
    face          face mesh object names, separated by ';' (default: meshes with shape keys)
    preset        rig preset name, 'auto', or a preset .json file
    style, style_at, emotion, emotion_at, seed, face_seed, sampling, steps, overlap, candidates,
    guidance, skip_guidance (or gesture_energy), style_guidance, upper_body_only (1/0), language
                  the generation settings, spelt as on the command line (`--style calm=0.7,
                  animated=0.3`, `--style-at 0=calm,12.5=animated`, `--emotion sad=0.6`,
                  `--emotion-at 0=happy,12.5=sad`, `--sampling quality`: fast, the default, or
                  quality, the model's own 25 steps, or an official preset; `--language zh`: a
                  language whose own face the model carries, empty for its shared face) and checked by
                  diffsheg_core.settings as the command line's are, so a row means what the
                  command line means
    start_frame, max_error, max_face_error, every_frame
                  keying: first frame, largest bone error (degrees), largest shape-key error,
                  key every frame (1/0, true/false, yes/no)
    outputs       what to write, separated by ';': blend, fbx_unreal, fbx_unity, glb, npz,
                  arkit_json, csv, mp4

Relative paths in a row resolve against the manifest's folder (paths in `defaults` are the
command line's and resolve against the working folder). `read_manifest` checks every row
before anything runs and raises one ManifestError listing every problem found, one per line.

Which lines are done (`line_key`, `Ledger`: `out_dir/done.jsonl`, so a rerun skips what is
done and redoes what changed) is `ledger`.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import unicodedata
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Collection, Iterator, Mapping, Optional

from .audio import probe_audio
from .emotion import check_emotion
from .errors import DiffshegError
from .files import resolve_path
from .settings import _NUMBERS as settings_numbers, GenerateSettings, _check_emotion_at, parse_emotion_at
from .style import check_style, check_style_at, parse_style, parse_style_at, unknown_styles
from .validate import check_language, check_number, parse_whole

OUTPUTS = ("blend", "fbx_unreal", "fbx_unity", "glb", "npz", "arkit_json", "csv", "mp4")
"""The output kinds, in the order a line's outputs are kept."""

OUTPUT_SUFFIXES = {"blend": ".blend", "fbx_unreal": "_unreal.fbx", "fbx_unity": "_unity.fbx", "glb": ".glb",
                   "npz": ".npz", "arkit_json": ".json", "csv": ".csv", "mp4": ".mp4"}
"""Each output kind -> the end of its file name (out/<id><suffix>)."""

BATCH_FILES = ("done.jsonl", "report.csv", "report.html")
"""The files the batch itself writes into the output folder (the ledger, the QC report):
no line's output may take one of these names."""

MAX_ID_BYTES = 200
"""The longest id (UTF-8 bytes): an output's staged and temporary names add up to 55 bytes
to it, and a file name holds at most 255."""

NEEDS_CHARACTER = frozenset({"blend", "fbx_unreal", "fbx_unity", "glb", "mp4"})
"""Outputs that key the motion onto a character, so need its .blend."""

CHARACTER = ("blend", "armature", "face", "preset")
GENERATION = ("style", "style_at", "emotion", "emotion_at", "seed", "face_seed", "sampling", "steps",
              "overlap", "candidates", "guidance", "skip_guidance", "style_guidance", "upper_body_only", "language")
KEYING = ("start_frame", "max_error", "max_face_error", "every_frame")
COLUMNS = ("id", "audio") + CHARACTER + GENERATION + KEYING + ("outputs",)
ALIASES = {"gesture_energy": "skip_guidance"}
"""Other spellings of columns (the command line's --gesture-energy)."""

SETTINGS_ONLY = ("model", "device", "backend", "precision", "threads")
"""GenerateSettings fields `defaults` may give but a row may not (one model per batch)."""

KEYING_DEFAULTS = {"start_frame": None, "max_error": 1.0, "max_face_error": 0.02, "every_frame": False}
"""batch_render.py's defaults for the keying options."""

MAX_FRAME = 1048574  # Blender's last frame
AUTO_PRESET = "auto"


class ManifestError(DiffshegError):
    """A manifest with bad rows; the message lists every one, one per line."""

    def __init__(self, path, problems: list[str]):
        self.problems = list(problems)
        count = f"{len(problems)} problem{'s' if len(problems) != 1 else ''}"
        super().__init__(f"manifest '{path}': {count}; nothing was run:\n" + "\n".join(self.problems))


@dataclass(frozen=True)
class Line:
    """One checked row of a manifest, every value resolved (defaults applied, paths absolute)."""

    id: str
    audio: Path
    settings: GenerateSettings          # the generation part, as the command line would build it
    blend: Optional[Path] = None
    armature: Optional[str] = None      # None: the scene's only armature
    face: Optional[tuple[str, ...]] = None  # None: the meshes with shape keys
    preset: str = AUTO_PRESET           # 'auto', a preset name, or the absolute path of a .json
    start_frame: Optional[int] = None   # None: the scene's start frame
    max_error: float = 1.0
    max_face_error: float = 0.02
    every_frame: bool = False
    outputs: tuple[str, ...] = ("npz",)
    row: int = 0                        # where it is in the manifest (for messages)


# ------------------------------------------------------------------ reading

def read_manifest(path, defaults: Optional[Mapping[str, Any]] = None, presets: Collection[str] = (),
                  style_names: Optional[Collection[str]] = None,
                  languages: Optional[Collection[str]] = None) -> list[Line]:
    """The checked lines of the manifest at `path` (CSV, or JSON Lines for .jsonl/.ndjson).

    `defaults`: values for cells a row leaves empty, by column name or GenerateSettings field
    (e.g. `vars(args)` of batch_render.py: keys that are neither are ignored); `face` may be
    a list. `presets`: the preset names there are. `style_names`: the model's style names,
    `languages` those it has a face of its own for (None: not checked here; the model checks
    them when it runs).
    Raises ManifestError listing every bad row (missing file, unknown preset or style,
    duplicate id, bad number, unknown column or output, ...)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise DiffshegError(f"manifest '{path}' does not exist or is not a file: check the path")
    folder = path.resolve().parent
    problems: list[str] = []
    base = _defaults(defaults or {}, problems)
    lines: list[Line] = []
    first_row: dict[str, int] = {}
    for row, cells in _rows(path, problems):
        line_id = cells.get("id")
        if isinstance(line_id, int) and not isinstance(line_id, bool):
            line_id = str(line_id)  # JSON's "id": 17
        line_id = line_id.strip() if isinstance(line_id, str) else None  # not text: _line reports it
        duplicate = not _empty(line_id) and line_id in first_row
        if duplicate:
            problems.append(f"row {row}, column id: duplicate id '{line_id}' (also on row {first_row[line_id]})")
        elif not _empty(line_id):
            first_row[line_id] = row
        line = _line(row, cells, base, folder, presets, style_names, languages, problems)
        if line is not None and not duplicate:
            lines.append(line)
    _check_file_names(lines, problems)
    if not lines and not problems:
        problems.append("no lines: the manifest holds no rows")
    if problems:
        raise ManifestError(path, problems)
    return lines


def _check_file_names(lines: list[Line], problems: list[str]) -> None:
    """A problem for each output that would take a name the batch writes itself, or the name
    of another line's output on a file system that ignores case (Windows, macOS)."""
    reserved = {name.casefold(): name for name in BATCH_FILES}
    taken: dict[str, Line] = {}
    for line in lines:
        for kind in line.outputs:
            name = output_name(line.id, kind)
            key = name.casefold()
            if key in reserved:
                problems.append(f"row {line.row}, column id: the {kind} output of '{line.id}' would be "
                                f"'{name}', which the batch writes itself ({reserved[key]}): "
                                "rename the line")
            elif key in taken and taken[key] is not line:
                other = taken[key]
                problems.append(f"row {line.row}, column id: '{line.id}' and '{other.id}' (row {other.row}) "
                                f"differ only in case, so their outputs '{name}' would overwrite each other on "
                                "Windows and macOS: rename one")
            taken.setdefault(key, line)


def output_name(line_id: str, kind: str) -> str:
    """The file name of a line's output of `kind` ('line1' and 'fbx_unreal': line1_unreal.fbx)."""
    return f"{line_id}{OUTPUT_SUFFIXES[kind]}"


def _rows(path: Path, problems: list[str]) -> Iterator[tuple[int, dict[str, Any]]]:
    """(row number, {column: cell}) of each non-blank row; unknown columns go to `problems`."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise DiffshegError(f"manifest '{path}' cannot be read ({exc}): save it as UTF-8 text") from None
    if path.suffix.lower() in (".jsonl", ".ndjson"):
        # split at newlines alone: JSON text may hold U+2028 and the like, which splitlines splits at
        for number, raw in enumerate(text.split("\n"), start=1):
            if not raw.strip():
                continue
            try:
                cells = json.loads(raw)
            except json.JSONDecodeError as exc:
                problems.append(f"row {number}: not a JSON object ({exc.msg} at character {exc.pos + 1})")
                continue
            if not isinstance(cells, dict):
                problems.append(f"row {number}: not a JSON object but {type(cells).__name__}")
                continue
            yield number, _known_columns(number, cells, problems)
        return
    reader = csv.reader(io.StringIO(text, newline=""))  # rows end at \n, \r\n or \r, never inside a cell
    header = next(reader, None)
    if header is None:
        return
    names = [name.strip() for name in header]
    seen: set[str] = set()
    for name in names:
        canonical = ALIASES.get(name, name)
        if name and canonical not in COLUMNS:
            problems.append(f"row 1 (header), column {name}: unknown column; the columns are "
                            f"{', '.join(COLUMNS)} (gesture_energy for skip_guidance)")
        elif canonical in seen:
            problems.append(f"row 1 (header), column {name}: the column is given twice")
        seen.add(canonical)
    if "id" not in seen or "audio" not in seen:
        problems.append("row 1 (header): the columns id and audio are required")
    row = 1
    for record in reader:
        row += 1
        if not any(cell.strip() for cell in record):
            continue
        if len(record) > len(names):
            problems.append(f"row {row}: {len(record)} cells but the header names {len(names)} columns")
            continue
        yield row, {ALIASES.get(n, n): cell for n, cell in zip(names, record)
                    if ALIASES.get(n, n) in COLUMNS}


def _known_columns(row: int, cells: dict, problems: list[str]) -> dict[str, Any]:
    out = {}
    for name, value in cells.items():
        canonical = ALIASES.get(name, name)
        if canonical not in COLUMNS:
            problems.append(f"row {row}, column {name}: unknown column; the columns are {', '.join(COLUMNS)}")
        elif canonical in out:
            problems.append(f"row {row}, column {name}: given twice (as {canonical} too)")
        else:
            out[canonical] = value
    return out


def _empty(value) -> bool:
    return value is None or (isinstance(value, str) and not value.strip())


def _defaults(defaults: Mapping[str, Any], problems: list[str]) -> dict[str, Any]:
    """The defaults every row starts from: the command line's values over the built-in ones,
    checked here (a bad default is reported once, not on every row)."""
    base: dict[str, Any] = dict(KEYING_DEFAULTS)
    given = {ALIASES.get(k, k): v for k, v in defaults.items()}
    for name in COLUMNS + SETTINGS_ONLY:
        if name in ("id", "audio") or _empty(given.get(name)):
            continue
        value = given[name]
        if name in SETTINGS_ONLY:
            base[name] = value
            continue
        try:
            base[name] = _parse(name, value, Path.cwd())
        except DiffshegError as exc:
            problems.append(f"defaults (command line), {name}: {exc}")
    if not _empty(base.get("model")) and isinstance(base["model"], (str, os.PathLike)):
        try:
            model = resolve_path(base["model"], "model file")
        except DiffshegError as exc:
            problems.append(f"defaults (command line), model: {exc}")
            return base
        if not model.is_file():
            problems.append(f"defaults (command line), model: '{model}' does not exist or is not a file")
        base["model"] = str(model)
    return base


def _line(row: int, cells: dict[str, Any], base: dict[str, Any], folder: Path, presets: Collection[str],
          style_names: Optional[Collection[str]], languages: Optional[Collection[str]],
          problems: list[str]) -> Optional[Line]:
    """The Line of one row, or None with its problems added to `problems`."""
    bad = len(problems)
    values = dict(base)
    for name, cell in cells.items():
        if _empty(cell):
            continue
        try:
            values[name] = _parse(name, cell, folder)
        except DiffshegError as exc:
            problems.append(f"row {row}, column {name}: {exc}")
    line_id = values.get("id")
    if _empty(cells.get("id")):
        problems.append(f"row {row}, column id: empty id: give every line a unique name")
    if values.get("audio") is None:
        if _empty(cells.get("audio")):
            problems.append(f"row {row}, column audio: no audio file given")
    elif _check_file(values["audio"], "audio", row, problems):
        try:
            probe_audio(values["audio"])
        except DiffshegError as exc:
            problems.append(f"row {row}, column audio: {exc}")
    outputs = values.get("outputs")
    if outputs is None and _empty(cells.get("outputs")):
        problems.append(f"row {row}, column outputs: none asked for: give some of {', '.join(OUTPUTS)} "
                        "(in the row or on the command line)")
    elif outputs and NEEDS_CHARACTER & set(outputs) and values.get("blend") is None:
        needs = ", ".join(o for o in outputs if o in NEEDS_CHARACTER)
        problems.append(f"row {row}, column blend: the outputs {needs} key the motion onto a character: "
                        "give its .blend")
    if values.get("blend") is not None and _check_file(values["blend"], "blend", row, problems):
        _check_blend(values["blend"], row, problems)
    preset = values.get("preset", AUTO_PRESET)
    if preset.lower().endswith(".json"):
        _check_file(Path(preset), "preset", row, problems)
    elif preset != AUTO_PRESET and preset not in presets:
        known = ", ".join(sorted(presets)) or "none"
        problems.append(f"row {row}, column preset: unknown preset '{preset}'; the presets are {known}, "
                        f"'{AUTO_PRESET}', or a preset .json file")
    if style_names is not None:
        for column in ("style", "style_at"):
            if values.get(column) is not None:
                _check_style_names(column, values[column], list(style_names), row, problems)
    if languages is not None and values.get("language") is not None and values["language"] not in languages:
        problems.append(f"row {row}, column language: the model has no face of its own for '{values['language']}' "
                        f"(it has: {', '.join(sorted(languages)) or 'none'}); leave the cell empty for its shared "
                        "face, which serves every language")
    settings = None
    try:
        settings = GenerateSettings(**{f.name: values[f.name] for f in fields(GenerateSettings)
                                       if values.get(f.name) is not None})
    except DiffshegError as exc:
        problems.append(f"row {row}, columns {', '.join(GENERATION)}: {exc}")
    if len(problems) > bad or settings is None:
        return None
    return Line(id=line_id, audio=values["audio"], settings=settings, blend=values.get("blend"),
                armature=values.get("armature"), face=values.get("face"), preset=preset,
                start_frame=values.get("start_frame"), max_error=values["max_error"],
                max_face_error=values["max_face_error"], every_frame=values["every_frame"],
                outputs=outputs, row=row)


def _check_file(path: Path, column: str, row: int, problems: list[str]) -> bool:
    """Whether `path` is a readable, non-empty regular file; a problem if not."""
    if not path.exists():
        why = "does not exist"
    elif not path.is_file():
        why = "is not a file"
    elif not os.access(path, os.R_OK):
        why = "cannot be read (check its permissions)"
    elif path.stat().st_size == 0:
        why = "is empty (0 bytes)"
    else:
        return True
    problems.append(f"row {row}, column {column}: '{path}' {why}")
    return False


BLEND_MAGIC = (b"BLENDER", b"\x1f\x8b", b"\x28\xb5\x2f\xfd")
"""How a .blend begins: plain, gzip-compressed (before 3.0) or zstd-compressed."""


def _check_blend(path: Path, row: int, problems: list[str]) -> None:
    """A problem unless `path` begins as a .blend file does."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        problems.append(f"row {row}, column blend: '{path}' cannot be read ({exc.strerror or exc})")
        return
    if not head.startswith(BLEND_MAGIC):
        problems.append(f"row {row}, column blend: '{path}' is not a Blender file: save the character "
                        "from Blender (File > Save As) and name that file")


def _check_style_names(column: str, value, names: list[str], row: int, problems: list[str]) -> None:
    specs = [style for _, style in value] if column == "style_at" else [value]
    problems += [f"row {row}, column {column}: {problem}" for spec in specs for problem in unknown_styles(spec, names)]


# ------------------------------------------------------------------ cells

_TRUE, _FALSE = ("1", "true", "yes", "y", "on"), ("0", "false", "no", "n", "off")
_NUMBERS = {name: (label, bounds, whole) for name, label, bounds, whole in settings_numbers
            if name in GENERATION}
"""The numeric generation settings: the name messages give them, bounds, whether whole (settings')."""
_NUMBERS.update({"seed": ("seed", (0, math.inf), True), "face_seed": ("face_seed", (0, math.inf), True),
                 "start_frame": ("start_frame", (-MAX_FRAME, MAX_FRAME), True),
                 "max_error": ("max_error (degrees)", (0.0, 180.0), False),
                 "max_face_error": ("max_face_error", (0.0, 1.0), False)})


def _number(name: str, value):
    """A numeric cell checked as GenerateSettings checks it: CSV text is read as the command
    line reads it (a whole number in digits, or a float), a JSON number as it is."""
    label, bounds, whole = _NUMBERS[name]
    if isinstance(value, str):
        text = value.strip()
        if whole:
            digits = parse_whole(text.removeprefix("-"))
            value = text if digits is None else (-digits if text.startswith("-") else digits)
        else:
            try:
                value = float(text)
            except ValueError:
                value = text
    elif whole and isinstance(value, float) and value.is_integer():
        value = int(value)  # JSON's 25.0
    return check_number(label, value, bounds, whole)


def _parse(name: str, value, folder: Path):
    """The value of one non-empty cell (a CSV string, or a JSON value); DiffshegError if bad."""
    if name in ("id", "armature"):
        text = _text(name, value)
        if name == "id":
            _check_id(text)
        return text
    if name in ("audio", "blend"):
        return _path(_text(name, value), folder, f"{name} file")
    if name == "preset":
        text = _text(name, value)
        return str(_path(text, folder, "preset file")) if text.lower().endswith(".json") else text
    if name == "face":
        names = value if isinstance(value, (list, tuple)) else _text(name, value).split(";")
        names = tuple(str(n).strip() for n in names if str(n).strip())
        return names or None
    if name == "outputs":
        kinds = value if isinstance(value, (list, tuple)) else _text(name, value).split(";")
        kinds = {str(k).strip().lower() for k in kinds if str(k).strip()}
        unknown = sorted(kinds - set(OUTPUTS))
        if unknown:
            raise DiffshegError(f"unknown output {', '.join(repr(k) for k in unknown)}; the outputs are "
                                f"{', '.join(OUTPUTS)}")
        if not kinds:
            raise DiffshegError(f"no output named: give some of {', '.join(OUTPUTS)}, separated by ';'")
        return tuple(k for k in OUTPUTS if k in kinds)
    if name in ("every_frame", "upper_body_only"):
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text in _TRUE or text in _FALSE:
            return text in _TRUE
        raise DiffshegError(f"{name} must be 1 or 0 (true/false, yes/no), got {value!r}")
    if name == "style":
        return check_style(_argument(parse_style, value) if isinstance(value, str) else value)
    if name == "style_at":
        return check_style_at(_argument(parse_style_at, value) if isinstance(value, str) else value)
    if name == "emotion":
        return check_emotion(value)
    if name == "sampling":
        return _sampling(value)
    if name == "language":
        return check_language(_text(name, value))
    if name == "emotion_at":
        return _check_emotion_at(_argument(parse_emotion_at, value) if isinstance(value, str) else value)
    if name in _NUMBERS:
        return _number(name, value)
    raise DiffshegError(f"unknown column {name}")


def _sampling(value) -> str:
    """A sampling's name (`--sampling`): fast, quality or an official preset, in any case."""
    from .foppas import PRESETS, SAMPLING_NAMES

    given = _text("sampling", value)
    if given.lower() not in SAMPLING_NAMES:
        raise DiffshegError(f"unknown sampling {given!r}: use fast (the default), quality (the model's own "
                            f"sampling, 25 steps) or an official preset ({', '.join(PRESETS)})")
    return given.lower()


def _text(name: str, value) -> str:
    if not isinstance(value, (str, int)) or isinstance(value, bool):
        raise DiffshegError(f"{name} must be text, got {value!r}")
    return str(value).strip()


def _check_id(text: str) -> None:
    """An id names the line's output files: no folders, no hidden names, no control
    characters or line breaks, short enough for a file name with its staged prefix."""
    if any(c in text for c in "/\\:") or text.startswith(".") \
            or any(unicodedata.category(c) in ("Cc", "Zl", "Zp") for c in text):
        raise DiffshegError(f"id {text!r} cannot name a file: use letters, digits, '-' and '_' "
                            "(no '/', '\\', ':', leading '.', control characters or line breaks)")
    size = len(text.encode("utf-8"))
    if size > MAX_ID_BYTES:
        raise DiffshegError(f"id '{text[:40]}...' is {size} bytes long, too long to name its files: "
                            f"keep ids to {MAX_ID_BYTES} bytes")


def _path(text: str, folder: Path, what: str) -> Path:
    path = Path(text).expanduser()
    return resolve_path(path if path.is_absolute() else folder / path, what)


def _argument(parse, text: str):
    """A command-line parser's value, its ArgumentTypeError as a DiffshegError."""
    import argparse

    try:
        return parse(text)
    except argparse.ArgumentTypeError as exc:
        raise DiffshegError(str(exc)) from None


def with_settings(line: Line, **changes) -> Line:
    """`line` with some generation settings changed (checked again)."""
    return replace(line, settings=replace(line.settings, **changes))
