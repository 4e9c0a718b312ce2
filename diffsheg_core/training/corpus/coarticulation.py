"""Mouth and jaw from timed phones: viseme targets blended by a dominance model of
coarticulation (after Cohen and Massaro 1993).

Every phone pulls each mouth channel toward its viseme's target with a dominance that
is flat over the phone and decays exponentially outside it; a channel's value is the
dominance-weighted mean of all targets. Lip closure of p b m and lip-teeth contact of f v
dominate strongly, so they are reached however short the phone; alveolar and velar
consonants dominate weakly, so the lips take their neighbours' shapes (the "t" in "two" is
rounded). Lip contact of p b m (closure) and f v is then enforced over the phone with
short smooth ramps, however short the phone. Nothing is held per phone: the curves move
continuously.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from ...rigs import ARKIT51
from .phones import SILENCE, Phone

GRID_RATE = 200.0
"""Samples per second of the internal curves (before sampling at the motion rate)."""

MOUTH_CHANNELS = (
    "jawOpen", "mouthClose", "mouthPressLeft", "mouthPressRight", "mouthFunnel", "mouthPucker",
    "mouthStretchLeft", "mouthStretchRight", "mouthSmileLeft", "mouthSmileRight",
    "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
)
_JAW = MOUTH_CHANNELS.index("jawOpen")


@dataclass(frozen=True)
class Viseme:
    """Targets (channel -> weight; 'Press' sets both sides of mouthPress, etc.), the
    dominance of its lips and of its jaw, and how far (seconds) that dominance reaches."""

    targets: dict
    lips: float = 1.0
    jaw: float = 1.0
    reach: float = 0.07


def _v(lips: float, jaw: float, reach: float, **targets: float) -> Viseme:
    return Viseme(targets, lips, jaw, reach)


VISEMES: dict[str, Viseme] = {
    "rest": _v(1.0, 1.0, 0.05, jawOpen=0.04, mouthClose=0.03, mouthShrugLower=0.05),
    "PBM": _v(3.0, 3.0, 0.04, jawOpen=0.02, mouthClose=0.5, Press=0.45, mouthRollLower=0.15,
              mouthRollUpper=0.1, mouthShrugLower=0.15),
    "FV": _v(3.0, 2.0, 0.04, jawOpen=0.07, mouthClose=0.12, mouthRollLower=0.5, UpperUp=0.2,
             Press=0.1),
    "TH": _v(1.0, 1.0, 0.05, jawOpen=0.13, LowerDown=0.15, Stretch=0.1),
    "TD": _v(0.4, 0.7, 0.04, jawOpen=0.12, LowerDown=0.1, Stretch=0.1),
    "SZ": _v(1.0, 1.5, 0.05, jawOpen=0.07, Stretch=0.25, Smile=0.1, LowerDown=0.1, UpperUp=0.1),
    "SH": _v(3.0, 1.0, 0.08, jawOpen=0.12, mouthFunnel=0.5, mouthPucker=0.25, UpperUp=0.2,
             LowerDown=0.15),
    "KG": _v(0.3, 0.6, 0.04, jawOpen=0.16, LowerDown=0.05),
    "L": _v(0.4, 0.8, 0.04, jawOpen=0.18, LowerDown=0.1),
    "R": _v(2.0, 0.8, 0.07, jawOpen=0.12, mouthFunnel=0.3, mouthPucker=0.3),
    "W": _v(4.0, 1.0, 0.10, jawOpen=0.07, mouthPucker=0.7, mouthFunnel=0.3),
    "AA": _v(1.0, 2.5, 0.07, jawOpen=0.58, LowerDown=0.2),
    "AE": _v(1.0, 2.5, 0.07, jawOpen=0.48, Stretch=0.25, LowerDown=0.25, UpperUp=0.1),
    "AH": _v(0.8, 2.0, 0.07, jawOpen=0.40, LowerDown=0.15),
    "AO": _v(1.5, 2.5, 0.07, jawOpen=0.48, mouthFunnel=0.35, mouthPucker=0.1),
    "EH": _v(1.0, 2.0, 0.07, jawOpen=0.33, Stretch=0.2, LowerDown=0.15),
    "ER": _v(1.5, 1.5, 0.07, jawOpen=0.22, mouthFunnel=0.3, mouthPucker=0.2),
    "IH": _v(1.0, 1.5, 0.07, jawOpen=0.22, Stretch=0.25, Smile=0.1),
    "IY": _v(1.5, 1.5, 0.07, jawOpen=0.14, Stretch=0.35, Smile=0.2),
    "UH": _v(2.0, 1.5, 0.07, jawOpen=0.2, mouthPucker=0.4, mouthFunnel=0.2),
    "UW": _v(3.0, 1.5, 0.09, jawOpen=0.12, mouthPucker=0.75, mouthFunnel=0.35),
    "OW": _v(2.0, 2.0, 0.07, jawOpen=0.36, mouthFunnel=0.5, mouthPucker=0.2),
}

_PHONE_VISEMES: dict[str, tuple[str, ...]] = {
    SILENCE: ("rest",), "P": ("PBM",), "B": ("PBM",), "M": ("PBM",), "F": ("FV",), "V": ("FV",),
    "TH": ("TH",), "DH": ("TH",), "T": ("TD",), "D": ("TD",), "N": ("TD",), "S": ("SZ",),
    "Z": ("SZ",), "SH": ("SH",), "ZH": ("SH",), "CH": ("SH",), "JH": ("SH",), "K": ("KG",),
    "G": ("KG",), "NG": ("KG",), "HH": ("KG",), "Y": ("IY",), "L": ("L",), "R": ("R",),
    "W": ("W",), "AA": ("AA",), "AE": ("AE",), "AH": ("AH",), "AO": ("AO",), "EH": ("EH",),
    "ER": ("ER",), "IH": ("IH",), "IY": ("IY",), "UH": ("UH",), "UW": ("UW",), "OW": ("OW", "UH"),
    "AW": ("AA", "UH"), "AY": ("AA", "IH"), "EY": ("EH", "IY"), "OY": ("AO", "IY"),
}
"""Diphthongs glide from their first viseme (60% of the phone) to their second."""

_BILABIAL_MIN = 0.08
"""Lips stay closed at least this long (s) for p b m, as real stop closures do."""

_CONTACT = {"PBM": 1.0, "FV": 0.7}
"""Visemes whose lip contact must be reached, and how fully: after blending, the curves are
pulled to their targets over the phone, with ramps of _CONTACT_RAMP s on both sides."""
_CONTACT_RAMP = 0.03


def _target_vector(v: Viseme) -> np.ndarray:
    out = np.zeros(len(MOUTH_CHANNELS))
    for key, value in v.targets.items():
        names = [key] if key in MOUTH_CHANNELS else [f"mouth{key}Left", f"mouth{key}Right"]
        for name in names:
            out[MOUTH_CHANNELS.index(name)] = value
    return out


_TARGETS = {name: _target_vector(v) for name, v in VISEMES.items()}


@dataclass(frozen=True)
class _Segment:
    viseme: str
    start: float
    end: float
    gain: float


def _segments(phones: list[Phone], stress_gain: float, effort: np.ndarray) -> list[_Segment]:
    out: list[_Segment] = []
    for p, vocal_effort in zip(phones, effort):
        names = _PHONE_VISEMES[p.label]
        gain = (1.0 + stress_gain * {1: 0.15, 2: 0.0, 0: -0.15}.get(p.stress, 0.0)) * vocal_effort \
            if p.is_vowel else 1.0
        start, end = p.start, p.end
        if names == ("PBM",) and end - start < _BILABIAL_MIN:
            mid = 0.5 * (start + end)
            start, end = mid - _BILABIAL_MIN / 2, mid + _BILABIAL_MIN / 2
        if len(names) == 1:
            out.append(_Segment(names[0], start, end, gain))
        else:
            split = start + 0.6 * (end - start)
            out += [_Segment(names[0], start, split, gain), _Segment(names[1], split, end, gain)]
    return out


def _dominance(seg: _Segment, t: np.ndarray, pause_inside: bool) -> tuple[np.ndarray, float, float]:
    """exp(-distance / reach) with distance 0 inside the segment. A pause's plateau is
    pulled in at both ends (the mouth leaves rest before speech starts) and a short pause
    inside speech dominates weakly (the lips do not relax in a breath between words)."""
    v = VISEMES[seg.viseme]
    start, end, lips, jaw = seg.start, seg.end, v.lips, v.jaw
    if seg.viseme == "rest":
        start, end = min(start + 0.08, end), max(end - 0.08, start)
        if pause_inside and seg.end - seg.start < 0.25:
            lips, jaw = 0.2, 0.2
    distance = np.maximum(0.0, np.maximum(start - t, t - end))
    return np.exp(-distance / v.reach), lips, jaw


def mouth_curves(phones: list[Phone], times: np.ndarray, jaw_scale: float = 1.0,
                 stress_gain: float = 1.0, effort: np.ndarray | None = None) -> np.ndarray:
    """(len(times), len(MOUTH_CHANNELS)) mouth weights at `times` (seconds).

    `jaw_scale` scales jaw opening (a speaker's articulation); `stress_gain` how much more
    stressed vowels open than unstressed ones; `effort` (one factor per phone,
    prosody.vowel_effort) how much wider each vowel opens for being spoken louder."""
    t0, t1 = 0.0, max(float(times[-1]) if len(times) else 0.0, phones[-1].end)
    grid = np.arange(t0, t1 + 1.0 / GRID_RATE, 1.0 / GRID_RATE)
    segs = _segments(phones, stress_gain, np.ones(len(phones)) if effort is None else effort)
    lips_w = np.zeros((len(segs), len(grid)))
    jaw_w = np.zeros_like(lips_w)
    targets = np.zeros((len(segs), len(MOUTH_CHANNELS)))
    for i, seg in enumerate(segs):
        inside = 0 < i < len(segs) - 1
        d, lips, jaw = _dominance(seg, grid, inside)
        lips_w[i], jaw_w[i] = lips * d, jaw * d
        targets[i] = _TARGETS[seg.viseme]
        if seg.viseme not in ("rest", "PBM"):
            targets[i, _JAW] *= seg.gain * jaw_scale
    eps = 1e-12
    curves = (lips_w.T @ targets) / (lips_w.sum(axis=0)[:, None] + eps)
    curves[:, _JAW] = (jaw_w.T @ targets[:, _JAW]) / (jaw_w.sum(axis=0) + eps)
    for seg in segs:
        if seg.viseme in _CONTACT:
            ramp = np.clip(1 + np.minimum(grid - seg.start, seg.end - grid) / _CONTACT_RAMP, 0, 1)
            env = _CONTACT[seg.viseme] * ramp * ramp * (3 - 2 * ramp)
            curves += env[:, None] * (_TARGETS[seg.viseme] - curves)
    curves = gaussian_filter1d(curves, sigma=0.015 * GRID_RATE, axis=0, mode="nearest")
    return np.stack([np.interp(times, grid, c) for c in curves.T], axis=1).clip(0.0, 1.0)


def viseme_phones() -> frozenset[str]:
    """The ARPAbet phones that have visemes (silence included)."""
    return frozenset(_PHONE_VISEMES)


def arkit_indices(names: tuple[str, ...] = MOUTH_CHANNELS) -> np.ndarray:
    """Columns of `names` in the ARKit-51 face vector."""
    return np.array([ARKIT51.index(n) for n in names])
