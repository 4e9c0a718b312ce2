"""Faces without the ARKit set: viseme and eye-close shape keys driven from ARKit weights.

Ready Player Me / Oculus avatars carry `viseme_*` keys, VRoid models `Fcl_MTH_A/I/U/E/O`
and `Fcl_EYE_Close_L/R` (their ARKit-named keys, where present, often move nothing). When
a face has no working key for a group's ARKit channels, each such key is driven by a
weighted sum of the motion's ARKit weights, clipped to [0, 1], so the face still talks and
blinks. Standard library only: the weights are this project's own approximations of the
mouth shapes (open vowel from the jaw, rounded vowels from funnel and pucker, spread vowels
from stretch and smile, lips shut from mouthClose and press).
"""

from __future__ import annotations

# group: (the ARKit channel whose working key means the group is covered, {key names: weights})
DERIVED: dict[str, tuple[str, dict[tuple[str, ...], dict[str, float]]]] = {
    "mouth": ("jawOpen", {
        ("viseme_aa", "Fcl_MTH_A"): {"jawOpen": 1.0},
        ("viseme_O", "Fcl_MTH_O"): {"jawOpen": 0.6, "mouthFunnel": 1.0},
        ("viseme_U", "Fcl_MTH_U"): {"mouthPucker": 1.0, "mouthFunnel": 0.5},
        ("viseme_I", "Fcl_MTH_I"): {"mouthStretchLeft": 0.5, "mouthStretchRight": 0.5, "jawOpen": 0.3},
        ("viseme_E", "Fcl_MTH_E"): {"mouthSmileLeft": 0.5, "mouthSmileRight": 0.5, "jawOpen": 0.4},
        ("viseme_PP",): {"mouthClose": 1.0, "mouthPressLeft": 0.5, "mouthPressRight": 0.5},
    }),
    "left eye": ("eyeBlinkLeft", {("Fcl_EYE_Close_L",): {"eyeBlinkLeft": 1.0}}),
    "right eye": ("eyeBlinkRight", {("Fcl_EYE_Close_R",): {"eyeBlinkRight": 1.0}}),
}


def derived_keys(covered: set[str], face_names: list[str]) -> list[tuple[tuple[str, ...], dict[int, float]]]:
    """(candidate key names, {face channel index: weight}) for every derived key of the groups
    whose ARKit channel has no working shape key (`covered`: the channels that have one)."""
    index = {name: i for i, name in enumerate(face_names)}
    out = []
    for anchor, keys in DERIVED.values():
        if anchor in covered or anchor not in index:
            continue
        for names, weights in keys.items():
            out.append((names, {index[c]: w for c, w in weights.items() if c in index}))
    return out
