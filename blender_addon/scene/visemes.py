"""Faces without the ARKit set: viseme and eye-close shape keys driven from ARKit weights.

Ready Player Me / Oculus avatars carry `viseme_*` keys, VRoid models `Fcl_MTH_A/I/U/E/O`
and `Fcl_EYE_Close_L/R` (their ARKit-named keys, where present, often move nothing). When
a face has no working key for a group's ARKit channels, each such key is driven from the
motion's ARKit weights, so the face still talks and blinks: the five vowel keys by
`diffsheg_core.vowels` (the same A, I, U, E, O a VRM avatar gets over VMC, adding up to at
most one full vowel), the lips-shut and eye-close keys by a weighted sum clipped to [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diffsheg_core.vowels import CHANNELS as VOWEL_CHANNELS, VOWELS, vowel_weights

# group: (the ARKit channel whose working key means the group is covered,
#         {key names: a vowel of diffsheg_core.vowels, or {ARKit channel: weight} summed})
DERIVED: dict[str, tuple[str, dict[tuple[str, ...], str | dict[str, float]]]] = {
    "mouth": ("jawOpen", {
        ("viseme_aa", "Fcl_MTH_A"): "A",
        ("viseme_I", "Fcl_MTH_I"): "I",
        ("viseme_U", "Fcl_MTH_U"): "U",
        ("viseme_E", "Fcl_MTH_E"): "E",
        ("viseme_O", "Fcl_MTH_O"): "O",
        ("viseme_PP",): {"mouthClose": 1.0, "mouthPressLeft": 0.5, "mouthPressRight": 0.5},
    }),
    "left eye": ("eyeBlinkLeft", {("Fcl_EYE_Close_L",): {"eyeBlinkLeft": 1.0}}),
    "right eye": ("eyeBlinkRight", {("Fcl_EYE_Close_R",): {"eyeBlinkRight": 1.0}}),
}


@dataclass(frozen=True)
class DerivedKey:
    """How one shape key follows the motion's face channels: a vowel, or a weighted sum."""

    face_names: tuple[str, ...]
    vowel: str | None = None
    weights: dict[int, float] = field(default_factory=dict)  # face channel index -> weight

    @property
    def channels(self) -> frozenset[int]:
        """The face channels the key follows."""
        if self.vowel is None:
            return frozenset(self.weights)
        return frozenset(i for i, name in enumerate(self.face_names) if name in VOWEL_CHANNELS)

    def values(self, face: np.ndarray) -> np.ndarray:
        """(T,) the key's weights from (T, C) face weights."""
        if self.vowel is not None:
            return vowel_weights(face, self.face_names)[:, VOWELS.index(self.vowel)]
        return np.clip(sum(w * face[:, i] for i, w in self.weights.items()), 0.0, 1.0)


def derived_keys(covered: set[str], face_names: list[str]) -> list[tuple[tuple[str, ...], DerivedKey]]:
    """(candidate key names, how the key follows the face) for every derived key of the
    groups whose ARKit channel has no working shape key (`covered`: the channels that have
    one) and that the motion's face channels can drive."""
    names = tuple(face_names)
    index = {name: i for i, name in enumerate(names)}
    out = []
    for anchor, keys in DERIVED.values():
        if anchor in covered or anchor not in index:
            continue
        for candidates, source in keys.items():
            key = (DerivedKey(names, vowel=source) if isinstance(source, str)
                   else DerivedKey(names, weights={index[c]: w for c, w in source.items() if c in index}))
            if key.channels:
                out.append((candidates, key))
    return out
