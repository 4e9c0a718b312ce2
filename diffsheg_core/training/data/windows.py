"""Training clips: sliding windows over takes, normalised, as a torch Dataset."""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from ...errors import DiffshegError
from .normalise import NormStats
from .take import Take


def window_starts(n_frames: int, clip_len: int, stride: int) -> list[int]:
    """Start frames of every full window of `clip_len` frames, `stride` apart."""
    if clip_len < 1 or stride < 1:
        raise DiffshegError(f"clip length ({clip_len}) and stride ({stride}) must be at least 1")
    return list(range(0, n_frames - clip_len + 1, stride))


class ClipDataset(Dataset):
    """Every window of every take. Items: motion (L, D) normalised, mel (L, 128),
    style (int), mask (D,) float (1 where the data loss takes the channel: where the take
    holds it, or its `taught` channels), and extra (L, E) when the takes carry a second
    speech input."""

    def __init__(self, takes: list[Take], clip_len: int, stride: int | list[int], stats: NormStats):
        """stride: frames between windows, for every take or one per take (datasets of
        different sizes trained together)."""
        self.takes = takes
        self.clip_len = clip_len
        self.stats = stats
        strides = stride if isinstance(stride, list) else [stride] * len(takes)
        self.index = [(i, s) for i, (t, step) in enumerate(zip(takes, strides, strict=True))
                      for s in window_starts(t.n_frames, clip_len, step)]
        if not self.index:
            longest = max((t.n_frames for t in takes), default=0)
            raise DiffshegError(
                f"no training clips: {len(takes)} usable takes, the longest {longest} frames, "
                f"but a clip needs {clip_len}; add data or shorten the clip length")
        self._normalised = [stats.normalise(t.motion).astype(np.float32) * t.mask for t in takes]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        take_i, start = self.index[i]
        take, end = self.takes[take_i], start + self.clip_len
        item = {
            "motion": torch.from_numpy(self._normalised[take_i][start:end]),
            "mel": torch.from_numpy(take.mel[start:end]),
            "style": torch.tensor(take.style, dtype=torch.long),
            "mask": torch.from_numpy((take.mask if take.taught is None else take.taught).astype(np.float32)),
        }
        if take.extra is not None:
            item["extra"] = torch.from_numpy(take.extra[start:end])
        return item
