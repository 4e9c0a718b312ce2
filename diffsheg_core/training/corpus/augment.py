"""Audio augmentation so a model trained on synthetic speech hears real-sounding voices:
pitch, tempo, room reverb and microphone band limits (one sox run), then background noise
and level (numpy). Phone times follow the tempo change."""

from __future__ import annotations

import subprocess
from dataclasses import asdict, dataclass

import numpy as np

from ...errors import DiffshegError
from .phones import SILENCE, Phone, extend_to, merge_silences

SAMPLE_RATE = 16000
"""Corpus audio rate."""


@dataclass(frozen=True)
class AugmentSpec:
    """One utterance's augmentation. `tempo` > 1 is faster speech (sox WSOLA `tempo`,
    pitch kept; it maps time t to t / tempo to within one WSOLA search window, ~15 ms,
    well under a 67 ms motion frame). `reverb` is (reverberance %, room scale %, wet dB)
    or None; `band` is (high-pass Hz, low-pass Hz) or None; noise is mixed at `snr_db`
    (None for none) and the result scaled to RMS `level_db` dBFS. `pad` (s) is silence
    added before and after the speech (recordings rarely start on the first word)."""

    pad: tuple[float, float] = (0.0, 0.0)
    pitch_cents: float = 0.0
    tempo: float = 1.0
    reverb: tuple[float, float, float] | None = None
    band: tuple[float, float] | None = None
    noise: str = "white"
    snr_db: float | None = None
    level_db: float = -23.0

    def to_dict(self) -> dict:
        return asdict(self)


def random_augment(rng: np.random.Generator) -> AugmentSpec:
    """Draw an augmentation; about one utterance in eight stays clean apart from its level."""
    def maybe(p: float) -> bool:
        return bool(rng.random() < p)

    return AugmentSpec(
        pad=(float(rng.uniform(0.0, 0.6)), float(rng.uniform(0.0, 0.8))),
        pitch_cents=float(rng.uniform(-400, 400)) if maybe(0.6) else 0.0,
        tempo=float(rng.uniform(0.88, 1.12)) if maybe(0.4) else 1.0,
        reverb=(float(rng.uniform(10, 70)), float(rng.uniform(20, 100)), float(rng.uniform(-8, 0)))
        if maybe(0.5) else None,
        band=(float(rng.uniform(80, 300)), float(rng.uniform(3400, 7500))) if maybe(0.3) else None,
        noise=str(rng.choice(["white", "pink", "brown"])),
        snr_db=float(rng.uniform(10, 40)) if maybe(0.6) else None,
        level_db=float(rng.uniform(-35, -16)),
    )


def _sox_effects(spec: AugmentSpec) -> list[str]:
    fx: list[str] = []
    if spec.pitch_cents:
        fx += ["pitch", f"{spec.pitch_cents:.1f}"]
    if spec.tempo != 1.0:
        fx += ["tempo", "-s", f"{spec.tempo:.4f}"]
    if spec.reverb is not None:
        reverberance, room, wet = spec.reverb
        fx += ["reverb", f"{reverberance:.1f}", "50", f"{room:.1f}", "100", "0", f"{wet:.1f}"]
    # band limits at the corpus rate: `pitch` down lowers sox's working rate, and a 16 kHz
    # voice (flite) shifted down would put the low-pass above that rate's Nyquist frequency
    fx += ["rate", "-v", str(SAMPLE_RATE)]
    if spec.band is not None:
        fx += ["highpass", f"{spec.band[0]:.0f}", "lowpass", f"{spec.band[1]:.0f}"]
    return fx


def _sox(samples: np.ndarray, sample_rate: int, effects: list[str]) -> np.ndarray:
    raw = ["-t", "f32", "-c", "1", "-e", "floating-point"]
    cmd = ["sox", "-V1", *raw, "-r", str(sample_rate), "-", *raw, "-", *effects]
    try:
        run = subprocess.run(cmd, input=np.ascontiguousarray(samples, np.float32).tobytes(),
                             capture_output=True, timeout=300)
    except subprocess.TimeoutExpired as exc:
        raise DiffshegError(f"sox took over 300 s ({' '.join(effects)})") from exc
    except FileNotFoundError as exc:
        raise DiffshegError("sox is not installed: run `apt-get install sox`") from exc
    if run.returncode != 0:
        raise DiffshegError(f"sox failed ({' '.join(effects)}): {run.stderr.decode()[-300:]}")
    return np.frombuffer(run.stdout, dtype=np.float32).copy()


def _noise(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Unit-RMS white, pink (1/f power) or brown (1/f^2) noise."""
    spectrum = np.fft.rfft(rng.standard_normal(n))
    f = np.maximum(np.fft.rfftfreq(n), 1.0 / n)
    spectrum *= {"white": 1.0, "pink": f ** -0.5, "brown": 1.0 / f}[kind]
    x = np.fft.irfft(spectrum, n)
    return x / max(np.sqrt(np.mean(x**2)), 1e-12)


def _speech_rms(x: np.ndarray) -> float:
    """RMS over the louder half of 20 ms blocks: the level of speech, not of its pauses."""
    n = len(x) // 320 * 320
    if n == 0:
        return float(np.sqrt(np.mean(x**2) + 1e-12))
    block = np.mean(x[:n].reshape(-1, 320) ** 2, axis=1)
    return float(np.sqrt(np.mean(block[block >= np.median(block)]) + 1e-12))


def augment(samples: np.ndarray, sample_rate: int, phones: list[Phone], spec: AugmentSpec,
            rng: np.random.Generator) -> tuple[np.ndarray, list[Phone]]:
    """Augmented 16 kHz audio and the phones re-timed to it (padding, tempo; the last
    pause stretched to the new end)."""
    before, after = (np.zeros(int(round(p * sample_rate)), np.float32) for p in spec.pad)
    y = _sox(np.concatenate([before, samples, after]), sample_rate, _sox_effects(spec))
    shift = len(before) / sample_rate
    if spec.snr_db is not None:
        y = y + _noise(spec.noise, len(y), rng) * _speech_rms(y) * 10 ** (-spec.snr_db / 20)
    y *= 10 ** (spec.level_db / 20) / _speech_rms(y)
    peak = float(np.max(np.abs(y))) if len(y) else 0.0
    if peak > 0.99:
        y *= 0.99 / peak
    end = len(y) / SAMPLE_RATE
    timed = [Phone(p.label, min((p.start + shift) / spec.tempo, end),
                   min((p.end + shift) / spec.tempo, end), p.stress) for p in phones]
    if shift > 0:
        timed.insert(0, Phone(SILENCE, 0.0, timed[0].start, 0))
    timed = extend_to(merge_silences([p for p in timed if p.end > p.start]), end)
    return y.astype(np.float32), timed
