"""The procedural face teacher: 51 ARKit weights per frame from visemes (mouth, jaw),
blinks, gaze, prosody-driven brows and a slowly drifting baseline expression."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from ...rigs import ARKIT51
from .phones import SILENCE, Phone
from .prosody import Accent
from .coarticulation import arkit_indices, mouth_curves

BLINK_MIN_S, BLINK_MAX_S = 0.26, 0.5
"""Blink length, eyelid leaving rest to back at rest. The lid is more than half closed for
half of it (130-250 ms), inside the 100-400 ms of real blinks."""


@dataclass(frozen=True)
class FaceStyle:
    """One speaker's facial manner, drawn per utterance."""

    jaw_scale: float = 1.0
    stress_gain: float = 1.0
    blink_rate: float = 18.0
    """Blinks per minute."""
    brow_gain: float = 0.3
    smile: float = 0.08
    drift: float = 0.05
    """Amplitude of the slow wandering of the expression channels."""

    @classmethod
    def random(cls, rng: np.random.Generator) -> "FaceStyle":
        return cls(jaw_scale=float(rng.uniform(0.8, 1.2)), stress_gain=float(rng.uniform(0.6, 1.4)),
                   blink_rate=float(rng.uniform(14, 28)), brow_gain=float(rng.uniform(0.15, 0.45)),
                   smile=float(rng.uniform(0.0, 0.22)), drift=float(rng.uniform(0.02, 0.08)))


def _col(name: str) -> int:
    return ARKIT51.index(name)


def _slow_noise(rng: np.random.Generator, n: int, fps: float, seconds: float = 1.0) -> np.ndarray:
    """Unit-std smooth noise with correlation time about `seconds`."""
    x = gaussian_filter1d(rng.standard_normal(n + 60), seconds * fps, mode="wrap")[30:30 + n]
    return x / (x.std() + 1e-9)


def blink_times(rng: np.random.Generator, duration: float, rate: float,
                pauses: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """(peak time, length) of each blink: gamma-distributed intervals (mean 60 / rate s,
    at least 0.6 s apart); half the blinks that fall near a pause move into it, where
    people tend to blink."""
    out: list[tuple[float, float]] = []
    t = float(rng.uniform(0.2, 60.0 / rate))
    while t < duration - 0.2:
        if pauses and rng.random() < 0.5:
            near = min(pauses, key=lambda p: abs(0.5 * (p[0] + p[1]) - t))
            if abs(0.5 * (near[0] + near[1]) - t) < 0.6:
                t = max(0.5 * (near[0] + near[1]), out[-1][0] + 0.6 if out else 0.0)
        out.append((t, float(rng.uniform(BLINK_MIN_S, BLINK_MAX_S))))
        t += max(0.6, float(rng.gamma(3.0, 60.0 / rate / 3.0)))
    return out


def blink_curve(times: np.ndarray, blinks: list[tuple[float, float]], fps: float) -> np.ndarray:
    """Eyelid closure: a fast close (40% of the blink) and a slower reopening; each peak is
    put on a frame so that sampling at `fps` never misses a blink."""
    out = np.zeros(len(times))
    for peak, length in blinks:
        peak = round(peak * fps) / fps
        close, reopen = 0.4 * length, 0.6 * length
        u = np.where(times < peak, (times - peak + close) / close, 1.0 - (times - peak) / reopen)
        out = np.maximum(out, np.where((u > 0) & (u <= 1), np.sin(0.5 * np.pi * np.clip(u, 0, 1)) ** 2, 0.0))
    return out


def _gaze(rng: np.random.Generator, n: int, fps: float) -> np.ndarray:
    """(n, 2) gaze (right, up) in weight units: fixations of 0.4-2.5 s joined by one-frame
    saccades; every other fixation returns near the centre (the listener)."""
    out = np.zeros((n, 2))
    i, centre = 0, True
    while i < n:
        length = int(rng.uniform(0.4, 2.5) * fps)
        target = rng.normal(0, 0.04, 2) if centre else rng.normal(0, [0.18, 0.1])
        out[i:i + length] = target
        i, centre = i + length, not centre
    return gaussian_filter1d(out, 0.6, axis=0, mode="nearest")


def _bumps(times: np.ndarray, accents: list[Accent], rise: float, fall: float) -> np.ndarray:
    """(len(accents), len(times)) raised-and-decaying bumps peaking just after each accent."""
    out = np.zeros((len(accents), len(times)))
    for i, a in enumerate(accents):
        dt = times - (a.time + 0.05)
        out[i] = np.where(dt < 0, np.exp(-0.5 * (dt / rise) ** 2), np.exp(-0.5 * (dt / fall) ** 2))
    return out


def pauses_of(phones: list[Phone]) -> list[tuple[float, float]]:
    return [(p.start, p.end) for p in phones if p.label == SILENCE]


def face_curves(phones: list[Phone], accents: list[Accent], n_frames: int, fps: float,
                style: FaceStyle, rng: np.random.Generator, effort: np.ndarray | None = None) -> np.ndarray:
    """(n_frames, 51) ARKit weights in [0, 1]; `effort` as for coarticulation.mouth_curves."""
    times = np.arange(n_frames) / fps
    face = np.zeros((n_frames, len(ARKIT51)))
    face[:, arkit_indices()] = mouth_curves(phones, times, style.jaw_scale, style.stress_gain, effort)

    blink = blink_curve(times, blink_times(rng, n_frames / fps, style.blink_rate, pauses_of(phones)), fps)
    for side in ("Left", "Right"):
        face[:, _col(f"eyeBlink{side}")] = blink * rng.uniform(0.92, 1.0)
        face[:, _col(f"eyeSquint{side}")] = 0.12 * blink

    gaze = _gaze(rng, n_frames, fps)
    right, up = gaze[:, 0], gaze[:, 1]
    face[:, _col("eyeLookOutRight")] = face[:, _col("eyeLookInLeft")] = np.maximum(right, 0)
    face[:, _col("eyeLookInRight")] = face[:, _col("eyeLookOutLeft")] = np.maximum(-right, 0)
    for side in ("Left", "Right"):
        face[:, _col(f"eyeLookUp{side}")] = np.maximum(up, 0)
        face[:, _col(f"eyeLookDown{side}")] = np.maximum(-up, 0) + 0.25 * blink

    raised = [a for a in accents if rng.random() < 0.35 + 0.5 * a.strength]
    frowns = rng.random(len(raised)) < 0.15
    bumps = _bumps(times, raised, 0.08, 0.3) * np.array([a.strength for a in raised])[:, None]
    brow_up = style.brow_gain * bumps[~frowns].sum(axis=0) if len(raised) else np.zeros(n_frames)
    brow_down = 0.8 * style.brow_gain * bumps[frowns].sum(axis=0) if len(raised) else np.zeros(n_frames)
    # overlapping raises add up, but saturate (a brow has only so much travel)
    brow_up = 0.6 * np.tanh((brow_up + style.drift * np.abs(_slow_noise(rng, n_frames, fps, 1.5))) / 0.6)
    face[:, _col("browInnerUp")] = brow_up
    for side in ("Left", "Right"):
        face[:, _col(f"browOuterUp{side}")] = 0.8 * brow_up
        face[:, _col(f"browDown{side}")] = brow_down
        face[:, _col(f"eyeWide{side}")] = 0.3 * brow_up

    smile = style.smile + style.drift * _slow_noise(rng, n_frames, fps, 2.0)
    smile = np.clip(smile, 0, None)
    for side in ("Left", "Right"):
        face[:, _col(f"mouthSmile{side}")] += smile
        face[:, _col(f"cheekSquint{side}")] = 0.4 * smile
        face[:, _col(f"mouthDimple{side}")] = 0.2 * smile
    quiet = ("mouthFrownLeft", "mouthFrownRight", "noseSneerLeft", "noseSneerRight",
             "jawForward", "jawLeft", "jawRight", "mouthLeft", "mouthRight", "cheekPuff")
    for name in quiet:
        face[:, _col(name)] += 0.3 * style.drift * np.abs(_slow_noise(rng, n_frames, fps, 1.2))
    return np.clip(face, 0.0, 1.0).astype(np.float32)

