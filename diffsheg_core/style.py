"""The gesture style: one of a model's style classes, a mix of them, and how it changes over time.

A style is given as a class index, a style name, or weights over indices or names
({"calm": 0.7, "animated": 0.3}): a `StyleSpec`. Its form is checked where settings are
made (`check_style`, `check_style_at`, and `parse_style` / `parse_style_at` for the command
line's spelling); against a model it becomes class weights summing to 1 (`style_weights`),
the model's style input a mix of one-hots (`style_vector`), and over a take's frames a
`StyleTrack` (`style_track`), the style travelling with the speech features in a
`conditioning.Conditioning`.
"""

from __future__ import annotations

import argparse
import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable, Optional, Union

import numpy as np

from .errors import DiffshegError
from .validate import STYLE_GUIDANCE, check_changes, check_number, parse_changes, parse_whole, plain_number

if TYPE_CHECKING:  # checkpoints imports this module (style_names_fit)
    from .checkpoints import ModelBundle

StyleSpec = Union[int, str, dict]
"""A style: a class index, a style name, or weights over indices or names."""

StyleChanges = tuple[tuple[float, StyleSpec], ...]
"""A style over time: ((seconds, style), ...), each style from its time on."""


# ---------------------------------------------------------------- the form of a style

def check_style(style) -> StyleSpec:
    """`style` if it has the form of a style (a numpy integer as an int), its weights finite
    numbers >= 0; which styles a model has is checked against the model (`style_weights`)."""
    if isinstance(style, numbers.Integral) and not isinstance(style, bool):
        return int(style)
    if isinstance(style, bool) or not isinstance(style, (int, str, dict)):
        raise DiffshegError(f"style must be a style index, a style name or weights over styles "
                            f"(e.g. {{'calm': 0.7, 'animated': 0.3}}), got {style!r}")
    if isinstance(style, dict):
        for name, weight in style.items():
            if plain_number(weight, whole=False) is None or weight < 0:
                raise DiffshegError(f"the weight of style {name!r} must be a finite number >= 0, got {weight!r}: "
                                    "give weights such as calm=0.7,animated=0.3 (only their ratio counts)")
    return style


def check_style_at(changes) -> Optional[StyleChanges]:
    """Style changes over time, checked and sorted by time (`validate.check_changes`); None for none."""
    return check_changes(changes, "style", check_style, "((0, 'calm'), (12.5, 'animated'))")


def parse_style(text: str) -> StyleSpec:
    """'2' -> 2, 'calm' -> 'calm', 'calm=0.7,animated=0.3' -> {'calm': 0.7, 'animated': 0.3}."""
    text = text.strip()
    if "=" not in text:
        index = parse_whole(text)
        return text if index is None else index
    weights: dict = {}
    for part in text.split(","):
        name, _, value = part.partition("=")
        name = name.strip()
        if name in weights:
            raise argparse.ArgumentTypeError(f"style {name!r} is given twice in {text!r}: give each style "
                                             "one weight")
        try:
            weights[name] = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"style weight {part!r} is not name=number (e.g. calm=0.7)") from None
        if not math.isfinite(weights[name]) or weights[name] < 0:
            raise argparse.ArgumentTypeError(f"style weight {part.strip()!r} must be a finite number >= 0 "
                                             "(e.g. calm=0.7,animated=0.3)")
    return weights


def parse_style_at(text: str) -> StyleChanges:
    """'0=calm,12.5=animated' -> ((0.0, 'calm'), (12.5, 'animated')); an item whose key is a
    name adds to the mix of the time before it: '0=calm,12.5=calm=0.3,animated=0.7'."""
    return parse_changes(text, "SECONDS=STYLE", "--style-at 0=calm,12.5=animated", parse_style)


def style_names_fit(names, style_dim: int) -> bool:
    """Whether `names` can be a model's style names: none, or `style_dim` different names
    (non-empty text), one per style class."""
    return names == [] or (isinstance(names, list) and len(names) == style_dim
                           and all(isinstance(n, str) and n for n in names) and len(set(names)) == len(names))


def unknown_styles(spec: StyleSpec, names: list[str]) -> list[str]:
    """What in `spec` names no style of a model with style `names` (a file's, read without
    loading it): one line per unknown name or index out of range."""
    problems = []
    for key in (spec if isinstance(spec, dict) else [spec]):
        if isinstance(key, str) and key not in names:
            problems.append(f"unknown style '{key}'; the model's styles are {', '.join(names) or 'none'}")
        elif isinstance(key, int) and not 0 <= key < len(names):
            problems.append(f"style index {key} is out of range; the model has {len(names)} styles "
                            f"(0-{len(names) - 1})")
    return problems


# ---------------------------------------------------------------- a style against a model

def style_weights(bundle: ModelBundle, style: Optional[StyleSpec]) -> dict[int, float]:
    """{style class: weight}, weights summing to 1, for a style given as a class index, a
    name, or weights over indices or names ({"calm": 0.7, "animated": 0.3}), None for the
    model's default style; official checkpoints' speaker one-hots take indices. Bad styles
    raise DiffshegError."""
    n, names = bundle.config.style_dim, bundle.style_names
    named = f" ({', '.join(names)})" if names else ""
    if style is None:
        style = bundle.default_style

    def index(key) -> int:
        if isinstance(key, str):
            if key in names:
                return names.index(key)
            if (number := parse_whole(key)) is not None:
                return index(number)
            raise DiffshegError(f"model {bundle.model_id} has no style '{key}': choose one of "
                                f"{', '.join(names) or f'the style indices 0 to {n - 1}'}")
        if isinstance(key, bool) or not isinstance(key, (int, np.integer)) or not 0 <= key < n:
            raise DiffshegError(f"style must be a whole number from 0 to {n - 1}{named} for this model, "
                                f"got {key!r}")
        return int(key)

    items = [(key, check_number(f"style weight of {key!r}", weight, (0.0, math.inf)))
             for key, weight in (style.items() if isinstance(style, dict) else [(style, 1.0)])]
    peak = max((weight for _, weight in items), default=0.0)
    if peak <= 0:
        raise DiffshegError(f"style weights {style!r} do not sum to a positive number: give at least "
                            "one style a weight above 0")
    weights: dict[int, float] = {}
    for key, weight in items:  # each over the largest first: weights near the float limit do not overflow
        weights[index(key)] = weights.get(index(key), 0.0) + weight / peak
    total = sum(weights.values())
    return {k: w / total for k, w in sorted(weights.items())}


def style_vector(bundle: ModelBundle, weights: dict[int, float]) -> np.ndarray:
    """(1, style_dim) mix of style one-hots, the model's style input."""
    vector = np.zeros((1, bundle.config.style_dim), np.float32)
    for k, w in weights.items():
        vector[0, k] = w
    return vector


def named_weights(bundle: ModelBundle, weights: dict[int, float]) -> dict[str, float]:
    """Style weights by name (by index for a model without style names)."""
    names = bundle.style_names
    return {(names[k] if names else str(k)): w for k, w in weights.items()}


def style_meta(bundle: ModelBundle, weights: dict[int, float], style_guidance: Optional[float]) -> dict:
    """What a Motion records of its style: the class (single styles), the weights by name
    (or index), the names of the model's styles and the style-guidance scale used (None: off)."""
    return {"style": next(iter(weights)) if len(weights) == 1 else None,
            "style_weights": named_weights(bundle, weights),
            "style_names": bundle.style_names, "style_guidance": style_guidance or 1.0}


def resolve_style_guidance(bundle: ModelBundle, scale: Optional[float]) -> Optional[float]:
    """The style-guidance scale (None or 1: off); it needs a model trained with a null style."""
    if scale is None or float(scale) == 1.0:
        return None
    if not bundle.null_style:
        raise DiffshegError(f"model {bundle.model_id} was trained without a null style, so style guidance "
                            "cannot work with it: leave the style strength at 1")
    return float(check_number("style_guidance", scale, STYLE_GUIDANCE))


# ---------------------------------------------------------------- a style over time

@dataclass(frozen=True)
class StyleTrack:
    """The style input of each of T frames, `rows` (T, style_dim). A window is sampled with
    one style (`window`): where the style changes over time (`changing`), the mean over its
    frames, so a change is blended in over about one window; else the style itself."""

    rows: np.ndarray
    changing: bool = False

    def __len__(self) -> int:
        return len(self.rows)

    def frames(self, first: int, end: int) -> StyleTrack:
        """Frames [first, end) of the track."""
        return StyleTrack(self.rows[first:end], self.changing)

    @staticmethod
    def join(parts: Iterable[StyleTrack]) -> StyleTrack:
        """Consecutive pieces of one track, as one."""
        parts = list(parts)
        return StyleTrack(np.concatenate([p.rows for p in parts]), parts[0].changing)

    def window(self) -> np.ndarray:
        """(1, style_dim): the style input a window of these frames is sampled with."""
        return self.rows.mean(axis=0, keepdims=True) if self.changing else self.rows[:1]


def style_track(bundle: ModelBundle, style: Optional[StyleSpec], style_at: Optional[StyleChanges],
                n_frames: int) -> StyleTrack:
    """The style of each of `n_frames` frames: `style` until the first change of `style_at`
    ((seconds, style), ...), then each change's style from its frame on (a change after the
    speech's end: never). With `style_at` the track is `changing` (even where every change
    names the same style): its windows take the mean over their frames."""
    rows = np.repeat(style_vector(bundle, style_weights(bundle, style)), n_frames, axis=0)
    for seconds, spec in style_at or ():  # min first: seconds * fps may be inf (1e308 s), which round() refuses
        frame = round(min(seconds * bundle.config.fps, n_frames))
        rows[frame:] = style_vector(bundle, style_weights(bundle, spec))
    return StyleTrack(rows, changing=bool(style_at))
