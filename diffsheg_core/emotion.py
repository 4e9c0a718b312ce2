"""Emotion: a mood and its intensity laid over generated motion, face and body.

The bundled model has no emotion input (it learned gesture styles only), so an emotion is
a performance layer applied to what the model made, the way an animator layers a mood over
a lip-synced take:

- the face through the ARKit channels the Facial Action Coding System gives each emotion
  (happy: AU6 cheek raiser and AU12 lip corner puller, cheek squint and mouth smile; sad:
  AU1 inner brow raiser and AU15 lip corner depressor; angry: AU4 brow lowerer, AU7 lid
  tightener, AU24 lip pressor; surprised: AU1+2 brows up and AU5 upper lid raiser, ...),
  raised towards a weight at full intensity and never past 1, while the expressions it
  opposes are relaxed. The channels that articulate speech (jaw, mouthClose, funnel,
  pucker, rolls, lower lip) are never touched, and the emotion's mouth channels give way
  where the lips close (mouthClose), so p, b and m still close; eyes wide give way to blinks.
- the body through energy (each joint's movement around its slow posture, a Gaussian of
  about half a second, scaled), sharpness (an unsharp mask on that movement: sharper
  strokes for anger) and posture (the head pitched down for sadness, back for surprise;
  the chest slumped for sadness).

An emotion changes over time like a style: `emotion_at` ((seconds, emotion), ...) and the
add-on's timeline markers `emotion:sad`; each change eases in over about a third of a second.
numpy only: it runs inside Blender.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, replace

import numpy as np

from .errors import DiffshegError
from .motion import Motion, smooth_frames
from .rotations import (axis_angle_to_quaternion, quaternion_conjugate, quaternion_product,
                        quaternion_sequence_continuous, quaternion_to_axis_angle)


@dataclass(frozen=True)
class Emotion:
    """What one emotion does at full intensity. Face channels are ARKit names; a name
    without Left/Right means both sides."""

    raised: dict[str, float] = field(default_factory=dict)  # channel -> weight it is raised towards
    relaxed: tuple[str, ...] = ()     # channels of the expressions it opposes, scaled down
    energy: float = 1.0               # movement around the slow posture, times this
    sharpness: float = 0.0            # unsharp-mask gain on that movement (0: none)
    head_pitch: float = 0.0           # degrees, down positive (over the neck and head)
    chest_pitch: float = 0.0          # degrees of slump, down positive (the upper spine)


EMOTIONS: dict[str, Emotion] = {
    "neutral": Emotion(),
    "happy": Emotion({"cheekSquint": 0.55, "mouthSmile": 0.6, "eyeSquint": 0.25, "mouthDimple": 0.2},
                     ("mouthFrown", "browDown"), energy=1.15, head_pitch=-3.0),
    "sad": Emotion({"browInnerUp": 0.65, "mouthFrown": 0.5, "browDown": 0.15, "eyeLookDown": 0.2},
                   ("mouthSmile", "cheekSquint", "browOuterUp"), energy=0.7, head_pitch=12.0, chest_pitch=5.0),
    "angry": Emotion({"browDown": 0.7, "eyeSquint": 0.45, "mouthPress": 0.4, "noseSneer": 0.3},
                     ("mouthSmile", "browInnerUp", "browOuterUp"), energy=1.2, sharpness=0.4, head_pitch=4.0),
    "surprised": Emotion({"browInnerUp": 0.7, "browOuterUp": 0.7, "eyeWide": 0.6},
                         ("browDown", "eyeSquint", "mouthPress"), energy=1.1, sharpness=0.3, head_pitch=-5.0),
    "fearful": Emotion({"browInnerUp": 0.7, "browOuterUp": 0.3, "eyeWide": 0.5, "mouthStretch": 0.4},
                       ("mouthSmile", "browDown"), energy=0.85, head_pitch=2.0, chest_pitch=2.0),
    "disgusted": Emotion({"noseSneer": 0.6, "mouthUpperUp": 0.3, "browDown": 0.3, "mouthFrown": 0.2},
                         ("mouthSmile", "browInnerUp"), energy=0.9, head_pitch=-2.0),
}
NAMES = tuple(EMOTIONS)
"""The emotions, in the order of an emotion track's columns."""

EmotionSpec = "str | dict[str, float]"
"""An emotion: a name ('happy'), a name at an intensity ('happy=0.6'), or intensities of a
mix ({'happy': 0.5, 'surprised': 0.3}); intensities from 0 to 1, adding up to at most 1."""

EASE_S = 0.15        # Gaussian sigma of a change of emotion: eased in over about 0.35 s
POSTURE_S = 0.5      # Gaussian sigma of the slow posture the energy scales movement around
STROKE_FRAMES = 3.0  # Gaussian sigma, in model frames, of the unsharp mask's blur (a stroke, 0.2 s)
CLOSED_LIPS = 0.12   # mouthClose at which the emotion's mouth channels have given way entirely
KEPT_MOUTH = ("mouthPress",)  # mouth channels that close the lips themselves: not given way
RELAX = 0.8          # how far, at full intensity, an opposed channel is relaxed
CHAINS = {"beat": {"head": (("Neck", 0.4), ("Neck1", 0.6)), "chest": (("Spine", 1.0),)},
          "smplx": {"head": (("neck", 0.4), ("head", 0.6)), "chest": (("spine3", 0.6), ("spine2", 0.4))}}
"""Per layout, the joints a head or chest pitch is spread over, with their shares."""


def check_emotion(spec) -> dict[str, float]:
    """{name: intensity} of an emotion spec (neutral and zero intensities left out); a
    DiffshegError that names the emotions or the bounds for anything else."""
    if isinstance(spec, str):
        spec = parse_emotion(spec)
    if not isinstance(spec, dict):
        raise DiffshegError(f"emotion must be a name ({', '.join(NAMES)}), name=intensity (happy=0.6) or "
                            f"intensities of a mix ({{'happy': 0.5, 'surprised': 0.3}}), got {spec!r}")
    out: dict[str, float] = {}
    for name, value in spec.items():
        name = name.lower() if isinstance(name, str) else name
        if name not in EMOTIONS:
            raise DiffshegError(f"unknown emotion {name!r}: choose one of {', '.join(NAMES)}")
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0.0 <= float(value) <= 1.0:
            raise DiffshegError(f"the intensity of emotion {name!r} must be a number from 0 to 1, got {value!r}")
        if name != "neutral" and float(value) > 0:
            out[name] = float(value)
    if sum(out.values()) > 1.0 + 1e-6:
        raise DiffshegError(f"the intensities of emotion {spec!r} add up to {sum(out.values()):g}: give them at "
                            "most 1 in all")
    return out


def parse_emotion(text: str) -> dict[str, float]:
    """'happy' -> {'happy': 1.0}; 'happy=0.6' -> {'happy': 0.6}; 'happy=0.5,surprised=0.3' a mix."""
    out: dict[str, float] = {}
    for part in text.split(","):
        name, sep, value = (p.strip() for p in part.partition("="))
        name = name.lower()
        if not name or name in out:
            raise DiffshegError(f"emotion {text!r}: give each emotion once, as name or name=intensity "
                                "(happy=0.6)")
        try:
            out[name] = float(value) if sep else 1.0
        except ValueError:
            raise DiffshegError(f"emotion {part.strip()!r} is not name=intensity (happy=0.6)") from None
    return out


def check_emotion_at(changes) -> tuple[tuple[float, dict[str, float]], ...] | None:
    """Emotion changes as ((seconds, {name: intensity}), ...) sorted by time; None for none."""
    try:
        items = [(float(t), check_emotion(spec))
                 for t, spec in (changes.items() if isinstance(changes, dict) else changes)]
    except (TypeError, ValueError):
        raise DiffshegError(f"emotion_at must be (seconds, emotion) pairs, e.g. ((0, 'calm'), (12.5, 'sad')), "
                            f"got {changes!r}") from None
    times = [t for t, _ in items]
    if any(not math.isfinite(t) or t < 0 for t in times) or len(set(times)) != len(times):
        raise DiffshegError(f"emotion_at needs distinct times in seconds >= 0, got {sorted(times)}")
    return tuple(sorted(items, key=lambda item: item[0])) or None


def emotion_track(emotion: dict[str, float] | None, changes, n_frames: int, fps: float) -> np.ndarray | None:
    """(T, len(NAMES)) intensity of each emotion per frame: `emotion` until the first of
    `changes` ((seconds, {name: intensity}), ...), each change's from its frame on, eased.
    None where every frame is neutral."""
    track = np.zeros((n_frames, len(NAMES)))
    for (t, spec) in ((0.0, emotion or {}),) + tuple(changes or ()):
        row = np.zeros(len(NAMES))
        for name, value in spec.items():
            row[NAMES.index(name)] = value
        track[min(n_frames, int(round(t * fps))):] = row
    if not track.any():
        return None
    return _smooth(track, EASE_S * fps)


def apply_emotion(motion: Motion, track: np.ndarray, start: int = 0, end: int | None = None) -> Motion:
    """`motion` with the emotions of `track` (emotion_track) laid over frames [start, end);
    the frames outside are returned as they were."""
    end = motion.n_frames if end is None else end
    rotations, face = motion.rotations.copy(), motion.face.copy()
    face[start:end] = _face(motion, track)[start:end]
    rotations[start:end] = _body(motion, track)[start:end]
    return replace(motion, rotations=rotations, face=face)


def _face(motion: Motion, track: np.ndarray) -> np.ndarray:
    """The face with each emotion's channels raised and its opposed channels relaxed."""
    names = {n: i for i, n in enumerate(motion.face_names)}
    if "mouthClose" not in names:  # not ARKit (an SMPL-X model's FLAME face): the body only
        return motion.face
    face = motion.face.astype(np.float64)
    lips_open = 1.0 - np.clip(face[:, names["mouthClose"]] / CLOSED_LIPS, 0.0, 1.0)
    blink = {side: face[:, names[f"eyeBlink{side}"]] for side in ("Left", "Right") if f"eyeBlink{side}" in names}
    for k, name in enumerate(NAMES):
        intensity = track[:, k]
        if not intensity.any():
            continue
        emotion = EMOTIONS[name]
        for channel, weight in emotion.raised.items():
            for column, side in _columns(channel, names):
                gate = lips_open if channel.startswith("mouth") and channel not in KEPT_MOUTH else 1.0
                if channel == "eyeWide" and side in blink:
                    gate = 1.0 - blink[side]
                face[:, column] += intensity * weight * gate * np.clip(1.0 - face[:, column], 0.0, None)
        for channel in emotion.relaxed:
            for column, _ in _columns(channel, names):
                face[:, column] *= 1.0 - RELAX * intensity
    return face.astype(motion.face.dtype)


def _columns(channel: str, names: dict[str, int]) -> list[tuple[int, str]]:
    """The face columns of `channel`: itself, or its Left and Right (with the side)."""
    if channel in names:
        return [(names[channel], "")]
    return [(names[channel + side], side) for side in ("Left", "Right") if channel + side in names]


def _body(motion: Motion, track: np.ndarray) -> np.ndarray:
    """Rotations with energy and sharpness scaled around the slow posture, then pitched."""
    mix = np.array([[EMOTIONS[n].energy - 1.0, EMOTIONS[n].sharpness, EMOTIONS[n].head_pitch,
                     EMOTIONS[n].chest_pitch] for n in NAMES])
    energy, sharpness, head, chest = (track @ mix).T
    energy += 1.0
    q = quaternion_sequence_continuous(axis_angle_to_quaternion(motion.rotations.astype(np.float64)))
    slow = _smooth(q, POSTURE_S * motion.fps)
    slow /= np.linalg.norm(slow, axis=-1, keepdims=True)
    movement = quaternion_to_axis_angle(quaternion_product(quaternion_conjugate(slow), q))  # (T, J, 3) around the posture
    stroke = movement - _smooth(movement, STROKE_FRAMES)
    movement = energy[:, None, None] * (movement + sharpness[:, None, None] * stroke)
    out = quaternion_product(slow, axis_angle_to_quaternion(movement))
    for part, pitch in (("head", head), ("chest", chest)):
        for joint, share in CHAINS.get(motion.rig, {}).get(part, ()):
            if joint in motion.joint_names and pitch.any():
                j = motion.joint_names.index(joint)
                out[:, j] = quaternion_product(_pitch(np.radians(pitch * share)), out[:, j])
    return quaternion_to_axis_angle(out).astype(motion.rotations.dtype)


def _pitch(angle: np.ndarray) -> np.ndarray:
    """(T, 4) quaternions (w, x, y, z) turning about x, the canonical nod (z forward, y up):
    positive looks down."""
    return np.stack([np.cos(angle / 2), np.sin(angle / 2), np.zeros_like(angle), np.zeros_like(angle)], axis=-1)


def _smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    return smooth_frames(values, sigma) if sigma > 0 and len(values) > 1 else values.astype(np.float64)
