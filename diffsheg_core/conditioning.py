"""What the network is conditioned on besides the motion, frame by frame: `Conditioning`,
the speech features (`SpeechFeatures`, made by `speech_features`) and the style of every
frame (`style.StyleTrack`).

The pipeline and the live engine make it, FOPPAS cuts it into windows (`frames`) and the
eps function hands a window's inputs to the network (`pipeline.make_eps_fn_factory`): each
part by name, never glued into columns and cut apart again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np

from .style import StyleTrack


@dataclass(frozen=True)
class SpeechFeatures:
    """The speech features of T motion frames: the mel frame centred on each, and the
    model's second speech input when it has one (phonetic posteriors, or HuBERT)."""

    mel: np.ndarray                       # (T, mel_dim) float32
    speech: Optional[np.ndarray] = None   # (T, speech_dim) float32; None: the model takes mel only

    def __len__(self) -> int:
        return len(self.mel)

    def frames(self, first: int, end: int) -> SpeechFeatures:
        """Frames [first, end)."""
        return SpeechFeatures(self.mel[first:end], None if self.speech is None else self.speech[first:end])

    @staticmethod
    def join(parts: Iterable[SpeechFeatures]) -> SpeechFeatures:
        """Consecutive pieces (a long recording's), as one."""
        parts = list(parts)
        speech = None if parts[0].speech is None else np.concatenate([p.speech for p in parts])
        return SpeechFeatures(np.concatenate([p.mel for p in parts]), speech)


@dataclass(frozen=True)
class Conditioning:
    """The network's conditioning for T frames: their speech features and their style."""

    features: SpeechFeatures
    style: StyleTrack

    def __len__(self) -> int:
        return len(self.features)

    def frames(self, first: int, end: int) -> Conditioning:
        """Frames [first, end): a window, or what is left of a stream."""
        return Conditioning(self.features.frames(first, end), self.style.frames(first, end))

    @staticmethod
    def join(parts: Iterable[Conditioning]) -> Conditioning:
        """Consecutive pieces, as one."""
        parts = list(parts)
        return Conditioning(SpeechFeatures.join(p.features for p in parts), StyleTrack.join(p.style for p in parts))
