"""The checks every place that takes a setting shares: the bounds of the generation
settings and the checks of numbers, whole numbers spelt as text, sampling seeds and
changes over time (a style's, an emotion's). One
module that `settings` (GenerateSettings, the command lines), `foppas` (FoppasConfig, the
sampler's seeds), the manifest, the runtime's backends and the add-on's panel import, and
that imports none of them. Standard library only: the add-on registers without numpy
(numbers' ABCs take numpy's scalars too).
"""

from __future__ import annotations

import argparse
import math
import numbers
import re
from typing import Callable

from .errors import DiffshegError

STEPS = (1, 1000)
OVERLAP = (0, 64)
CANDIDATES = (1, 16)
GUIDANCE = (0.0, 10.0)
STYLE_GUIDANCE = (0.0, 10.0)
SKIP_GUIDANCE = (0.0, 1.0)
THREADS = (1, 256)
DEVICES = ("auto", "cpu", "cuda")
BACKENDS = ("auto", "onnx", "torch")
PRECISIONS = ("fp32", "bf16", "fp16")
LANGUAGE_CODE = re.compile(r"[a-z]{2,3}(-[a-z0-9]{2,8})*")  # BCP 47's shape, lower case: zh, yue, pt-br


def check_language(language) -> str:
    """A language code (zh, pt-br; any case) in lower case, else a DiffshegError."""
    if not isinstance(language, str) or not LANGUAGE_CODE.fullmatch(language.strip().lower()):
        raise DiffshegError(f"language must be a language code such as zh or pt-br (a language whose own face the "
                            f"model carries), got {language!r}")
    return language.strip().lower()


def check_number(name: str, value, bounds: tuple, whole: bool = False) -> int | float:
    """`value` as a plain int (`whole`) or float if it is a finite number within `bounds`
    (an upper bound of math.inf: none), else a DiffshegError. numpy numbers count as numbers."""
    lo, hi = bounds
    number = plain_number(value, whole)
    if number is None or not lo <= number <= hi:
        kind = "a whole number" if whole else "a number"
        span = f">= {lo:g}" if hi == math.inf else f"from {lo:g} to {hi:g}"
        raise DiffshegError(f"{name} must be {kind} {span}, got {value!r}")
    return number


def plain_number(value, whole: bool) -> int | float | None:
    """`value` as a Python int (`whole`) or finite float; None if it is no such number (a bool is not)."""
    # numbers' ABCs take numpy's scalars too, without importing numpy (the add-on registers without it)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral if whole else numbers.Real):
        return None
    if whole:
        return int(value)
    try:
        number = float(value)
    except OverflowError:  # an int beyond the floats
        return None
    return number if math.isfinite(number) else None


def parse_whole(text: str) -> int | None:
    """The whole number `text` spells in ASCII digits ('12', ' 12 '); None for anything else
    ('-1', '1.5', and digits str.isdigit takes but int() does not, such as '²')."""
    text = text.strip()
    return int(text) if text.isascii() and text.isdigit() else None


def check_seed(seed) -> int:
    """A sampling seed: any whole number >= 0 (numpy's SeedSequence takes integers of any size)."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise DiffshegError(f"seed must be a whole number >= 0, got {seed!r}")
    return int(seed)


def check_changes(changes, name: str, check: Callable, example: str) -> tuple | None:
    """Changes of `name` over time as ((seconds, check(value)), ...) sorted by time, each time
    a finite number >= 0 given once (one after the speech's end never takes effect); None for none."""
    try:
        items = [(_check_change_time(name, t, example), check(value))
                 for t, value in (changes.items() if isinstance(changes, dict) else changes)]
    except (TypeError, ValueError):
        raise DiffshegError(f"{name}_at must be (seconds, {name}) pairs, e.g. {example}, got {changes!r}") from None
    times = [t for t, _ in items]
    if len(set(times)) != len(times):
        raise DiffshegError(f"{name}_at gives {'an' if name[0] in 'aeiou' else 'a'} {name} twice for the same "
                            f"time: {sorted(times)}")
    return tuple(sorted(items, key=lambda item: item[0])) or None


def _check_change_time(name: str, seconds, example: str) -> float:
    """`seconds` as a float if it is a finite number >= 0; else a DiffshegError (inf and nan named)."""
    if isinstance(seconds, numbers.Real) and not isinstance(seconds, bool) and not _finite(seconds):
        raise DiffshegError(f"{name}_at: the {name} change time {seconds!r} is not a finite number of seconds: "
                            f"give the seconds from the start of the speech, e.g. {example}")
    return check_number(f"{name} change time (seconds)", seconds, (0.0, math.inf))


def _finite(number: numbers.Real) -> bool:
    """Whether `number` is finite (an int beyond the floats is)."""
    try:
        return math.isfinite(number)
    except OverflowError:
        return True


def parse_changes(text: str, form: str, example: str, parse: Callable) -> tuple:
    """Changes over time as the command line spells them, SECONDS=NAME[=WEIGHT], an item
    without seconds joining the mix before it; each time's mix read by `parse` (which raises
    argparse.ArgumentTypeError, as this does)."""
    entries: list[list] = []
    for part in text.split(","):
        key, _, rest = part.strip().partition("=")
        try:
            seconds = float(key)
        except ValueError:
            seconds = None
        if seconds is not None and not math.isfinite(seconds):
            raise argparse.ArgumentTypeError(f"{part.strip()!r} in {text!r}: {key.strip()} is not a finite number "
                                             f"of seconds; give the seconds from the start of the speech (e.g. "
                                             f"{example})")
        if seconds is not None and rest:
            entries.append([seconds, [rest]])
        elif entries and rest:
            entries[-1][1].append(part.strip())
        else:
            raise argparse.ArgumentTypeError(f"{part.strip()!r} in {text!r} is not {form} (e.g. {example})")
    return tuple((seconds, parse(",".join(parts))) for seconds, parts in entries)
