"""Layout-free naturalness features: where the wrists go and how the head is held.

Both wrists' positions in the chest frame come from forward kinematics of the collar,
upper-arm and forearm rotations over the layout's rest offsets, with lengths divided by
upper arm + forearm, so BEAT and SMPL-X motion (and the BEAT BVH and the BEAT2 SMPL-X
versions of one capture) give comparable figures (diffsheg_core.kinematics, which the
runtime shares). From them, at the motion's own rate:
speed (mean |velocity|, arm lengths/s), jitter (mean |acceleration|, arm lengths/s^2) and
spread (standard deviation of the positions, arm lengths). Head pitch is the angle the
head's forward axis points below the horizontal of the hips, in degrees.
"""

from __future__ import annotations

import numpy as np

from ...errors import DiffshegError
from ...kinematics import CHAINS, local_rotations, rest_offsets, wrist_positions, wrist_speed
from ...motion import Motion

__all__ = ["CHAINS", "NATURALNESS", "head_pitch", "naturalness", "rest_offsets", "wrist_positions"]


def head_pitch(motion: Motion) -> np.ndarray:
    """(T,) degrees the head looks below the hips' horizontal (negative: up)."""
    frame = np.broadcast_to(np.eye(3), (motion.n_frames, 3, 3))
    for joint in CHAINS[motion.rig]["head"]:
        frame = frame @ local_rotations(motion, joint)
    forward = frame[:, :, 2]  # canonical z is the character's forward, y up
    return np.degrees(np.arcsin(np.clip(-forward[:, 1], -1.0, 1.0)))


NATURALNESS = ("wrist speed (arm lengths/s)", "wrist jitter (arm lengths/s^2)", "wrist spread (arm lengths)",
               "head pitch (deg, down)")
"""The names of `naturalness`'s figures."""


def naturalness(motion: Motion) -> dict[str, float]:
    """Wrist speed, jitter and spread, and mean head pitch, of one motion."""
    wrists = wrist_positions(motion)
    if len(wrists) < 3:
        raise DiffshegError(f"naturalness needs at least 3 frames, got {len(wrists)}")
    fps = motion.fps
    acceleration = np.diff(wrists, n=2, axis=0) * fps ** 2
    return dict(zip(NATURALNESS, (
        wrist_speed(wrists, fps),
        float(np.linalg.norm(acceleration, axis=-1).mean()),
        float(np.sqrt(wrists.var(axis=0).sum(axis=-1)).mean()),
        float(head_pitch(motion).mean()))))
