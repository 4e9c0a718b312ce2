"""The text the corpus speaks: Debian's fortune cookies (package `fortunes`), cleaned and
cut into utterances of a few seconds each."""

from __future__ import annotations

import re
from pathlib import Path

from ...errors import DiffshegError

FORTUNES_DIR = Path("/usr/share/games/fortunes")
_SKIP_FILES = {"art", "ascii-art", "translate-me", "perl"}
"""Pictures, non-English text and code."""

MIN_WORDS, MAX_WORDS = 6, 40
"""Utterance length: about 2 to 15 seconds at a conversational rate."""

_ATTRIBUTION = re.compile(r"^\s*(--|~~)\s")
_OVERSTRIKE = re.compile(r"_\x08")
"""Underlining by overstrike, as old fortunes write it."""
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")
_SENTENCE_END = re.compile(r"(?<=[.!?])[\"')\]]*\s+")


def fortune_files(directory: Path = FORTUNES_DIR) -> list[Path]:
    """The English fortune text files (not their .dat indices or .u8 links)."""
    if not directory.is_dir():
        raise DiffshegError(f"{directory} does not exist: install the text source with "
                            "`apt-get install fortunes`, or pass your own text files with --text")
    return sorted(p for p in directory.iterdir()
                  if p.is_file() and not p.suffix and p.name not in _SKIP_FILES)


def _is_prose(entry: str) -> bool:
    chars = [c for c in entry if not c.isspace()]
    return bool(chars) and sum(c.isalpha() for c in chars) / len(chars) > 0.8


def _clean(entry: str) -> str:
    lines = [ln for ln in entry.splitlines() if not _ATTRIBUTION.match(ln)]
    text = _CONTROL.sub("", _OVERSTRIKE.sub("", " ".join(lines)))
    return " ".join(text.split())


def split_utterances(text: str) -> list[str]:
    """Cut prose into utterances of MIN_WORDS..MAX_WORDS words at sentence ends (at commas,
    then anywhere, for longer sentences); shorter leftovers are dropped."""
    pieces: list[str] = []
    for sentence in _SENTENCE_END.split(text):
        words = sentence.split()
        while len(words) > MAX_WORDS:
            cut = max((i for i in range(MIN_WORDS, MAX_WORDS) if words[i - 1][-1] in ",;:"),
                      default=MAX_WORDS)
            pieces.append(" ".join(words[:cut]))
            words = words[cut:]
        if words:
            pieces.append(" ".join(words))
    out: list[str] = []
    current: list[str] = []
    for piece in pieces:
        n = len(piece.split())
        if current and len(" ".join(current).split()) + n > MAX_WORDS:
            out.append(" ".join(current))
            current = []
        current.append(piece)
    if current:
        out.append(" ".join(current))
    return [u for u in out if len(u.split()) >= MIN_WORDS]


def load_texts(paths: list[Path] | None = None) -> list[str]:
    """Utterance texts from fortune-format files (entries separated by lines of '%';
    plain text files work too). Default: all English fortunes."""
    files = fortune_files() if paths is None else [Path(p) for p in paths]
    texts: list[str] = []
    for path in files:
        try:
            raw = path.read_text(encoding="utf-8", errors="replace")
        except OSError as exc:
            raise DiffshegError(f"{path}: cannot read text source ({exc})") from exc
        for entry in re.split(r"^%\s*$|\n\s*\n", raw, flags=re.M):
            if _is_prose(entry):
                texts.extend(split_utterances(_clean(entry)))
    if not texts:
        raise DiffshegError(f"no usable English prose in {', '.join(map(str, files))}")
    return texts
