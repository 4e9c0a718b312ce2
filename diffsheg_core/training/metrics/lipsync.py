"""Lip-sync: phoneme contrast of mouth opening (open vowels against bilabials) and the
correlation of mouth opening with the speech envelope or a reference, at the best lag."""

from __future__ import annotations

import numpy as np

from ...errors import DiffshegError
from .textgrid import Interval

OPEN_VOWELS = ("AA", "AE", "AH", "AO", "AW", "AY")
BILABIALS = ("P", "B", "M")
ENVELOPE_RATE = 100.0
"""Hz at which mouth curves and speech envelopes are compared."""


def base_phone(label: str) -> str:
    """ARPAbet phone without its stress digit, upper case ('AH0' -> 'AH')."""
    return label.strip().upper().rstrip("012")


def values_at(curve: np.ndarray, fps: float, times: np.ndarray) -> np.ndarray:
    """Linear interpolation of a per-frame curve (frame i at i / fps) at `times` seconds."""
    return np.interp(np.asarray(times, np.float64), np.arange(len(curve)) / fps, curve)


def phone_middles(phones: list[Interval], wanted: tuple[str, ...], duration: float) -> np.ndarray:
    """Middle times of the intervals whose base phone is in `wanted` and that lie within the motion."""
    return np.array([p.middle for p in phones if base_phone(p.label) in wanted and p.end <= duration])


def phoneme_contrast(curve: np.ndarray, fps: float, phones: list[Interval],
                     open_phones: tuple[str, ...] = OPEN_VOWELS,
                     closed_phones: tuple[str, ...] = BILABIALS) -> dict[str, float]:
    """Mean of `curve` at the middle of open vowels and of bilabials, and their ratio."""
    duration = len(curve) / fps
    at_open = phone_middles(phones, open_phones, duration)
    at_closed = phone_middles(phones, closed_phones, duration)
    if len(at_open) == 0 or len(at_closed) == 0:
        raise DiffshegError(
            f"phone timings hold {len(at_open)} open vowels and {len(at_closed)} bilabials within "
            f"{duration:.1f} s of motion; phoneme contrast needs both")
    open_mean = float(values_at(curve, fps, at_open).mean())
    closed_mean = float(values_at(curve, fps, at_closed).mean())
    return {
        "open": open_mean,
        "bilabial": closed_mean,
        "ratio": open_mean / closed_mean if closed_mean > 0 else float("inf"),
        "n_open": len(at_open),
        "n_bilabial": len(at_closed),
    }


def speech_envelope_db(samples: np.ndarray, sample_rate: int, rate: float = ENVELOPE_RATE,
                       floor_db: float = 60.0) -> np.ndarray:
    """RMS level in dB in windows of 2 / rate seconds every 1 / rate seconds, floored at
    `floor_db` below the loudest window (so silence does not dominate)."""
    y = np.asarray(samples, np.float64)
    hop = sample_rate / rate
    n = int(len(y) / hop)
    if n < 2:
        raise DiffshegError("audio too short for a speech envelope")
    win = int(round(2 * hop))
    padded = np.concatenate([np.zeros(win // 2), y, np.zeros(win)])
    starts = (np.arange(n) * hop).astype(int)
    power = np.cumsum(np.concatenate([[0.0], padded**2]))
    rms = np.sqrt((power[starts + win] - power[starts]) / win)
    db = 20 * np.log10(np.maximum(rms, 1e-10))
    return np.maximum(db, db.max() - floor_db)


def lagged_correlation(a: np.ndarray, b: np.ndarray, rate: float,
                       max_lag: float = 0.15) -> tuple[float, float]:
    """Best Pearson correlation of `a` and `b` (same rate) over lags within +-max_lag
    seconds, and that lag; a positive lag means `a` follows `b`."""
    n = min(len(a), len(b))
    a, b = np.asarray(a[:n], np.float64), np.asarray(b[:n], np.float64)
    max_k = int(round(max_lag * rate))
    if n - max_k < 3:
        raise DiffshegError("sequences too short to correlate")
    best = (-np.inf, 0.0)
    for k in range(-max_k, max_k + 1):
        x, y = (a[k:], b[: n - k]) if k >= 0 else (a[: n + k], b[-k:])
        if x.std() == 0 or y.std() == 0:
            continue
        r = float(np.corrcoef(x, y)[0, 1])
        if r > best[0]:
            best = (r, k / rate)
    if not np.isfinite(best[0]):
        return 0.0, 0.0
    return best


def resample_curve(curve: np.ndarray, fps: float, rate: float = ENVELOPE_RATE) -> np.ndarray:
    """Per-frame curve at `fps` -> the same span sampled at `rate` Hz."""
    times = np.arange(int(len(curve) / fps * rate)) / rate
    return values_at(curve, fps, times)


def envelope_correlation(mouth: np.ndarray, fps: float, samples: np.ndarray,
                         sample_rate: int, max_lag: float = 0.15) -> tuple[float, float]:
    """Correlation of mouth opening with the speech envelope in dB at the best lag."""
    return lagged_correlation(resample_curve(mouth, fps), speech_envelope_db(samples, sample_rate),
                              ENVELOPE_RATE, max_lag)


def reference_correlation(mouth: np.ndarray, reference: np.ndarray, fps: float,
                          max_lag: float = 0.15) -> tuple[float, float]:
    """Correlation of mouth opening with a reference's mouth opening at the best lag."""
    return lagged_correlation(resample_curve(mouth, fps), resample_curve(reference, fps),
                              ENVELOPE_RATE, max_lag)


def voiced_reference_correlation(mouth: np.ndarray, reference: np.ndarray, fps: float, samples: np.ndarray,
                                 sample_rate: int) -> float:
    """reference_correlation over the voiced frames only (qc.voiced_frames), at the best lag
    within qc.MAX_LAG: how closely a mouth moves with a reference mouth (a motion capture's)
    while the voice sounds, which shared pauses cannot flatter."""
    from ...qc import MAX_LAG, lagged_correlation, voiced_frames

    n = min(len(mouth), len(reference))
    voiced = voiced_frames(samples, sample_rate, fps, n)
    return lagged_correlation(np.asarray(mouth[:n], np.float64), np.asarray(reference[:n], np.float64),
                              int(MAX_LAG * fps + 1e-9), where=voiced)


def phone_following(mouth: np.ndarray, fps: float, phones: list[Interval], samples: np.ndarray,
                    sample_rate: int) -> float:
    """Correlation over the voiced frames (qc.voiced_frames) of a mouth-opening curve with
    the viseme jaw of `phones`: how closely the mouth follows what is said, whatever the
    loudness."""
    from ...qc import voiced_frames

    voiced = voiced_frames(samples, sample_rate, fps, len(mouth))
    return float(np.corrcoef(mouth[voiced], viseme_jaw(phones, len(mouth), fps)[voiced])[0, 1])


def viseme_jaw(phones: list[Interval], n_frames: int, fps: float) -> np.ndarray:
    """(n_frames,) the jaw opening the teacher's visemes give these timed ARPAbet phones (the
    corpus's coarticulation, neutral stress and effort): what lip-sync that follows the
    phones exactly would do. Gaps and labels it has no viseme for ('sp', '') are silence."""
    from ..corpus.coarticulation import MOUTH_CHANNELS, mouth_curves, viseme_phones
    from ..corpus.phones import SILENCE, VOWELS, Phone

    known, out, t = viseme_phones(), [], 0.0
    for p in sorted(phones, key=lambda p: p.start):
        label = base_phone(p.label)
        if label not in known or p.end <= p.start:
            continue
        if p.start > t:
            out.append(Phone(SILENCE, t, p.start))
        out.append(Phone(label, max(p.start, t), p.end, 1 if label in VOWELS else 0))
        t = max(t, p.end)
    out.append(Phone(SILENCE, t, max(t + 0.1, n_frames / fps)))
    return mouth_curves(out, np.arange(n_frames) / fps)[:, MOUTH_CHANNELS.index("jawOpen")]
