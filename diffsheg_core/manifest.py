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
    style, style_at, emotion, emotion_at, seed, face_seed, steps, overlap, candidates,
    guidance, skip_guidance (or gesture_energy), style_guidance, upper_body_only (1/0)
                  the generation settings, spelt as on the command line (`--style calm=0.7,
                  animated=0.3`, `--style-at 0=calm,12.5=animated`, `--emotion sad=0.6`,
                  `--emotion-at 0=happy,12.5=sad`) and checked by
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

`line_key` fingerprints a line's inputs (see there) and `Ledger` records the lines done in
`out_dir/done.jsonl`, so a rerun skips what is done and redoes what changed.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import secrets
import time
import unicodedata
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Collection, Iterable, Iterator, Mapping, Optional

from .audio import probe_audio
from .emotion import check_emotion
from .errors import DiffshegError
from .files import resolve_path
from .settings import (
    _NUMBERS as settings_numbers, GenerateSettings, _check_emotion_at, _check_style, _check_style_at, check_number,
    parse_emotion_at, parse_style, parse_style_at, parse_whole,
)

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
GENERATION = ("style", "style_at", "emotion", "emotion_at", "seed", "face_seed", "steps", "overlap",
              "candidates", "guidance", "skip_guidance", "style_guidance", "upper_body_only")
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
                  style_names: Optional[Collection[str]] = None) -> list[Line]:
    """The checked lines of the manifest at `path` (CSV, or JSON Lines for .jsonl/.ndjson).

    `defaults`: values for cells a row leaves empty, by column name or GenerateSettings field
    (e.g. `vars(args)` of batch_render.py: keys that are neither are ignored); `face` may be
    a list. `presets`: the preset names there are. `style_names`: the model's style names
    (None: not checked here; the model checks them when it runs).
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
        line = _line(row, cells, base, folder, presets, style_names, problems)
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
          style_names: Optional[Collection[str]], problems: list[str]) -> Optional[Line]:
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
    for spec in specs:
        for key in (spec if isinstance(spec, dict) else [spec]):
            if isinstance(key, str) and key not in names:
                problems.append(f"row {row}, column {column}: unknown style '{key}'; the model's styles are "
                                f"{', '.join(names) or 'none'}")
            elif isinstance(key, int) and not 0 <= key < len(names):
                problems.append(f"row {row}, column {column}: style index {key} is out of range; the model "
                                f"has {len(names)} styles (0-{len(names) - 1})")


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
        return _check_style(_argument(parse_style, value) if isinstance(value, str) else value)
    if name == "style_at":
        return _check_style_at(_argument(parse_style_at, value) if isinstance(value, str) else value)
    if name == "emotion":
        return check_emotion(value)
    if name == "emotion_at":
        return _check_emotion_at(_argument(parse_emotion_at, value) if isinstance(value, str) else value)
    if name in _NUMBERS:
        return _number(name, value)
    raise DiffshegError(f"unknown column {name}")


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


# ------------------------------------------------------------------ identity

KEY_CHUNK = 1 << 20  # the model file is identified by its size and its first and last MiB


def file_digest(path, chunk: int = KEY_CHUNK) -> str:
    """sha256 of a whole file's bytes (read `chunk` bytes at a time)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def model_identity(model=None) -> str:
    """A cheap identity of the model file (None: the bundled default): its size and a
    sha256 of its first and last MiB. Retraining changes the weights throughout, so the
    head and tail change with it; reading two MiB keeps this instant for any model size.
    (A model given as a loaded bundle is identified by its model id, if it has one.)"""
    if model is not None and not isinstance(model, (str, os.PathLike)):
        return f"bundle:{getattr(model, 'model_id', type(model).__name__)}"
    if model is None:
        from .checkpoints import DEFAULT_WEIGHTS

        path = DEFAULT_WEIGHTS
    else:
        path = Path(model).expanduser()
    try:
        size = path.stat().st_size
        digest = hashlib.sha256()
        with open(path, "rb") as fh:
            digest.update(fh.read(KEY_CHUNK))
            if size > KEY_CHUNK:
                fh.seek(max(KEY_CHUNK, size - KEY_CHUNK))
                digest.update(fh.read(KEY_CHUNK))
    except OSError as exc:
        raise DiffshegError(f"model file '{path}' cannot be read ({exc.strerror or exc})") from None
    return f"{size}:{digest.hexdigest()}"


KEY_IGNORES = ("model", "threads")
"""Settings that do not enter a line's key as values: the model enters as its file's
identity, and the thread count does not change the result."""


def line_key(line: Line, digests: Optional[dict] = None) -> str:
    """sha256 (hex) over everything that decides a line's outputs: the audio file's bytes,
    the .blend's bytes (and a preset .json's), every generation setting but the thread count,
    the character and keying fields, the outputs, the software version and the model file's
    identity (`model_identity`). Not the id, nor where the files lie. `digests`: what
    earlier calls hashed (see `line_keys`)."""
    from . import __version__

    digests = {} if digests is None else digests

    def digest(what: str, path, make) -> str:
        if (what, str(path)) not in digests:
            digests[what, str(path)] = make(path)
        return digests[what, str(path)]

    s = line.settings
    settings = {f.name: getattr(s, f.name) for f in fields(s) if f.name not in KEY_IGNORES}
    preset = line.preset
    if preset.lower().endswith(".json"):
        preset = "json:" + digest("file", preset, file_digest)
    by_path = s.model is None or isinstance(s.model, (str, os.PathLike))  # else a loaded bundle, by its id
    record = {
        "version": __version__,
        "model": digest("model", s.model, model_identity) if by_path else model_identity(s.model),
        "audio": digest("file", line.audio, file_digest),
        "blend": None if line.blend is None else digest("file", line.blend, file_digest),
        "settings": settings,
        "armature": line.armature, "face": line.face, "preset": preset,
        "start_frame": line.start_frame, "max_error": line.max_error, "max_face_error": line.max_face_error,
        "every_frame": line.every_frame, "outputs": list(line.outputs),
    }
    text = json.dumps(record, sort_keys=True, default=_jsonable, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def line_keys(lines: Iterable[Line]) -> dict[str, str]:
    """`line_key` of each line by id, hashing each file once however many lines name it: a
    10,000-line rerun of one character reads its .blend once, not 10,000 times."""
    digests: dict = {}
    return {line.id: line_key(line, digests) for line in lines}


def _jsonable(value):
    if isinstance(value, (tuple, set, frozenset)):
        return list(value)
    return repr(value)


# ------------------------------------------------------------------ ledger

class Ledger:
    """The lines done in a batch's output folder: `out_dir/done.jsonl`, one JSON object per
    line done ({"id", "key", "outputs", "time"}, and "staged"), appended and fsynced by the
    one driver process. A line is done when the ledger holds its id with its current key;
    a torn last line (a driver killed mid-write) is ignored, so that line is redone, and
    a record with key null (`forget`) undoes the ones before it.

    Each attempt at a line writes its outputs whole as hidden files beside their final
    names in `out_dir` (`staged_path`: the same folder, so relative paths saved in a .blend
    or an FBX resolve alike from both names), and `commit` records the line (naming the
    attempt) before renaming its files into place: the record is the commit point. A
    driver killed before it leaves no output of the line under its final name; killed
    after it, the next driver's `recover` finishes the renames. Either way every output in
    `out_dir` belongs to a line recorded done, and `recover` removes what unfinished
    attempts left. An output that cannot be put in place (a folder at its name) fails its
    line alone: recorded, it is put in place by the next run, or the line is forgotten and
    done again there when it still cannot be."""

    NAME = "done.jsonl"
    STAGED = ".staged-"

    def __init__(self, out_dir):
        self.out_dir = Path(out_dir)
        self.path = self.out_dir / self.NAME
        self._done: dict[str, dict] = {}   # id -> its latest whole entry
        self._load()

    def _load(self) -> None:
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return
        except OSError as exc:
            raise DiffshegError(f"the ledger '{self.path}' cannot be read ({exc.strerror or exc})") from None
        for raw in data.split(b"\n"):
            try:
                entry = json.loads(raw.decode("utf-8"))
                line_id, key = entry["id"], entry["key"]
            except (UnicodeDecodeError, json.JSONDecodeError, TypeError, KeyError):
                continue  # blank, or torn by a kill: that line was not recorded
            if isinstance(line_id, str) and isinstance(key, str):
                self._done[line_id] = entry
            elif isinstance(line_id, str) and key is None:
                self._done.pop(line_id, None)  # forgotten

    def key(self, line_id: str) -> Optional[str]:
        """The key the line was last recorded with; None if never."""
        entry = self._done.get(line_id)
        return None if entry is None else entry["key"]

    def done(self, line: Line, key: Optional[str] = None) -> bool:
        """Whether `line` is recorded with the same id and key (`key`: its line_key, if known)."""
        recorded = self.key(line.id)
        return recorded is not None and recorded == (key if key is not None else line_key(line))

    def record(self, line: Line, outputs: Iterable, key: Optional[str] = None, staged: Optional[str] = None) -> str:
        """Record `line` as done with its `outputs` (paths; `staged`: the attempt whose
        staged files they still are, see `commit`); its key."""
        key = key if key is not None else line_key(line)
        entry = {"id": line.id, "key": key, "outputs": [str(o) for o in outputs],
                 "time": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        if staged is not None:
            entry["staged"] = staged
        self._append(entry)
        self._done[line.id] = entry
        return key

    def forget(self, line_id: str) -> None:
        """Record line `line_id` as not done (a null key), so the next check redoes it."""
        self._append({"id": line_id, "key": None, "time": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
        self._done.pop(line_id, None)

    def _append(self, entry: dict) -> None:
        """Append `entry` as one JSON line and fsync it."""
        data = (json.dumps(entry, ensure_ascii=False) + "\n").encode("utf-8")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
            try:
                if os.fstat(fd).st_size and not self._ends_with_newline():
                    data = b"\n" + data  # a torn last line stays a line of its own
                os.write(fd, data)
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError as exc:
            raise DiffshegError(f"the ledger '{self.path}' could not be written ({exc.strerror or exc}): "
                                "free some disk space; the line will be redone next run") from None

    def _ends_with_newline(self) -> bool:
        with open(self.path, "rb") as fh:
            fh.seek(-1, os.SEEK_END)
            return fh.read(1) == b"\n"

    def commit(self, line: Line, staged: str, outputs: Iterable, key: Optional[str] = None) -> str:
        """Record `line` as done, then rename its `outputs` (their final paths in
        `out_dir`) from the files attempt `staged` wrote them whole to into place; its key.
        DiffshegError naming the output if one cannot be put in place (see `recover`)."""
        outputs = [Path(o) for o in outputs]
        key = self.record(line, outputs, key, staged=staged)
        self._move_in_place(staged, outputs)
        return key

    def recover(self) -> list[str]:
        """Finish the renames of lines recorded before they were done (a killed driver, an
        output that could not be put in place); a line whose outputs still cannot be is
        forgotten, to be done again. Then `clean_staging`. Returns one message per line
        forgotten."""
        problems = []
        for line_id, entry in list(self._done.items()):
            staged = entry.get("staged")
            if not isinstance(staged, str):
                continue
            try:
                self._move_in_place(staged, [Path(o) for o in entry["outputs"]])
            except DiffshegError as exc:
                self.forget(line_id)
                problems.append(f"{line_id}: {exc}; doing the line again")
        self.clean_staging()
        return problems

    def clean_staging(self) -> None:
        """Remove the staged files of attempts not recorded and the temporary files of
        writers killed mid-write (`.NAME.partial...`); no line may be under way. The staged
        files of recorded lines stay for `recover` to put in place."""
        kept = tuple(f"{self.STAGED}{e['staged']}." for e in self._done.values() if isinstance(e.get("staged"), str))
        for path in [*self.out_dir.glob(f"{self.STAGED}*"), *self.out_dir.glob(".*.partial*")]:
            if path.name.startswith(kept) or not path.is_file():
                continue
            try:
                path.unlink(missing_ok=True)
            except OSError as exc:
                raise DiffshegError(f"cannot remove the unfinished output '{path}' ({exc.strerror or exc}): "
                                    "remove it by hand") from None

    def _move_in_place(self, staged: str, outputs: list[Path]) -> None:
        """Each output attempt `staged` wrote to its final name (os.replace: atomic)."""
        for output in outputs:
            source, target = staged_path(self.out_dir, staged, output.name), self.out_dir / output.name
            if not source.is_file():
                continue  # put in place before
            try:
                os.replace(source, target)
            except OSError as exc:
                raise DiffshegError(f"cannot put {output.name} in place in '{self.out_dir}' "
                                    f"({exc.strerror or exc}): remove or rename what is at '{target}'; "
                                    "the next run puts it there") from None


def stage_name() -> str:
    """A new name for one attempt at a line to stage its outputs under (see Ledger); each
    attempt has its own, so a retried line starts clean. It does not hold the line's id,
    which the staged files' names hold once already (see MAX_ID_BYTES)."""
    return secrets.token_hex(8)


def staged_path(out_dir, staged: str, name: str) -> Path:
    """Where attempt `staged` writes the output `out_dir/name` before it is put in place:
    a hidden file in the same folder."""
    return Path(out_dir) / f"{Ledger.STAGED}{staged}.{name}"


def with_settings(line: Line, **changes) -> Line:
    """`line` with some generation settings changed (checked again)."""
    return replace(line, settings=replace(line.settings, **changes))
