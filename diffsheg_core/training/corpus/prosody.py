"""Pitch accents: which stressed syllables stand out, and how much, from the phones'
lexical stress and the speech itself (vowel duration, loudness and F0 from YIN)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .phones import Phone

F0_MIN, F0_MAX = 60.0, 420.0


@dataclass(frozen=True)
class Accent:
    """A prominent syllable: `time` (s) near its vowel onset, `strength` in (0, 1]."""

    time: float
    strength: float


def _zscore(x: np.ndarray) -> np.ndarray:
    return (x - x.mean()) / (x.std() + 1e-9) if len(x) > 1 else np.zeros_like(x)


def _vowel_f0(samples: np.ndarray, sample_rate: int, vowels: list[Phone]) -> np.ndarray:
    """Median F0 (semitones above 55 Hz) per vowel; NaN where YIN finds no periodic voice."""
    import librosa

    hop = max(sample_rate // 100, 1)
    frame = int(2 ** np.ceil(np.log2(sample_rate / F0_MIN * 2.2)))
    if len(samples) < frame:
        return np.full(len(vowels), np.nan)
    f0 = librosa.yin(samples, fmin=F0_MIN, fmax=F0_MAX, sr=sample_rate, frame_length=frame,
                     hop_length=hop, center=True)
    rms = librosa.feature.rms(y=samples, frame_length=frame, hop_length=hop, center=True)[0]
    n = min(len(f0), len(rms))
    f0, rms = f0[:n], rms[:n]
    voiced = (rms > 0.1 * np.percentile(rms, 95)) & (f0 > F0_MIN * 1.05) & (f0 < F0_MAX * 0.95)
    out = np.full(len(vowels), np.nan)
    for i, v in enumerate(vowels):
        a, b = int(v.start * 100), max(int(v.end * 100), int(v.start * 100) + 1)
        sel = f0[a:b][voiced[a:b]]
        if len(sel):
            out[i] = 12 * np.log2(np.median(sel) / 55.0)
    return out


def _vowel_level(samples: np.ndarray, sample_rate: int, vowels: list[Phone]) -> np.ndarray:
    """RMS level in dB of each vowel."""
    out = np.zeros(len(vowels))
    for i, v in enumerate(vowels):
        seg = samples[int(v.start * sample_rate): max(int(v.end * sample_rate), int(v.start * sample_rate) + 1)]
        out[i] = 10 * np.log10(np.mean(seg.astype(np.float64) ** 2) + 1e-10) if len(seg) else -100.0
    return out


def find_accents(samples: np.ndarray, sample_rate: int, phones: list[Phone]) -> list[Accent]:
    """Accents on lexically stressed vowels (all vowels when stress is unknown) that are
    prominent: longer, louder or higher than the utterance's typical vowel."""
    vowels = [p for p in phones if p.is_vowel]
    if not vowels:
        return []
    duration = _zscore(np.log(np.array([v.end - v.start for v in vowels])))
    level = _zscore(_vowel_level(samples, sample_rate, vowels))
    f0 = _vowel_f0(samples, sample_rate, vowels)
    pitch = np.zeros(len(vowels))
    if np.isfinite(f0).sum() > 1:
        ok = np.isfinite(f0)
        pitch[ok] = _zscore(f0[ok])
    lexical = np.array([{1: 1.0, 2: 0.3, 0: -1.0}.get(v.stress, 0.0) for v in vowels])
    score = lexical + 0.6 * duration + 0.5 * level + 0.5 * pitch
    candidates = np.array([v.stress in (1, -1) for v in vowels]) & (score > np.median(score))
    strength = 1.0 / (1.0 + np.exp(-(score - np.median(score))))
    return [Accent(v.start + 0.25 * (v.end - v.start), float(s))
            for v, s, keep in zip(vowels, strength, candidates) if keep]


EFFORT_PER_DB = 0.04
"""How much wider the jaw opens on a vowel per dB it is louder than the utterance's typical
vowel: speakers open the jaw further when they speak with more effort (Schulman 1989, loud
against normal speech), in every language."""
EFFORT_RANGE = (0.6, 1.4)


def vowel_effort(samples: np.ndarray, sample_rate: int, phones: list[Phone]) -> np.ndarray:
    """Per phone, the jaw-opening factor of its vocal effort: 1 + EFFORT_PER_DB times its
    level above the utterance's median vowel level (clipped to EFFORT_RANGE); 1 for
    consonants and pauses."""
    out = np.ones(len(phones))
    index = [i for i, p in enumerate(phones) if p.is_vowel]
    if index:
        level = _vowel_level(samples, sample_rate, [phones[i] for i in index])
        out[index] = np.clip(1 + EFFORT_PER_DB * (level - np.median(level)), *EFFORT_RANGE)
    return out
