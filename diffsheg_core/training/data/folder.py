"""The user's own recordings: a folder of `take.wav` with `take.bvh` (gestures, any
skeleton that has the `beat` joints) and/or `take.csv` (Live Link Face ARKit weights) or
`take.json` (ARKit JSON), read to the `beat` layout. Channels a take lacks are masked
out of training. All takes get the style class of the data configuration."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...audio import load_audio, n_motion_frames
from ...motion import FaceCurves, read_arkit_json, read_livelink_csv
from ...rigs import BEAT
from .beat import face_on_frames, read_gesture
from .sources import TakeSource, read_split_csv
from .take import Take, make_take

if TYPE_CHECKING:
    from .dataset import DataConfig

LAYOUT = BEAT
WHOLE_BODY = False
"""whole_body data: none (the takes hold no lower body in the beat layout)."""
FACE_SUFFIXES = (".csv", ".json")


def find_takes(root: Path) -> list[TakeSource]:
    split_file = root / "train_test_split.csv"
    split = read_split_csv(split_file) if split_file.is_file() else {}
    sources = []
    for wav in sorted(p for p in root.iterdir() if p.suffix.lower() == ".wav"):
        files = {"audio": wav}
        if wav.with_suffix(".bvh").is_file():
            files["motion"] = wav.with_suffix(".bvh")
        face = next((wav.with_suffix(s) for s in FACE_SUFFIXES if wav.with_suffix(s).is_file()), None)
        if face is not None:
            files["face"] = face
        missing = [] if len(files) > 1 else [f"{wav.stem}.bvh or {wav.stem}.csv (no motion for this audio)"]
        sources.append(TakeSource(wav.stem, files, 0, split.get(wav.stem) or split.get(wav.name), missing))
    return sources


def _read_face(path: Path) -> FaceCurves:
    return read_livelink_csv(path) if path.suffix.lower() == ".csv" else read_arkit_json(path)


def read_take(source: TakeSource, config: DataConfig) -> Take:
    audio = load_audio(source.files["audio"])
    has_body, has_face = "motion" in source.files, "face" in source.files
    gesture = read_gesture(source.files["motion"], config.fps) if has_body else None
    n = len(gesture) if has_body else n_motion_frames(audio, config.fps)
    if has_face:
        face = _read_face(source.files["face"])
        if not has_body:
            n = min(n, int(len(face.weights) / face.fps * config.fps))
        face = face_on_frames(face, n, config.fps, str(source.files["face"]), config.max_length_mismatch)
    else:
        face = np.zeros((n, len(BEAT.face_names)))
    if gesture is None:
        gesture = np.zeros((n, BEAT.gesture_dim))
    mask = np.concatenate([np.full(BEAT.gesture_dim, has_body), np.full(BEAT.expression_dim, has_face)])
    return make_take(source.name, np.concatenate([gesture, face], axis=1), audio, config.fps,
                     config.style, mask, config.max_length_mismatch)
