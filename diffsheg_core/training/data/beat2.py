"""BEAT2: `wave16k/<take>.wav`, `smplxflame_30/<take>.npz` (SMPL-X poses 165 = global 3,
body 63, jaw 3, eyes 6, hands 90; FLAME expressions 100; 30 fps) and
`train_test_split.csv`, read to the `smplx` layout."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...audio import load_audio
from ...rigs import SMPLX, SMPLX_JOINTS
from .sources import TakeSource, read_split_csv, speaker_style
from .take import Take, TakeError, check_finite, decimate, make_take

if TYPE_CHECKING:
    from .dataset import DataConfig

LAYOUT = SMPLX
WHOLE_BODY = False
"""whole_body data: none (SMPL-X takes, not in the beat layout)."""
_JOINT_IDS = [SMPLX_JOINTS.index(j) for j in SMPLX.joint_names]


def find_takes(root: Path) -> list[TakeSource]:
    split = read_split_csv(root / "train_test_split.csv")
    sources = []
    for name, kind in sorted(split.items()):
        files = {"audio": root / "wave16k" / f"{name}.wav", "motion": root / "smplxflame_30" / f"{name}.npz"}
        missing = [str(p) for p in files.values() if not p.is_file()]
        sources.append(TakeSource(name, files, speaker_style(name), kind, missing))
    return sources


def read_motion(path: Path, fps: float) -> np.ndarray:
    """(T, 232) smplx-layout motion at `fps` from a BEAT2 smplxflame npz."""
    try:
        with np.load(path, allow_pickle=False) as z:
            poses, expressions = z["poses"], z["expressions"]
            source_fps = float(z["mocap_frame_rate"])
    except KeyError as exc:
        raise TakeError(f"{path}: no {exc} array; a BEAT2 motion file holds poses, expressions, "
                        "trans, betas and mocap_frame_rate") from exc
    except (OSError, ValueError) as exc:
        raise TakeError(f"{path}: not a readable npz file ({exc})") from exc
    if poses.ndim != 2 or poses.shape[1] != 3 * len(SMPLX_JOINTS):
        raise TakeError(f"{path}: poses have shape {poses.shape}, expected (T, {3 * len(SMPLX_JOINTS)}): "
                        "joints are missing")
    if expressions.ndim != 2 or expressions.shape[1] < len(SMPLX.face_names) or len(expressions) != len(poses):
        raise TakeError(f"{path}: expressions have shape {expressions.shape}, expected "
                        f"({len(poses)}, {len(SMPLX.face_names)})")
    check_finite(str(path), "the poses", poses)
    check_finite(str(path), "the expressions", expressions)
    rotations = poses.reshape(len(poses), -1, 3)[:, _JOINT_IDS]
    motion = SMPLX.join(rotations, expressions[:, : len(SMPLX.face_names)])
    return decimate(motion, source_fps, fps, str(path))


def read_take(source: TakeSource, config: DataConfig) -> Take:
    motion = read_motion(source.files["motion"], config.fps)
    audio = load_audio(source.files["audio"])
    return make_take(source.name, motion, audio, config.fps, source.style, np.ones(LAYOUT.dim, bool),
                     config.max_length_mismatch)
