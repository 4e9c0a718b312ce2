"""Beat alignment (BA): audio onsets against motion beats (velocity minima), scored with
the Gaussian kernel of DiffSHEG eq. 12 as BEAT implements it: for every audio beat, the
distance to the nearest motion beat."""

from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks

from ...errors import DiffshegError
from .smoothness import speed

DEFAULT_SIGMA = 0.3
"""Kernel width in seconds (BEAT's setting)."""


MIN_BEAT_GAP = 0.2
"""Seconds between two audio beats at least: closer onsets could not show as two stops
in motion at 15 fps."""


def audio_beats(samples: np.ndarray, sample_rate: int, min_gap: float = MIN_BEAT_GAP) -> np.ndarray:
    """Onset times in seconds (librosa's spectral-flux onset detector), at least `min_gap` apart."""
    import librosa

    y = np.asarray(samples, np.float32)
    if y.ndim != 1 or len(y) == 0:
        raise DiffshegError(f"audio beats need mono samples, got shape {y.shape}")
    hop = 512
    return librosa.onset.onset_detect(y=y, sr=sample_rate, hop_length=hop, units="time",
                                      wait=int(np.ceil(min_gap * sample_rate / hop)))


def motion_beats(x: np.ndarray, fps: float, group: int = 3,
                 min_prominence: float = 0.1) -> np.ndarray:
    """Times (seconds) where the motion comes to a momentary stop: local minima of the
    joint speed whose dip is at least `min_prominence` times the 95th percentile speed,
    refined between frames by a parabola through the minimum and its neighbours."""
    v = speed(x, fps, group)
    if len(v) < 3:
        return np.zeros(0)
    prominence = min_prominence * max(np.percentile(v, 95), 1e-9)
    idx, _ = find_peaks(-v, prominence=prominence)
    idx = idx[(idx > 0) & (idx < len(v) - 1)]
    left, mid, right = v[idx - 1], v[idx], v[idx + 1]
    curvature = left - 2 * mid + right
    offset = np.where(curvature > 0, 0.5 * (left - right) / np.where(curvature > 0, curvature, 1), 0.0)
    # speed sample i lies between frames i and i + 1
    return (idx + 0.5 + np.clip(offset, -0.5, 0.5)) / fps


def beat_alignment(audio_times: np.ndarray, motion_times: np.ndarray,
                   sigma: float = DEFAULT_SIGMA) -> float:
    """Mean over audio beats of exp(-d^2 / (2 sigma^2)), d = distance to the nearest
    motion beat; 0 when the motion has no beats."""
    a = np.asarray(audio_times, np.float64)
    m = np.asarray(motion_times, np.float64)
    if len(a) == 0:
        raise DiffshegError("beat alignment needs audio with at least one onset (is the audio silent?)")
    if len(m) == 0:
        return 0.0
    d = np.abs(a[:, None] - m[None, :]).min(axis=1)
    return float(np.exp(-(d**2) / (2 * sigma**2)).mean())
