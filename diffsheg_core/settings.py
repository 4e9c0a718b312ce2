"""The options of one generation, checked once, in one place.

The add-on's panel, batch_render.py and the command line each map their own inputs onto
one `GenerateSettings` with one function, so every option exists everywhere and means
the same everywhere. None always means "the model's default"; each option has one
spelling of "off": guidance 1, skip_guidance (gesture energy) 0, candidates 1.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, fields
from typing import Union

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


StyleSpec = Union[int, str, dict]
"""A style: a class index, a style name, or weights over indices or names."""


def check_number(name: str, value, bounds: tuple, whole: bool = False):
    """`value` if it is a number within `bounds` (a whole number if `whole`), else a DiffshegError."""
    lo, hi = bounds
    kind = "a whole number" if whole else "a number"
    if (isinstance(value, bool) or not isinstance(value, (int, float) if not whole else int)
            or (not whole and not math.isfinite(value)) or not lo <= value <= hi):
        raise DiffshegError(f"{name} must be {kind} from {lo:g} to {hi:g}, got {value!r}")
    return value


def _check_choice(name: str, value, choices: tuple) -> str:
    if value not in choices:
        raise DiffshegError(f"{name} must be one of {', '.join(choices)}, got {value!r}")
    return value


@dataclass(frozen=True)
class GenerateSettings:
    """Every option of `diffsheg_core.generate` that a user sets. Checked when made."""

    model: object = None                # None: the bundled default; a path, or a loaded ModelBundle
    seed: int = 0                       # same seed, same motion (any whole number >= 0)
    face_seed: int | None = None        # fixes the face apart from `seed`; None: `seed` drives both
    steps: int | None = None            # DDIM steps
    overlap: int | None = None          # frames shared by consecutive windows
    candidates: int | None = None       # best-of-N windows; 1: off
    style: StyleSpec | None = None      # a style index or name, or weights {name or index: weight}; None: the model's default
    style_guidance: float | None = None  # style strength: eps_null + s (eps_style - eps_null); 1: off
    guidance: float | None = None       # classifier-free guidance scale; 1: off
    skip_guidance: float | None = None  # gesture energy (skip guidance); 0: off
    device: str = "auto"
    backend: str = "auto"
    precision: str = "fp32"
    threads: int | None = None          # CPU threads; None: runtime.backends.default_threads

    def __post_init__(self):
        from .foppas import check_seed

        check_seed(self.seed)
        if self.face_seed is not None:
            check_seed(self.face_seed)
        for name, bounds in (("steps", STEPS), ("overlap", OVERLAP), ("candidates", CANDIDATES),
                             ("threads", THREADS)):
            if getattr(self, name) is not None:
                check_number(name, getattr(self, name), bounds, whole=True)
        if self.style is not None and (not isinstance(self.style, (int, str, dict)) or isinstance(self.style, bool)):
            raise DiffshegError(f"style must be a style index, a style name or weights over styles "
                                f"(e.g. {{'calm': 0.7, 'animated': 0.3}}), got {self.style!r}")
        for name, label, bounds in (("guidance", "guidance", GUIDANCE),
                                    ("skip_guidance", "skip_guidance (gesture energy)", SKIP_GUIDANCE),
                                    ("style_guidance", "style_guidance", STYLE_GUIDANCE)):
            if getattr(self, name) is not None:
                check_number(label, getattr(self, name), bounds)
        _check_choice("device", self.device, DEVICES)
        _check_choice("backend", self.backend, BACKENDS)
        _check_choice("precision", self.precision, PRECISIONS)


# ---------------------------------------------------------------- command lines

def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The generation options, for every command line that generates (CLI and batch_render.py)."""
    g = parser.add_argument_group("generation")
    g.add_argument("--model", "--checkpoint", dest="model",
                   help="model file (ours, .safetensors, or an official DiffSHEG .pth); default: the bundled one")
    g.add_argument("--seed", type=int, default=0, help="same seed, same motion (default 0)")
    g.add_argument("--face-seed", type=int,
                   help="keep the face of this seed while --seed changes the gestures (default: off)")
    g.add_argument("--steps", type=int, help=f"DDIM steps, {STEPS[0]}-{STEPS[1]} (default: the model's, 25)")
    g.add_argument("--overlap", type=int, help="frames shared by consecutive windows (default: the model's)")
    g.add_argument("--candidates", type=int,
                   help=f"best-of-N windows, {CANDIDATES[0]}-{CANDIDATES[1]}: each later window is sampled N "
                        "times and the one that best continues the motion is kept (default 1: off)")
    g.add_argument("--style", type=parse_style,
                   help="style: a name or index (--style calm), or weights over styles "
                        "(--style calm=0.7,animated=0.3); default: the model's default style")
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
    g.add_argument("--threads", type=int, help="CPU threads (default 1, or $DIFFSHEG_THREADS)")


def from_arguments(args: argparse.Namespace) -> GenerateSettings:
    """The settings of parsed `add_arguments` options."""
    return GenerateSettings(**{f.name: getattr(args, f.name) for f in fields(GenerateSettings)})


def parse_style(text: str) -> StyleSpec:
    """'2' -> 2, 'calm' -> 'calm', 'calm=0.7,animated=0.3' -> {'calm': 0.7, 'animated': 0.3}."""
    text = text.strip()
    if "=" not in text:
        return int(text) if text.isdigit() else text
    weights: dict = {}
    for part in text.split(","):
        name, _, value = part.partition("=")
        try:
            weights[name.strip()] = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"style weight {part!r} is not name=number (e.g. calm=0.7)") from None
    return weights
