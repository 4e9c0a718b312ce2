"""Timed phones in one shared alphabet (ARPAbet without stress digits, `SIL` for pauses),
whatever made them: espeak-ng, festival, flite, or a forced aligner's TextGrid."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import DiffshegError
from ...phonetic import ARPABET, SILENCE, VOWELS  # the one phone alphabet



@dataclass(frozen=True)
class Phone:
    """One phone: ARPAbet `label`, times in seconds, lexical `stress`
    (1 primary, 2 secondary, 0 unstressed or a consonant, -1 unknown)."""

    label: str
    start: float
    end: float
    stress: int = -1

    @property
    def middle(self) -> float:
        return 0.5 * (self.start + self.end)

    @property
    def is_vowel(self) -> bool:
        return self.label in VOWELS


# espeak-ng English phoneme mnemonics (phsource/ph_english*) -> ARPAbet.
_ESPEAK = {
    "@": "AH", "@-": "AH", "@2": "AH", "@5": "AH", "@L": "AH", "@r": "ER", "3": "ER", "3:": "ER",
    "a": "AE", "a#": "AH", "aa": "AA", "A:": "AA", "A@": "AA", "A": "AA", "a:": "AA",
    "aI": "AY", "aI@": "AY", "aI3": "AY", "aU": "AW", "aU@": "AW",
    "e": "EH", "E": "EH", "E2": "EH", "E3": "EH", "e@": "EH", "eI": "EY", "e#": "EH",
    "i": "IY", "i:": "IY", "i@": "IH", "i@3": "IH", "I": "IH", "I2": "IH", "I#": "IH", "i#": "IY",
    "0": "AA", "0#": "AA", "O": "AO", "O:": "AO", "O@": "AO", "o@": "AO", "OI": "OY", "o": "OW",
    "oU": "OW", "oU#": "OW", "O2": "AO",
    "u:": "UW", "u": "UW", "U": "UH", "U@": "UH", "u@": "UH", "V": "AH", "VR": "ER", "y": "UW",
    "p": "P", "b": "B", "t": "T", "d": "D", "k": "K", "g": "G", "f": "F", "v": "V",
    "T": "TH", "D": "DH", "s": "S", "z": "Z", "S": "SH", "Z": "ZH", "h": "HH", "tS": "CH",
    "dZ": "JH", "m": "M", "n": "N", "N": "NG", "l": "L", "r": "R", "w": "W", "j": "Y",
    "t#": "T", "d#": "D", "n-": "N", "m-": "M", "l/": "L", "r-": "R", "x": "HH", "?": "T",
    "*": "R", "l#": "L", "z#": "Z", "s#": "S", "w#": "W",
}

# festival's US phone set (radio, also flite's) -> ARPAbet.
_FESTIVAL = {
    "ax": "AH", "axr": "ER", "el": "L", "em": "M", "en": "N", "dx": "T", "hv": "HH",
    "ix": "IH", "nx": "N", "pau": SILENCE, "h#": SILENCE, "brth": SILENCE, "#": SILENCE,
}


# Other languages' espeak-ng mnemonics (phsource/ph_*: Kirshenbaum letters, X-SAMPA for
# Japanese) -> the ARPAbet phone whose mouth is nearest: lip closure (p b m, and the
# bilabial fricatives' near closure as F/V), rounding (front rounded vowels go to the
# rounded ones) and openness; the tongue-only contrasts English lacks (retroflex, dental,
# palatal, uvular, aspiration, length, tone, nasality) fall together.
_ESPEAK_WORLD = {
    "a": "AA", "A": "AA", "a#": "AH", "&": "AE", "@": "AH", "3": "AH", "V": "AH", "7": "AH",
    "e": "EY", "E": "EH", "i": "IY", "I": "IH", "1": "IH", "o": "OW", "O": "AO", "0": "AA",
    "u": "UW", "U": "UH", "y": "UW", "Y": "UH", "W": "ER", "8": "UH", "Q": "G",
    "aI": "AY", "ai": "AY", "aU": "AW", "au": "AW", "eI": "EY", "EI": "EY", "ei": "EY",
    "oU": "OW", "ou": "OW", "OI": "OY", "oI": "OY", "Wy": "OY", "VU": "AW", "eU": "EH",
    "iE": "IY", "iu": "UW", "u@": "UW", "y@": "UW", "o@": "AO", "ong": "UH", "yu": "UW",
    "ja": "AA", "ju": "UW", "jo": "OW", "je": "EH",
    "B": "V", "p\\": "F", "C": "HH", "x": "HH", "X": "HH", "H": "HH", "h": "HH", "q": "K",
    "gH": "G", "c": "K", "J": "D", "n^": "N", "l^": "L", "L": "L", "R": "R", "**": "R",
    "r`": "R", "t_s": "S", "ts": "S", "dz": "Z", "t_s\\": "CH", "d_z\\": "JH", "s\\": "SH",
    "z\\": "ZH", "s.": "SH", "z.": "ZH", "ts.": "CH", "tS.": "CH", "ts;": "CH", "dz;": "JH",
    "sx": "SH", "S;": "SH", "Z;": "ZH", "pf": "P", "ss": "S", "t.": "T", "d.": "D", "n.": "N", "r.": "R",
    "dH": "DH", "?": "T", "!": "T",
}
_MODIFIERS = ":#;~\"-_\\`^[.!'"
"""Length, aspiration, palatalisation, nasality, retroflexion and the like, after the letter."""


def _without_tone(symbol: str) -> str:
    """The mnemonic without a tone's trailing digits (Mandarin `a55`, Vietnamese `e3`),
    keeping a digit that is the vowel itself (`011` is `0` with tone 11)."""
    while len(symbol) > 1 and symbol[-1].isdigit():
        symbol = symbol[:-1]
    return symbol


def _from_espeak_world(symbol: str) -> str | None:
    base = _without_tone(symbol.lstrip("?") or symbol)
    for candidate in (base, base.rstrip(_MODIFIERS), base.strip(_MODIFIERS)):
        if candidate in _ESPEAK_WORLD:
            return _ESPEAK_WORLD[candidate]
        if candidate in _ESPEAK:
            return _ESPEAK[candidate]
    return None


def from_espeak(symbol: str, language: str = "en") -> str:
    """ARPAbet label of an espeak-ng phoneme mnemonic of `language` (the voice's language
    code, e.g. 'en-us', 'de', 'cmn'); pauses (`_`, `_:`...) are SIL."""
    if symbol == "" or symbol.startswith("_") or symbol.startswith("|"):
        return SILENCE
    if not language.startswith("en"):
        label = _from_espeak_world(symbol)
        if label is not None:
            return label
        stripped = _without_tone(symbol).strip(_MODIFIERS)
        return "AH" if stripped and stripped[0] in "aeiouAEIOUVy@0381&W7" else "T"
    if symbol in _ESPEAK:
        return _ESPEAK[symbol]
    stripped = symbol.rstrip("#-:/23[;")
    if stripped in _ESPEAK:
        return _ESPEAK[stripped]
    # unseen variants: judge by the first character (a vowel letter gives the neutral AH)
    return "AH" if stripped[:1] in "aeiouAEIOUV@03" else "T"


def from_festival(symbol: str) -> str:
    """ARPAbet label of a festival segment name."""
    if symbol in _FESTIVAL:
        return _FESTIVAL[symbol]
    label = symbol.upper()
    if label not in ARPABET:
        raise DiffshegError(f"festival phone {symbol!r} is not in the US phone set this corpus maps")
    return label


def from_festival_segments(segments: list[tuple[str, float, bool]]) -> list[Phone]:
    """Phones from festival / flite segments given as (name, end time, in a stressed
    syllable), in order; each starts where the one before ended, empty ones are dropped,
    and only vowels keep the stress."""
    phones, start = [], 0.0
    for name, end, stressed in segments:
        if end > start:
            label = from_festival(name)
            phones.append(Phone(label, start, end, int(stressed) if label in VOWELS else 0))
            start = end
    return phones


_ARPA_STRESS = re.compile(r"^([A-Z]+)([012])?$")


def from_arpabet(symbol: str) -> tuple[str, int]:
    """(label, stress) of an aligner phone such as 'AA1'; silence marks give SIL."""
    s = symbol.strip().upper()
    if s in ("", "SIL", "SP", "SPN", "<SIL>", "<EPS>"):
        return SILENCE, 0
    m = _ARPA_STRESS.match(s)
    if not m or m.group(1) not in ARPABET:
        raise DiffshegError(f"phone {symbol!r} is not ARPAbet; the teacher needs ARPAbet phones")
    return m.group(1), int(m.group(2)) if m.group(2) else (-1 if m.group(1) in VOWELS else 0)


def phones_from_textgrid(path: str | Path) -> list[Phone]:
    """The phone tier of a forced-alignment TextGrid (e.g. Montreal Forced Aligner) as Phones."""
    from ..metrics.textgrid import phone_tier, read_textgrid

    out = []
    for iv in phone_tier(read_textgrid(path), path):
        if iv.end > iv.start:
            label, stress = from_arpabet(iv.label)
            out.append(Phone(label, iv.start, iv.end, stress))
    check_phones(out)
    return out


def check_phones(phones: list[Phone]) -> None:
    """Raise unless the phones are non-empty, in time order, not overlapping, in ARPAbet."""
    if not phones:
        raise DiffshegError("no phones: the synthesiser or aligner produced an empty phone list")
    prev_end = 0.0
    for p in phones:
        if p.label not in ARPABET:
            raise DiffshegError(f"phone label {p.label!r} is not ARPAbet")
        if p.start < prev_end - 1e-6 or p.end <= p.start:
            raise DiffshegError(
                f"phone {p.label} at {p.start:.3f}-{p.end:.3f} s overlaps or precedes the one before "
                f"(ending {prev_end:.3f} s): phone timings must be increasing")
        prev_end = p.end


def merge_silences(phones: list[Phone]) -> list[Phone]:
    """Join neighbouring SIL phones into one."""
    out: list[Phone] = []
    for p in phones:
        if out and p.label == SILENCE and out[-1].label == SILENCE:
            out[-1] = Phone(SILENCE, out[-1].start, p.end, 0)
        else:
            out.append(p)
    return out


def extend_to(phones: list[Phone], end: float) -> list[Phone]:
    """The phones with the time up to `end` (s) covered by a pause: the last pause is
    stretched, or one appended."""
    last = phones[-1]
    if last.end >= end:
        return list(phones)
    if last.label == SILENCE:
        return phones[:-1] + [Phone(SILENCE, last.start, end, 0)]
    return phones + [Phone(SILENCE, last.end, end, 0)]


def phones_to_arrays(phones: list[Phone]) -> dict[str, np.ndarray]:
    """The npz form: phone_labels, phone_start, phone_end, phone_stress."""
    return {
        "phone_labels": np.array([p.label for p in phones], dtype=np.str_),
        "phone_start": np.array([p.start for p in phones], dtype=np.float64),
        "phone_end": np.array([p.end for p in phones], dtype=np.float64),
        "phone_stress": np.array([p.stress for p in phones], dtype=np.int8),
    }


def phones_from_arrays(z) -> list[Phone]:
    """Inverse of `phones_to_arrays` (takes any mapping, e.g. an open npz)."""
    return [Phone(str(l), float(s), float(e), int(st)) for l, s, e, st in zip(
        z["phone_labels"], z["phone_start"], z["phone_end"], z["phone_stress"])]
