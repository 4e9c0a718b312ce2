"""The checks every place that takes a setting shares: the bounds of the generation
settings and the checks of numbers, whole numbers spelt as text and sampling seeds. One
module that `settings` (GenerateSettings, the command lines), `foppas` (FoppasConfig, the
sampler's seeds), the manifest, the runtime's backends and the add-on's panel import, and
that imports none of them. Standard library only: the add-on registers without numpy
(numbers' ABCs take numpy's scalars too).
"""

from __future__ import annotations

import math
import numbers

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


def check_number(name: str, value, bounds: tuple, whole: bool = False) -> int | float:
    """`value` as a plain int (`whole`) or float if it is a finite number within `bounds`
    (an upper bound of math.inf: none), else a DiffshegError. numpy numbers count as numbers."""
    lo, hi = bounds
    number = _plain_number(value, whole)
    if number is None or not lo <= number <= hi:
        kind = "a whole number" if whole else "a number"
        span = f">= {lo:g}" if hi == math.inf else f"from {lo:g} to {hi:g}"
        raise DiffshegError(f"{name} must be {kind} {span}, got {value!r}")
    return number


def _plain_number(value, whole: bool) -> int | float | None:
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
