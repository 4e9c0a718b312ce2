"""Smoothness and agility: jitter (mean jerk), acceleration at FOPPAS clip seams, and the
motion / velocity / acceleration curves of DiffSHEG's figure 13."""

from __future__ import annotations

import numpy as np

from ...errors import DiffshegError


def _frames(x: np.ndarray, need: int) -> np.ndarray:
    x = np.asarray(x, np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or len(x) < need:
        raise DiffshegError(f"need a (T, D) motion with at least {need} frames, got shape {x.shape}")
    return x


def mean_jerk(x: np.ndarray, fps: float) -> float:
    """Mean absolute third derivative over frames and channels (units per s^3)."""
    x = _frames(x, 4)
    return float(np.abs(np.diff(x, n=3, axis=0)).mean() * fps**3)


def acceleration_per_frame(x: np.ndarray, fps: float) -> np.ndarray:
    """(T,) mean absolute second derivative over channels; the ends repeat their neighbour."""
    x = _frames(x, 3)
    acc = np.abs(np.diff(x, n=2, axis=0)).mean(axis=1) * fps**2
    return np.concatenate([acc[:1], acc, acc[-1:]])


def foppas_seams(n_frames: int, clip_len: int, overlap: int) -> list[int]:
    """First frame of every window after the first, for windows of `clip_len` frames
    stepping by `clip_len - overlap` (the FOPPAS layout)."""
    step = clip_len - overlap
    if step <= 0:
        raise DiffshegError(f"overlap {overlap} must be smaller than the clip length {clip_len}")
    return list(range(step, max(n_frames - overlap, step), step))


def seam_smoothness(x: np.ndarray, fps: float, seams: list[int], overlap: int) -> float:
    """Mean acceleration over the seam regions (each overlap plus one frame either side)
    divided by the mean acceleration everywhere else: 1 means seams are invisible."""
    acc = acceleration_per_frame(x, fps)
    at_seam = np.zeros(len(acc), dtype=bool)
    for s in seams:
        at_seam[max(s - 1, 0) : min(s + overlap + 1, len(acc))] = True
    if not at_seam.any() or at_seam.all():
        raise DiffshegError("seam smoothness needs frames both at and away from clip seams")
    inside = acc[~at_seam].mean()
    return float(acc[at_seam].mean() / max(inside, 1e-12))


def motion_curves(x_normalised: np.ndarray) -> dict[str, np.ndarray]:
    """DiffSHEG figure 13: frame-wise channel mean of the normalised motion, of the absolute
    frame difference (velocity) and of the absolute difference of velocity (acceleration)."""
    x = _frames(x_normalised, 3)
    vel = np.diff(x, axis=0)
    return {
        "motion": x.mean(axis=1),
        "velocity": np.abs(vel).mean(axis=1),
        "acceleration": np.abs(np.diff(vel, axis=0)).mean(axis=1),
    }


def speed(x: np.ndarray, fps: float, group: int = 3) -> np.ndarray:
    """(T-1,) speed between consecutive frames: mean over parameter groups (joints) of the
    L2 norm of their change, per second."""
    x = _frames(x, 2)
    if x.shape[1] % group:
        raise DiffshegError(f"{x.shape[1]} channels do not split into groups of {group}")
    d = np.diff(x, axis=0).reshape(len(x) - 1, -1, group)
    return np.linalg.norm(d, axis=2).mean(axis=1) * fps
