"""The crash-safe ledger of a batch: which lines of a manifest are done, and their outputs
put in place whole.

`line_key` fingerprints a line's inputs (see there) and `Ledger` records the lines done in
`out_dir/done.jsonl`, so a rerun skips what is done and redoes what changed. Each attempt
at a line writes its outputs as hidden staged files (`stage_name`, `staged_path`) that
`Ledger.commit` puts in place after recording the line; `Ledger.recover` finishes what a
killed driver left. The manifest itself (reading and checking its rows) is `manifest`.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import time
from dataclasses import fields
from pathlib import Path
from typing import Iterable, Optional

from .errors import DiffshegError
from .manifest import Line


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
    which the staged files' names hold once already (see manifest.MAX_ID_BYTES)."""
    return secrets.token_hex(8)


def staged_path(out_dir, staged: str, name: str) -> Path:
    """Where attempt `staged` writes the output `out_dir/name` before it is put in place:
    a hidden file in the same folder."""
    return Path(out_dir) / f"{Ledger.STAGED}{staged}.{name}"
