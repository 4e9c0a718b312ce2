"""The options of one generation, checked once, in one place.

The add-on's panel, batch_render.py and the command line each map their own inputs onto
one `GenerateSettings` with one function, so every option exists everywhere and means
the same everywhere. None always means "the model's default"; each option has one
spelling of "off": guidance 1, skip_guidance (gesture energy) 0, candidates 1.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

from .errors import DiffshegError
from .validate import (BACKENDS, CANDIDATES, DEVICES, GUIDANCE, OVERLAP, PRECISIONS, SKIP_GUIDANCE, STEPS,
                       STYLE_GUIDANCE, THREADS, check_changes, check_language, check_number, check_seed,
                       parse_changes)

if TYPE_CHECKING:
    from .style import StyleSpec


def _check_choice(name: str, value, choices: tuple) -> str:
    if value not in choices:
        raise DiffshegError(f"{name} must be one of {', '.join(choices)}, got {value!r}")
    return value


_NUMBERS = (("steps", "steps", STEPS, True), ("overlap", "overlap", OVERLAP, True),
            ("candidates", "candidates", CANDIDATES, True), ("threads", "threads", THREADS, True),
            ("guidance", "guidance", GUIDANCE, False),
            ("skip_guidance", "skip_guidance (gesture energy)", SKIP_GUIDANCE, False),
            ("style_guidance", "style_guidance", STYLE_GUIDANCE, False))
"""The numeric settings: field, the name messages give it, bounds, whether whole."""


def _check_emotion_at(changes) -> tuple[tuple[float, dict], ...] | None:
    from .emotion import check_emotion  # numpy: only where an emotion is asked for

    return check_changes(changes, "emotion", check_emotion, "((0, 'happy'), (12.5, 'sad'))")


@dataclass(frozen=True)
class GenerateSettings:
    """Every option of `diffsheg_core.generate` that a user sets. Checked when made."""

    model: object = None                # None: the bundled default; a path, or a loaded ModelBundle
    seed: int = 0                       # same seed, same motion (any whole number >= 0)
    face_seed: int | None = None        # fixes the face apart from `seed`; None: `seed` drives both
    sampling: str = "fast"              # 'fast' (5 steps) or 'quality' (the model's own, 25 steps), or a preset
    steps: int | None = None            # DDIM steps (None: the sampling's)
    overlap: int | None = None          # frames shared by consecutive windows
    candidates: int | None = None       # best-of-N windows; 1: off
    style: StyleSpec | None = None      # a style index or name, or weights {name or index: weight}; None: the model's default
    style_at: tuple | None = None       # style changes over time: ((seconds, style), ...); before the first, `style`
    style_guidance: float | None = None  # style strength: eps_null + s (eps_style - eps_null); 1: off
    emotion: str | dict | None = None   # 'happy', 'happy=0.6' or {name: intensity}; None: neutral (see emotion.py)
    emotion_at: tuple | None = None     # emotion changes over time: ((seconds, emotion), ...); before the first, `emotion`
    upper_body_only: bool = False       # no hips and legs (lower_body): for seated characters, or legs keyed by hand
    language: str | None = None         # a language whose own face the model carries ('zh'); None: the shared face
    guidance: float | None = None       # classifier-free guidance scale; 1: off
    skip_guidance: float | None = None  # gesture energy (skip guidance); 0: off
    device: str = "auto"
    backend: str = "auto"
    precision: str = "fp32"
    threads: int | None = None          # CPU threads; None: runtime.backends.default_threads

    def __post_init__(self):
        self._set("seed", check_seed(self.seed))
        if self.face_seed is not None:
            self._set("face_seed", check_seed(self.face_seed))
        _check_choice("sampling", self.sampling, _sampling_names())
        for name, label, bounds, whole in _NUMBERS:
            if getattr(self, name) is not None:
                self._set(name, check_number(label, getattr(self, name), bounds, whole))
        if self.style is not None or self.style_at is not None:
            from .style import check_style, check_style_at  # numpy: only where a style is asked for

            if self.style is not None:
                self._set("style", check_style(self.style))
            if self.style_at is not None:
                self._set("style_at", check_style_at(self.style_at))
        if self.emotion is not None:
            from .emotion import check_emotion  # numpy: only where an emotion is asked for

            self._set("emotion", check_emotion(self.emotion) or None)
        if self.emotion_at is not None:
            self._set("emotion_at", _check_emotion_at(self.emotion_at))
        if not isinstance(self.upper_body_only, bool):
            raise DiffshegError(f"upper_body_only must be True or False, got {self.upper_body_only!r}")
        if self.language is not None:
            self._set("language", check_language(self.language))
        _check_choice("device", self.device, DEVICES)
        _check_choice("backend", self.backend, BACKENDS)
        _check_choice("precision", self.precision, PRECISIONS)

    def _set(self, name: str, value) -> None:
        """Store a checked value (numpy numbers as Python's) in the frozen settings."""
        object.__setattr__(self, name, value)


# ---------------------------------------------------------------- command lines

def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The generation options, for every command line that generates (CLI and batch_render.py)."""
    from .style import parse_style, parse_style_at  # numpy: only where a command line generates

    g = parser.add_argument_group("generation")
    g.add_argument("--model", "--checkpoint", dest="model",
                   help="model file (ours, .safetensors, or an official DiffSHEG .pth); default: the bundled one")
    g.add_argument("--seed", type=int, default=0, help="same seed, same motion (default 0)")
    g.add_argument("--face-seed", type=int,
                   help="keep the face of this seed while --seed changes the gestures (default: off)")
    g.add_argument("--sampling", default="fast", choices=_sampling_names(),
                   help="fast (default: 5 steps, each one pass of the model's distilled student where it has one, "
                        "with the quality figures of 25) or quality (the model's own sampling, 25 steps, about 5.5 "
                        "times slower); or an official preset")
    g.add_argument("--steps", type=int, help=f"DDIM steps, {STEPS[0]}-{STEPS[1]} (default: the sampling's, 5 or 25)")
    g.add_argument("--overlap", type=int, help="frames shared by consecutive windows (default: the model's)")
    g.add_argument("--candidates", type=int,
                   help=f"best-of-N windows, {CANDIDATES[0]}-{CANDIDATES[1]}: each later window is sampled N "
                        "times and the one that best continues the motion is kept (default 1: off)")
    g.add_argument("--style", type=parse_style,
                   help="style: a name or index (--style calm), or weights over styles "
                        "(--style calm=0.7,animated=0.3); default: the model's default style")
    g.add_argument("--style-at", type=parse_style_at, metavar="SECONDS=STYLE,...",
                   help="the style from given times on, blended over about one window: "
                        "--style-at 0=calm,12.5=animated (a mix: 12.5=calm=0.3,animated=0.7)")
    g.add_argument("--emotion", type=_emotion_argument,
                   help="emotion over the face and body: neutral, happy, sad, angry, surprised, fearful or "
                        "disgusted, at an intensity from 0 to 1 (--emotion happy=0.6; default 1), or a mix "
                        "(--emotion happy=0.5,surprised=0.3); default neutral")
    g.add_argument("--emotion-at", type=parse_emotion_at, metavar="SECONDS=EMOTION,...",
                   help="the emotion from given times on, eased in: --emotion-at 0=happy,12.5=sad=0.6")
    g.add_argument("--upper-body-only", action="store_true",
                   help="no hips and legs: for seated characters, or when you key the legs yourself "
                        "(default: the whole body, on models of the beat layout)")
    g.add_argument("--language", type=_language_argument,
                   help="a language whose own face the model carries, fine-tuned on that language's captured "
                        "faces: zh (Mandarin) in the bundled model; default: the shared face, which serves every "
                        "language")
    g.add_argument("--style-guidance", type=float,
                   help="style strength: 1 is the style as trained (default), above 1 goes beyond it "
                        "(models trained with a null style)")
    g.add_argument("--guidance", type=float,
                   help="classifier-free guidance scale, 0-10 (default: the model's; 1 = off)")
    g.add_argument("--gesture-energy", "--skip-guidance", dest="skip_guidance", type=float,
                   help="gesture skip-guidance scale, 0-1: higher, livelier gestures (default: the model's; 0 = off)")
    g.add_argument("--device", default="auto", choices=DEVICES)
    g.add_argument("--backend", default="auto", choices=BACKENDS,
                   help="onnx (onnxruntime, CPU) or torch (CUDA, official checkpoints); default auto")
    g.add_argument("--precision", default="fp32", choices=PRECISIONS, help="bf16 / fp16: autocast on CUDA")
    g.add_argument("--threads", type=int,
                   help=f"CPU threads, {THREADS[0]}-{THREADS[1]} (default 1, or $DIFFSHEG_THREADS, in the same bounds)")


def _sampling_names() -> tuple[str, ...]:
    from .foppas import SAMPLING_NAMES  # numpy: only where a sampling is checked, as emotions are

    return SAMPLING_NAMES


def from_arguments(args: argparse.Namespace) -> GenerateSettings:
    """The settings of parsed `add_arguments` options."""
    return GenerateSettings(**{f.name: getattr(args, f.name) for f in fields(GenerateSettings)})


def _language_argument(text: str) -> str:
    try:
        return check_language(text)
    except DiffshegError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _emotion_argument(text: str) -> dict:
    from .emotion import check_emotion

    try:
        return check_emotion(text)
    except DiffshegError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def parse_emotion_at(text: str) -> tuple[tuple[float, dict], ...]:
    """'0=happy,12.5=sad=0.6' -> ((0.0, {'happy': 1.0}), (12.5, {'sad': 0.6})); a mix as for
    styles: '12.5=happy=0.5,surprised=0.3'. Each emotion checked as --emotion checks it."""
    return parse_changes(text, "SECONDS=EMOTION", "--emotion-at 0=happy,12.5=sad=0.6", _emotion_argument)
