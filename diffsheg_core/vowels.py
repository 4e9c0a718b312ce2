"""VRM's five mouth shapes (A, I, U, E, O) from ARKit weights, for faces that talk through
vowel shapes instead of ARKit's muscles: VRM avatars over VMC (live/vmc.py) and Ready
Player Me / VRoid faces in Blender without working ARKit keys (the add-on's visemes.py).

The mouth is split by three amounts: opening o = min(1, 2 jawOpen) (speech seldom opens
ARKit's jaw past half, VRM's A is a full 'ah'), rounding r = max(mouthFunnel, mouthPucker)
and spreading s = max(mean mouthStretch, mean mouthSmile):

    A = o (1 - r)(1 - s)   E = o s (1 - r)   O = o r
    I = (1 - o) s (1 - r)  U = (1 - o) r

They add up to at most 1, so together they never open the mouth past one full vowel (a sum
of shape keys each driven on its own would stack an A and an O into one gaping mouth).
numpy only: it runs inside Blender.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

VOWELS: tuple[str, ...] = ("A", "I", "U", "E", "O")
CHANNELS: tuple[str, ...] = ("jawOpen", "mouthFunnel", "mouthPucker", "mouthStretchLeft", "mouthStretchRight",
                             "mouthSmileLeft", "mouthSmileRight")
"""The ARKit channels the vowels are made from."""
OPEN_GAIN = 2.0  # jawOpen -> mouth opening


def vowel_weights(face: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """(T, 5) weights of A, I, U, E, O from (T, C) ARKit weights named `names` (a channel
    missing counts as 0)."""
    face = np.clip(np.asarray(face, dtype=np.float64), 0.0, 1.0)
    index = {name: i for i, name in enumerate(names)}

    def w(name: str) -> np.ndarray:
        return face[:, index[name]] if name in index else np.zeros(len(face))

    o = np.minimum(1.0, OPEN_GAIN * w("jawOpen"))
    r = np.maximum(w("mouthFunnel"), w("mouthPucker"))
    s = np.maximum((w("mouthStretchLeft") + w("mouthStretchRight")) / 2, (w("mouthSmileLeft") + w("mouthSmileRight")) / 2)
    return np.stack([o * (1 - r) * (1 - s), (1 - o) * s * (1 - r), (1 - o) * r, o * s * (1 - r), o * r], axis=1)
