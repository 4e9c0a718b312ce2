"""Praat TextGrid reader (long and short text formats) for timed words and phones."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ...errors import DiffshegError

_TOKEN = re.compile(r'"((?:[^"]|"")*)"|(-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)')
_INDEX = re.compile(r"\[\s*\d*\s*\]")


@dataclass(frozen=True)
class Interval:
    start: float
    end: float
    label: str

    @property
    def middle(self) -> float:
        return 0.5 * (self.start + self.end)


def _tokens(text: str) -> list[str | float]:
    """Quoted strings and numbers in file order; keys and bracketed indices dropped, which
    makes the long and the short format the same token stream."""
    out: list[str | float] = []
    for m in _TOKEN.finditer(_INDEX.sub(" ", text)):
        out.append(m.group(1).replace('""', '"') if m.group(1) is not None else float(m.group(2)))
    return out


def read_textgrid(path: str | Path) -> dict[str, list[Interval]]:
    """Tier name -> intervals (point tiers give zero-length intervals)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DiffshegError(f"{path}: cannot read TextGrid ({exc})") from exc
    for encoding in ("utf-8-sig", "utf-16"):
        try:
            text = raw.decode(encoding)
            break
        except UnicodeDecodeError:
            continue
    else:
        raise DiffshegError(f"{path}: TextGrid is neither UTF-8 nor UTF-16 text")
    tok = _tokens(text)
    try:
        if tok[:2] != ["ooTextFile", "TextGrid"]:
            raise ValueError("missing the 'ooTextFile' / 'TextGrid' header")
        pos, n_tiers = 5, int(tok[4])
        tiers: dict[str, list[Interval]] = {}
        for _ in range(n_tiers):
            kind, name, n = tok[pos], tok[pos + 1], int(tok[pos + 4])
            pos += 5
            if kind == "IntervalTier":
                tiers[name] = [Interval(float(tok[pos + 3 * i]), float(tok[pos + 3 * i + 1]),
                                        str(tok[pos + 3 * i + 2])) for i in range(n)]
                pos += 3 * n
            elif kind == "TextTier":
                tiers[name] = [Interval(float(tok[pos + 2 * i]), float(tok[pos + 2 * i]),
                                        str(tok[pos + 2 * i + 1])) for i in range(n)]
                pos += 2 * n
            else:
                raise ValueError(f"unknown tier class {kind!r}")
    except (IndexError, ValueError, TypeError) as exc:
        raise DiffshegError(f"{path}: not a Praat TextGrid in text format ({exc})") from exc
    return tiers


def phone_tier(tiers: dict[str, list[Interval]], path: str | Path = "TextGrid") -> list[Interval]:
    """The phone tier ('phones', 'phone' or 'phonemes', any case)."""
    for name, intervals in tiers.items():
        if name.lower() in ("phones", "phone", "phonemes"):
            return intervals
    raise DiffshegError(f"{path}: no phone tier (found tiers: {', '.join(tiers) or 'none'})")
