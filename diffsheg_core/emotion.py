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
Live, `EmotionStream` lays one emotion over each hop as it is made.
numpy only: it runs inside Blender.
"""

from __future__ import annotations

import numbers
import threading
from dataclasses import dataclass, field, replace

import numpy as np

from .errors import DiffshegError
from .motion import Motion, smooth_frames
from .rigs import BEAT_LOWER_JOINTS
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

EASE_S = 0.15        # Gaussian sigma of a change of emotion: eased in over about 0.35 s
POSTURE_S = 0.5      # Gaussian sigma of the slow posture the energy scales movement around
STROKE_FRAMES = 3.0  # Gaussian sigma, in model frames, of the unsharp mask's blur (a stroke, 0.2 s)
CLOSED_LIPS = 0.12   # mouthClose at which the emotion's mouth channels have given way entirely
KEPT_MOUTH = ("mouthPress",)  # mouth channels that close the lips themselves: not given way
RELAX = 0.8          # how far, at full intensity, an opposed channel is relaxed
HOLD_S = 0.5         # seconds over which the emotion eases in around a pinned pose
SWITCH_S = 0.35      # seconds over which an emotion changed live eases in (from the change on)
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
        # compared as given: float() of an int beyond the floats overflows; inf and nan fail the bounds
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0.0 <= value <= 1.0:
            infinite = isinstance(value, numbers.Real) and not isinstance(value, bool) and _infinite(value)
            raise DiffshegError(f"the intensity of emotion {name!r} must be a{' finite' if infinite else ''} number "
                                f"from 0 to 1, got {value!r}")
        if name != "neutral" and float(value) > 0:
            out[name] = float(value)
    if sum(out.values()) > 1.0 + 1e-6:
        raise DiffshegError(f"the intensities of emotion {spec!r} add up to {sum(out.values()):g}: give them at "
                            "most 1 in all")
    return out


def _infinite(number: numbers.Real) -> bool:
    """Whether `number` is inf or nan (an int beyond the floats is finite)."""
    try:
        return not np.isfinite(float(number))
    except OverflowError:
        return False


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


def emotion_track(emotion: dict[str, float] | None, changes, n_frames: int, fps: float) -> np.ndarray | None:
    """(T, len(NAMES)) intensity of each emotion per frame: `emotion` until the first of
    `changes` ((seconds, {name: intensity}), ...), each change's from its frame on, eased (a
    change after the end: never). None where every frame is neutral."""
    track = np.zeros((n_frames, len(NAMES)))
    for (t, spec) in ((0.0, emotion or {}),) + tuple(changes or ()):
        track[round(min(t * fps, n_frames)):] = _row(spec)  # min first: t * fps may be inf (1e308 s)
    if not track.any():
        return None
    return smooth_frames(track, EASE_S * fps)


def take_emotion(motion: Motion) -> np.ndarray | None:
    """The emotion track laid over `motion` (emotion_track), from its meta: the emotion it was
    generated with, then each regenerated range's own; None where it was all neutral."""
    n, fps = motion.n_frames, motion.fps
    track = emotion_track(motion.meta.get("emotion") or None, motion.meta.get("emotion_at") or None, n, fps)
    for record in motion.meta.get("regenerated", []):
        ranged = emotion_track(record.get("emotion") or None, record.get("emotion_at") or None, n, fps)
        if ranged is not None or track is not None:
            track = np.zeros((n, len(NAMES))) if track is None else track
            track[record["start"]:record["end"]] = 0.0 if ranged is None else ranged[record["start"]:record["end"]]
    return track if track is not None and track.any() else None


def apply_emotion(motion: Motion, track: np.ndarray, start: int = 0, end: int | None = None,
                  held: tuple[tuple[int, str], ...] = ()) -> Motion:
    """`motion` with the emotions of `track` (emotion_track) laid over frames [start, end);
    the frames outside are returned as they were. `held`: (frame, joint) a pin holds (a
    pose the take must pass through): that joint keeps its pose at that frame, the emotion
    eased in over HOLD_S around it."""
    end = motion.n_frames if end is None else end
    body = _body(motion, track)
    for joint in {j for _, j in held}:
        k = motion.joint_names.index(joint)
        frames = np.array([f for f, j in held if j == joint], dtype=np.float64)
        away = np.abs(np.arange(motion.n_frames)[:, None] - frames[None]).min(axis=1)
        body[:, k] = _toward(motion.rotations[:, k], body[:, k], np.clip(away / (HOLD_S * motion.fps), 0.0, 1.0))
    rotations, face = motion.rotations.copy(), motion.face.copy()
    face[start:end] = _face(motion, track)[start:end]
    rotations[start:end] = body[start:end]
    return replace(motion, rotations=rotations, face=face)


class EmotionStream:
    """The emotion laid over a live motion, a hop of frames at a time (live/session.py): the
    face exactly as `apply_emotion` lays it over a whole take (it is frame by frame), the
    body's energy and sharpness around the slow posture of the frames made so far, where
    offline also sees the next ones, so a stroke is scaled a moment later in its course;
    the head's and chest's pitch exactly. The performer may change it while speaking
    (`set`, from any thread): the new one eases in over SWITCH_S from the next hop, and
    `changes` keeps when, for the recording's meta ("emotion_at")."""

    def __init__(self, emotion: dict[str, float] | None, fps: float):
        self.fps = fps
        self.context = int(np.ceil(3 * POSTURE_S * fps))  # smooth_frames' reach at the posture's sigma
        self.frames = 0                    # frames made so far
        self.changes: list[tuple[float, dict[str, float]]] = []  # (seconds, emotion) of each change
        self._ease = max(1, int(round(SWITCH_S * fps)))
        self._start = self._target = _row(check_emotion(emotion or {}))
        self._since = 0                    # the frame the last change began to ease in
        self._pending: dict[str, float] | None = None  # set by another thread, taken at the next hop
        self._lock = threading.Lock()
        self._before: Motion | None = None  # the last `context` frames made, without the emotion
        self._before_rows = np.zeros((0, len(NAMES)))

    def set(self, emotion) -> None:
        """Change the emotion (a spec as `check_emotion` takes; {} or 'neutral' for none) from
        the next hop on. Raises DiffshegError, on the caller's thread, for a bad one."""
        checked = check_emotion(emotion if emotion else {})
        with self._lock:
            self._pending = checked

    def add(self, part: Motion) -> Motion:
        """`part`, the next frames of the stream, with the emotion laid over them."""
        n = part.n_frames
        if not n:
            return part
        with self._lock:
            pending, self._pending = self._pending, None
        if pending is not None:
            self._start, self._target, self._since = self._rows(np.array([self.frames]))[0], _row(pending), self.frames
            # noted at the middle of its ease, where emotion_track (a recording's regenerated ranges) centres it
            self.changes.append(((self.frames + self._ease / 2) / self.fps, pending))
        rows = self._rows(np.arange(self.frames, self.frames + n))
        window = part if self._before is None else replace(
            part, rotations=np.concatenate([self._before.rotations, part.rotations]),
            face=np.concatenate([self._before.face, part.face]))
        track = np.concatenate([self._before_rows, rows])
        laid = apply_emotion(window, track) if track.any() else window
        self._before = replace(window, rotations=window.rotations[-self.context:], face=window.face[-self.context:])
        self._before_rows = track[-self.context:]
        self.frames += n
        return replace(part, rotations=laid.rotations[-n:], face=laid.face[-n:])

    def _rows(self, frames: np.ndarray) -> np.ndarray:
        """(len(frames), len(NAMES)) the emotion at these frames, easing from the last change."""
        w = np.clip((frames - self._since) / self._ease, 0.0, 1.0)[:, None]
        return self._start + w * w * (3 - 2 * w) * (self._target - self._start)


def _row(emotion: dict[str, float]) -> np.ndarray:
    """(len(NAMES),) the intensities of a checked emotion spec."""
    row = np.zeros(len(NAMES))
    for name, value in emotion.items():
        row[NAMES.index(name)] = value
    return row


def remove_emotion(motion: Motion, track: np.ndarray) -> Motion:
    """About the motion `apply_emotion(·, track)` was given: the face and the head's and
    chest's pitch exactly, the body's energy and sharpness to first order. A range is
    regenerated against it, so that its emotion is laid over the new frames once."""
    return replace(motion, rotations=_body(motion, track, inverse=True), face=_face(motion, track, inverse=True))


def _toward(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(T, 3) axis-angle rotations the fraction `w` (T,) of the way from `a` to `b`."""
    qa, qb = axis_angle_to_quaternion(a.astype(np.float64)), axis_angle_to_quaternion(b.astype(np.float64))
    step = quaternion_to_axis_angle(quaternion_product(quaternion_conjugate(qa), qb)) * w[:, None]
    return quaternion_to_axis_angle(quaternion_product(qa, axis_angle_to_quaternion(step))).astype(a.dtype)


def _face(motion: Motion, track: np.ndarray, inverse: bool = False) -> np.ndarray:
    """The face with each emotion's channels raised and its opposed channels relaxed (with
    `inverse`, the face those steps were taken from: each is undone, in reverse order)."""
    names = {n: i for i, n in enumerate(motion.face_names)}
    if "mouthClose" not in names:  # not ARKit (an SMPL-X model's FLAME face): the body only
        return motion.face
    face = motion.face.astype(np.float64)
    lips_open = 1.0 - np.clip(face[:, names["mouthClose"]] / CLOSED_LIPS, 0.0, 1.0)  # never changed
    blink = {side: face[:, names[f"eyeBlink{side}"]] for side in ("Left", "Right") if f"eyeBlink{side}" in names}
    steps = []  # (column, gain a: raise f -> f + a (1 - f)) or (column, factor: relax f -> f * factor)
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
                steps.append(("raise", column, intensity * weight * gate))
        for channel in emotion.relaxed:
            for column, _ in _columns(channel, names):
                steps.append(("relax", column, 1.0 - RELAX * intensity))
    for kind, column, value in (reversed(steps) if inverse else steps):
        f = face[:, column]
        if kind == "relax":
            face[:, column] = f / value if inverse else f * value
        else:
            face[:, column] = (f - value) / (1.0 - value) if inverse else f + value * np.clip(1.0 - f, 0.0, None)
    return face.astype(motion.face.dtype)


def _columns(channel: str, names: dict[str, int]) -> list[tuple[int, str]]:
    """The face columns of `channel`: itself, or its Left and Right (with the side)."""
    if channel in names:
        return [(names[channel], "")]
    return [(names[channel + side], side) for side in ("Left", "Right") if channel + side in names]


def _body(motion: Motion, track: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Rotations with energy and sharpness scaled around the slow posture, then pitched (with
    `inverse`, unpitched, then the scaling undone to first order); the hips and legs as they are."""
    mix = np.array([[EMOTIONS[n].energy - 1.0, EMOTIONS[n].sharpness, EMOTIONS[n].head_pitch,
                     EMOTIONS[n].chest_pitch] for n in NAMES])
    energy, sharpness, head, chest = (track @ mix).T
    energy += 1.0
    sign = -1.0 if inverse else 1.0
    q = quaternion_sequence_continuous(axis_angle_to_quaternion(motion.rotations.astype(np.float64)))
    if inverse:
        q = _pitched(motion, q, head, chest, sign)
    slow = smooth_frames(q, POSTURE_S * motion.fps)
    slow /= np.linalg.norm(slow, axis=-1, keepdims=True)
    movement = quaternion_to_axis_angle(quaternion_product(quaternion_conjugate(slow), q))  # (T, J, 3) around the posture
    gain, sharp = energy[:, None, None], sharpness[:, None, None]
    if inverse:  # x = gain ((1 + sharp) m - sharp blur(m))  =>  m ~ (x / gain + sharp blur(x / gain)) / (1 + sharp)
        x = movement / gain
        movement = (x + sharp * smooth_frames(x, STROKE_FRAMES)) / (1.0 + sharp)
    else:
        movement = gain * (movement + sharp * (movement - smooth_frames(movement, STROKE_FRAMES)))
    out = quaternion_product(slow, axis_angle_to_quaternion(movement))
    if not inverse:
        out = _pitched(motion, out, head, chest, sign)
    rotations = quaternion_to_axis_angle(out).astype(motion.rotations.dtype)
    legs = [k for k, name in enumerate(motion.joint_names) if name in BEAT_LOWER_JOINTS]
    rotations[:, legs] = motion.rotations[:, legs]  # the hips and legs stand as made (their feet are planted)
    return rotations


def _pitched(motion: Motion, q: np.ndarray, head: np.ndarray, chest: np.ndarray, sign: float) -> np.ndarray:
    """(T, J, 4) `q` with the head's and chest's joints pitched by `sign` times their share."""
    q = q.copy()
    for part, pitch in (("head", head), ("chest", chest)):
        for joint, share in CHAINS.get(motion.rig, {}).get(part, ()):
            if joint in motion.joint_names and pitch.any():
                j = motion.joint_names.index(joint)
                q[:, j] = quaternion_product(_pitch(np.radians(sign * pitch * share)), q[:, j])
    return q


def _pitch(angle: np.ndarray) -> np.ndarray:
    """(T, 4) quaternions (w, x, y, z) turning about x, the canonical nod (z forward, y up):
    positive looks down."""
    return np.stack([np.cos(angle / 2), np.sin(angle / 2), np.zeros_like(angle), np.zeros_like(angle)], axis=-1)
