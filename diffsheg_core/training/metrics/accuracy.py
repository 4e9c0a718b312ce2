"""Accuracy against ground truth: PCM and its semantically weighted form SRGR."""

from __future__ import annotations

import numpy as np

from ...errors import DiffshegError


def _correct(pred: np.ndarray, target: np.ndarray, delta: float, group: int) -> np.ndarray:
    """(T, D/group) booleans: the L2 error of each parameter group is below delta."""
    pred, target = np.asarray(pred, np.float64), np.asarray(target, np.float64)
    if pred.shape != target.shape or pred.ndim != 2:
        raise DiffshegError(
            f"prediction {pred.shape} and ground truth {target.shape} must be equal (T, D) arrays; "
            "trim both to the same frame count first")
    if pred.shape[1] % group:
        raise DiffshegError(f"{pred.shape[1]} channels do not split into groups of {group}")
    err = (pred - target).reshape(len(pred), -1, group)
    return np.linalg.norm(err, axis=2) < delta


def pcm(pred: np.ndarray, target: np.ndarray, delta: float = 1.0, group: int = 3) -> float:
    """Percent of correct motion parameters (DiffSHEG eq. 10), as a fraction in [0, 1].

    `group` = 3 treats each joint's axis-angle as one parameter; 1 treats every channel
    (e.g. blendshape weights) separately. DiffSHEG uses delta = 1.0 on SHOW."""
    return float(_correct(pred, target, delta, group).mean())


def srgr(pred: np.ndarray, target: np.ndarray, frame_weights: np.ndarray,
         delta: float = 1.0, group: int = 3) -> float:
    """PCM with each frame weighted by its semantic relevance (BEAT's SRGR), divided by the
    total weight so that a perfect prediction scores 1 on any take. BEAT divides by the frame
    count instead and rescales by 1 / 0.165 (its data set's mean weight): BEAT's value is this
    one times the take's mean weight / 0.165."""
    correct = _correct(pred, target, delta, group).mean(axis=1)
    w = np.asarray(frame_weights, np.float64)
    if w.shape != correct.shape:
        raise DiffshegError(f"need one semantic weight per frame ({len(correct)}), got {w.shape}")
    if w.sum() <= 0:
        raise DiffshegError("semantic frame weights sum to zero")
    return float((w * correct).sum() / w.sum())
