"""The result of generation: `Motion`, and its `.npz` form.

Everything a client (the add-on, a writer, a script) needs is here; nothing in it
refers to the model that made it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import DiffshegError


@dataclass
class Motion:
    """Joint rotations and face weights sampled at `fps`.

    rotations: (T, J, 3) axis-angle radians, each joint in its parent's frame.
    face: (T, K) blendshape weights (ARKit, nominally 0..1) or expression coefficients.
    root_translation: optional (T, 3).
    meta: model id, seed, audio file, sample rate, software version, ...
    """

    fps: float
    rig: str
    joint_names: list[str]
    rotations: np.ndarray
    face_names: list[str]
    face: np.ndarray
    root_translation: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.joint_names = list(self.joint_names)
        self.face_names = list(self.face_names)
        self.rotations = np.asarray(self.rotations, dtype=np.float32)
        self.face = np.asarray(self.face, dtype=np.float32)
        if self.root_translation is not None:
            self.root_translation = np.asarray(self.root_translation, dtype=np.float32)
        self.validate()

    def validate(self) -> None:
        t = self.n_frames
        if self.fps <= 0:
            raise DiffshegError(f"Motion fps must be positive, got {self.fps}")
        if self.rotations.shape != (t, len(self.joint_names), 3):
            raise DiffshegError(
                f"Motion rotations have shape {self.rotations.shape}, expected "
                f"({t}, {len(self.joint_names)}, 3) for {len(self.joint_names)} joints")
        if self.face.shape != (t, len(self.face_names)):
            raise DiffshegError(
                f"Motion face weights have shape {self.face.shape}, expected "
                f"({t}, {len(self.face_names)})")
        if self.root_translation is not None and self.root_translation.shape != (t, 3):
            raise DiffshegError(
                f"Motion root_translation has shape {self.root_translation.shape}, expected ({t}, 3)")

    @property
    def n_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def duration(self) -> float:
        """Seconds covered: frame i is at time i / fps."""
        return self.n_frames / self.fps

    def save_npz(self, path: str | Path) -> Path:
        path = Path(path)
        arrays = {
            "fps": np.float64(self.fps),
            "rig": np.str_(self.rig),
            "joint_names": np.array(self.joint_names, dtype=np.str_),
            "rotations": self.rotations,
            "face_names": np.array(self.face_names, dtype=np.str_),
            "face": self.face,
            "meta": np.str_(json.dumps(self.meta, default=str)),
        }
        if self.root_translation is not None:
            arrays["root_translation"] = self.root_translation
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)
        return path

    @classmethod
    def load_npz(cls, path: str | Path) -> "Motion":
        path = Path(path)
        if not path.is_file():
            raise DiffshegError(f"{path}: no such motion file")
        try:
            with np.load(path, allow_pickle=False) as z:
                return cls(
                    fps=float(z["fps"]),
                    rig=str(z["rig"]),
                    joint_names=[str(n) for n in z["joint_names"]],
                    rotations=z["rotations"],
                    face_names=[str(n) for n in z["face_names"]],
                    face=z["face"],
                    root_translation=z["root_translation"] if "root_translation" in z else None,
                    meta=json.loads(str(z["meta"])),
                )
        except (KeyError, ValueError, OSError) as exc:
            raise DiffshegError(
                f"{path}: not a motion file written by diffsheg_core ({exc})") from exc
