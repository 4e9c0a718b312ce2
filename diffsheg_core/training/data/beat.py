"""BEAT: `<speaker>/<take>.wav`, `<take>.bvh` (75-joint skeleton, 120 fps, taken to the
model rate by keeping every n-th frame) and `<take>.json` ARKit weights, read to the
`beat` layout. A take without its .json keeps its gestures and trains no face.
An optional `train_test_split.csv` (BEAT2's format) at the root gives the splits."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...audio import load_audio
from ...bvh import bvh_to_motion, read_bvh
from ...motion import FaceCurves, read_arkit_json
from ...rigs import BEAT
from .sources import TakeSource, read_split_csv, speaker_style
from .take import Take, TakeError, check_finite, decimate, make_take

if TYPE_CHECKING:
    from .dataset import DataConfig

LAYOUT = BEAT
WHOLE_BODY = False
"""whole_body data: none (the takes' lower body is not in the beat layout)."""


def find_takes(root: Path) -> list[TakeSource]:
    split_file = root / "train_test_split.csv"
    split = read_split_csv(split_file) if split_file.is_file() else {}
    sources = []
    for wav in sorted(root.glob("*/*.wav")):
        files = {"audio": wav, "motion": wav.with_suffix(".bvh")}
        if wav.with_suffix(".json").is_file():
            files["face"] = wav.with_suffix(".json")
        missing = [str(files["motion"])] if not files["motion"].is_file() else []
        sources.append(TakeSource(wav.stem, files, speaker_style(wav.stem), split.get(wav.stem), missing))
    return sources


def read_gesture(path: Path, fps: float, source_fps: float | None = None) -> np.ndarray:
    """(T, 141) axis-angle of the 47 `beat` joints at `fps` from a BVH file; `source_fps`
    overrides the file's frame time (for headers known to be stale)."""
    motion = bvh_to_motion(read_bvh(path, fps=source_fps), BEAT)
    check_finite(str(path), "the motion", motion.rotations)
    return decimate(motion.rotations.reshape(motion.n_frames, -1), motion.fps, fps, str(path))


def face_on_frames(face: FaceCurves, n_frames: int, fps: float, where: str,
                   max_mismatch: float) -> np.ndarray:
    """(n_frames, 51) ARKit weights in layout order, interpolated at the motion's frame times."""
    duration = len(face.weights) / face.fps
    if n_frames / fps - duration > max_mismatch:
        raise TakeError(f"{where}: the face capture ({duration:.2f} s) is shorter than the body "
                        f"motion ({n_frames / fps:.2f} s)")
    columns = face.weights[:, [face.names.index(n) for n in BEAT.face_names]]
    source_t, target_t = np.arange(len(columns)) / face.fps, np.arange(n_frames) / fps
    return np.stack([np.interp(target_t, source_t, c) for c in columns.T], axis=1)


def read_take(source: TakeSource, config: DataConfig) -> Take:
    gesture = read_gesture(source.files["motion"], config.fps)
    if "face" in source.files:
        face = face_on_frames(read_arkit_json(source.files["face"]), len(gesture), config.fps,
                              str(source.files["face"]), config.max_length_mismatch)
    else:
        face = np.zeros((len(gesture), len(BEAT.face_names)))
    mask = np.concatenate([np.ones(BEAT.gesture_dim, bool),
                           np.full(BEAT.expression_dim, "face" in source.files)])
    audio = load_audio(source.files["audio"])
    return make_take(source.name, np.concatenate([gesture, face], axis=1), audio, config.fps,
                     source.style, mask, config.max_length_mismatch)
