"""Normalisation statistics: per-channel mean and std of model-space motion."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import DiffshegError
from ...rigs import Layout
from .take import Take

MIN_STD = 1e-4
"""Channels that barely move get this std, so normalising never divides by ~0."""


@dataclass
class NormStats:
    mean: np.ndarray
    std: np.ndarray

    def __post_init__(self) -> None:
        self.mean = np.asarray(self.mean, np.float32)
        self.std = np.maximum(np.asarray(self.std, np.float32), MIN_STD)
        if self.mean.shape != self.std.shape or self.mean.ndim != 1:
            raise DiffshegError(f"normalisation mean {self.mean.shape} and std {self.std.shape} differ")

    def normalise(self, x: np.ndarray) -> np.ndarray:
        return (x - self.mean) / self.std

    def denormalise(self, x: np.ndarray) -> np.ndarray:
        return x * self.std + self.mean


def compute_stats(takes: list[Take]) -> NormStats:
    """Mean and std over every frame of `takes`, per channel, using only the takes that
    hold the channel (mask); channels no take holds get mean 0, std 1."""
    if not takes:
        raise DiffshegError("no usable training takes to compute normalisation statistics from")
    dim = takes[0].motion.shape[1]
    total, total_sq, count = np.zeros(dim), np.zeros(dim), np.zeros(dim)
    for take in takes:
        m = take.motion.astype(np.float64)
        total += np.where(take.mask, m.sum(axis=0), 0.0)
        total_sq += np.where(take.mask, (m**2).sum(axis=0), 0.0)
        count += np.where(take.mask, len(m), 0)
    held = count > 0
    mean = np.where(held, total / np.maximum(count, 1), 0.0)
    var = np.where(held, total_sq / np.maximum(count, 1) - mean**2, 1.0)
    return NormStats(mean, np.sqrt(np.maximum(var, 0.0)))


def official_stats(layout: Layout, folder: str | Path) -> NormStats:
    """The statistics the official checkpoints were trained with, from `folder`
    (../shared/data/beat for `beat`, ../shared/data/show for `smplx`)."""
    from ...official_checkpoints import official_stats as read_official

    mean, std = read_official("beat" if layout.name == "beat" else "show", folder)
    if len(mean) != layout.dim:
        raise DiffshegError(f"official statistics in {folder} have {len(mean)} channels, layout "
                            f"'{layout.name}' needs {layout.dim}")
    return NormStats(mean, std)
