"""The teacher: speech and its timed phones in, `beat`-layout motion out (47 joints from
real motion capture placed on the prosody, with the same capture frames' hips, legs and hips
translation when the library has them; 51 procedural ARKit face weights).

The corpus builder runs it on synthetic speech; the evaluation runs it on any speech with
phone timings (e.g. the real take's TextGrid) to score the teacher beside the model.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ... import __version__
from ...audio import Audio, n_motion_frames
from ...errors import DiffshegError
from ...lower_body import JOINTS, plant_feet, settle, with_lower_body
from ...motion import Motion
from ...rigs import ARKIT51, BEAT, BEAT_JOINTS
from .face import FaceStyle, face_curves
from .gestures import GESTURE_STYLES, GestureLibrary, GestureStyle, gesture_rotations, load_library
from .phones import Phone, check_phones, phones_from_arrays, phones_to_arrays
from .prosody import find_accents, vowel_effort

TEACHER_VERSION = 4
"""Bump when the teacher's output changes; it is stored with every utterance. v2: longer,
pose-matched cross-fades, nods that keep the mean head pitch, named gesture styles, the
last 20 s of the capture held out. v3: the jaw opens wider on louder vowels (vocal effort).
v4: the whole body: the hips, legs and hips' translation of the same capture frames as the
gestures (BEAT2's SMPL-X take), settled and with the feet planted as generation plants them."""

STYLE_NAMES: tuple[str, ...] = tuple(GESTURE_STYLES)


@dataclass(frozen=True)
class TeacherStyle:
    """A speaker's manner: face and gesture parameters, drawn per utterance for variety;
    `name` is the named gesture style (GESTURE_STYLES) the gesture parameters come from."""

    face: FaceStyle = field(default_factory=FaceStyle)
    gesture: GestureStyle = field(default_factory=GestureStyle)
    name: str = "conversational"

    @classmethod
    def random(cls, rng: np.random.Generator, name: str | None = None) -> "TeacherStyle":
        """Face parameters at random; the gesture style `name`, or one of STYLE_NAMES at random."""
        face = FaceStyle.random(rng)
        name = name or STYLE_NAMES[int(rng.integers(len(STYLE_NAMES)))]
        return cls(face, GestureStyle.random(rng, name), name)


def teach(audio: Audio, phones: list[Phone], *, seed: int = 0, style: TeacherStyle | None = None,
          library: GestureLibrary | None = None) -> Motion:
    """Teacher motion for `audio` with its phone timings, one frame per mel frame at 15 fps.

    `style` None draws one from `seed`. `library` defaults to the real take's gestures."""
    check_phones(phones)
    rng = np.random.default_rng(seed)
    style = style or TeacherStyle.random(rng)
    fps = BEAT.fps
    n_frames = n_motion_frames(audio, fps)
    if n_frames < 2:
        raise DiffshegError(f"audio of {len(audio.samples) / audio.sample_rate:.2f} s is too short "
                            "for a teacher motion (need at least two frames at 15 fps)")
    samples = np.asarray(audio.samples, dtype=np.float32)
    accents = find_accents(samples, audio.sample_rate, phones)
    library = library or load_library()
    track = gesture_rotations(accents, n_frames, fps, style.gesture, rng, library)
    face = face_curves(phones, accents, n_frames, fps, style.face, rng,
                       vowel_effort(samples, audio.sample_rate, phones))
    motion = Motion(
        fps=fps, rig=BEAT.name, joint_names=list(BEAT_JOINTS), rotations=track.rotations[:, :len(BEAT_JOINTS)],
        face_names=list(ARKIT51), face=face,
        meta={"model": f"teacher-v{TEACHER_VERSION}", "seed": seed, "audio": audio.path,
              "sample_rate": audio.sample_rate, "software": __version__,
              "style": asdict(style), "accents": [a.time for a in accents], "strokes": track.strokes},
    )
    if track.root is None:
        return motion
    lower = track.rotations[:, len(BEAT_JOINTS):].astype(np.float64)
    trans = settle(lower, track.root, library.lower)
    lower, spans = plant_feet(lower, trans, fps, track.contacts)
    return with_lower_body(motion, lower, trans, spans)


def teach_files(audio_path: str | Path, textgrid_path: str | Path, seed: int = 0) -> Motion:
    """Teacher motion for a recording and its forced-alignment TextGrid (phone tier)."""
    from ...audio import load_audio
    from .phones import phones_from_textgrid

    return teach(load_audio(audio_path), phones_from_textgrid(textgrid_path), seed=seed)


def save_utterance(path: str | Path, motion: Motion, phones: list[Phone], info: dict) -> Path:
    """Write one corpus utterance's motion: gesture (T, 141) axis-angle, or (T, 168) with the
    lower body, and then `root` (T, 3), the hips' translation; face (T, 51), fps, the phones
    (labels, start, end, stress) and `info` (JSON) into an .npz, atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    root = {} if motion.root_translation is None else {"root": motion.root_translation}
    with open(tmp, "wb") as fh:
        np.savez(fh, gesture=motion.rotations.reshape(motion.n_frames, -1), face=motion.face,
                 fps=np.float64(motion.fps), info=np.str_(json.dumps(info | {"meta": motion.meta})),
                 **root, **phones_to_arrays(phones))
    tmp.replace(path)
    return path


def load_utterance(path: str | Path) -> tuple[Motion, list[Phone], dict]:
    """The Motion, phones and info of an utterance written by `save_utterance`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            info = json.loads(str(z["info"]))
            gesture, face, fps, phones = z["gesture"], z["face"], float(z["fps"]), phones_from_arrays(z)
            root = z["root"] if "root" in z else None
    except (OSError, KeyError, ValueError) as exc:
        raise DiffshegError(f"{path}: not a corpus utterance ({exc}); rebuild the corpus") from exc
    joints = BEAT_JOINTS + (JOINTS if root is not None else ())
    motion = Motion(fps=fps, rig=BEAT.name, joint_names=list(joints),
                    rotations=gesture.reshape(len(gesture), -1, 3), face_names=list(ARKIT51),
                    face=face, root_translation=root, meta=info.get("meta", {}))
    return motion, phones, info
