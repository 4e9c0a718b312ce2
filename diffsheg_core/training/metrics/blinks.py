"""Blinks: how often the eyes close and for how long."""

from __future__ import annotations

import numpy as np

DEFAULT_THRESHOLD = 0.5


def detect_blinks(signal: np.ndarray, fps: float,
                  threshold: float = DEFAULT_THRESHOLD) -> list[tuple[float, float]]:
    """(start, end) seconds of every run of the blink signal above `threshold`; the
    crossings are interpolated between frames, so durations are not quantised to 1 / fps."""
    s = np.asarray(signal, np.float64)
    above = s > threshold
    edges = np.diff(above.astype(int))
    starts, ends = list(np.flatnonzero(edges == 1) + 1), list(np.flatnonzero(edges == -1) + 1)
    if len(s) and above[0]:
        starts.insert(0, 0)
    if len(s) and above[-1]:
        ends.append(len(s))

    def crossing(i: int) -> float:
        """Time where the signal crosses the threshold between frames i - 1 and i."""
        if i <= 0 or i >= len(s):
            return min(max(i, 0), len(s)) / fps
        a, b = s[i - 1], s[i]
        return (i - 1 + (threshold - a) / (b - a)) / fps

    return [(crossing(a), crossing(b)) for a, b in zip(starts, ends)]


def blink_stats(signal: np.ndarray, fps: float, threshold: float = DEFAULT_THRESHOLD) -> dict[str, float]:
    """Blinks per minute and their mean / min / max duration in seconds."""
    blinks = detect_blinks(signal, fps, threshold)
    minutes = len(signal) / fps / 60.0
    durations = np.array([b - a for a, b in blinks])
    return {
        "count": len(blinks),
        "per_minute": len(blinks) / minutes if minutes > 0 else 0.0,
        "mean_duration": float(durations.mean()) if len(durations) else 0.0,
        "min_duration": float(durations.min()) if len(durations) else 0.0,
        "max_duration": float(durations.max()) if len(durations) else 0.0,
    }
