"""Layout-free naturalness features: where the wrists go and how the head is held.

Both wrists' positions in the chest frame come from forward kinematics of the collar,
upper-arm and forearm rotations over the layout's rest offsets, with lengths divided by
upper arm + forearm, so BEAT and SMPL-X motion (and the BEAT BVH and the BEAT2 SMPL-X
versions of one capture) give comparable figures. From them, at the motion's own rate:
speed (mean |velocity|, arm lengths/s), jitter (mean |acceleration|, arm lengths/s^2) and
spread (standard deviation of the positions, arm lengths). Head pitch is the angle the
head's forward axis points below the horizontal of the hips, in degrees.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ...errors import DiffshegError
from ...motion import Motion
from ...rotations import axis_angle_to_matrix

# per layout: the arm chain of each side (collar, upper arm, forearm, wrist) and the chain
# from the hips to the head
CHAINS = {
    "beat": {"arms": [tuple(f"{s}{j}" for j in ("Shoulder", "Arm", "ForeArm", "Hand")) for s in ("Left", "Right")],
             "head": ("Spine", "Spine1", "Spine2", "Spine3", "Neck", "Neck1", "Head")},
    "smplx": {"arms": [tuple(f"{s}_{j}" for j in ("collar", "shoulder", "elbow", "wrist")) for s in ("left", "right")],
              "head": ("spine1", "spine2", "spine3", "neck", "head")},
}
# SMPL-X has no skeleton file here: rest offsets (metres, canonical axes) of the neutral body
_SMPLX_ARM = {"collar": (0.0, 0.0, 0.0), "shoulder": (0.12, 0.03, -0.01), "elbow": (0.26, -0.01, -0.02),
              "wrist": (0.25, 0.01, -0.01)}


@lru_cache(maxsize=None)
def _offsets(layout: str) -> dict[str, np.ndarray]:
    """Rest offset of each arm joint from its parent, in canonical axes."""
    if layout == "beat":
        from ...bvh import beat_skeleton

        skeleton = beat_skeleton()
        return {n: skeleton.offsets[i].astype(np.float64) for i, n in enumerate(skeleton.joint_names)}
    if layout == "smplx":
        return {f"{side}_{j}": np.array(v) * (1.0 if side == "left" else np.array([-1.0, 1.0, 1.0]))
                for side in ("left", "right") for j, v in _SMPLX_ARM.items()}
    raise DiffshegError(f"no arm chain known for the '{layout}' layout")


def _rotations(motion: Motion, joint: str) -> np.ndarray:
    """(T, 3, 3) local rotations of `joint`; identity for joints the motion does not move."""
    if joint in motion.joint_names:
        return axis_angle_to_matrix(motion.rotations[:, motion.joint_names.index(joint)].astype(np.float64))
    return np.broadcast_to(np.eye(3), (motion.n_frames, 3, 3))


def wrist_positions(motion: Motion) -> np.ndarray:
    """(T, 2, 3) left and right wrist positions in the chest frame, in arm lengths."""
    if motion.rig not in CHAINS:
        raise DiffshegError(f"no arm chain known for the '{motion.rig}' layout")
    offsets = _offsets(motion.rig)
    out = []
    for collar, upper, fore, wrist in CHAINS[motion.rig]["arms"]:
        length = np.linalg.norm(offsets[fore]) + np.linalg.norm(offsets[wrist])
        frame = _rotations(motion, collar)
        position = np.einsum("tij,j->ti", frame, offsets[upper])
        for joint, child in ((upper, fore), (fore, wrist)):
            frame = frame @ _rotations(motion, joint)
            position = position + np.einsum("tij,j->ti", frame, offsets[child])
        out.append(position / length)
    return np.stack(out, axis=1)


def head_pitch(motion: Motion) -> np.ndarray:
    """(T,) degrees the head looks below the hips' horizontal (negative: up)."""
    frame = np.broadcast_to(np.eye(3), (motion.n_frames, 3, 3))
    for joint in CHAINS[motion.rig]["head"]:
        frame = frame @ _rotations(motion, joint)
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
    velocity = np.diff(wrists, axis=0) * fps
    acceleration = np.diff(wrists, n=2, axis=0) * fps ** 2
    return dict(zip(NATURALNESS, (
        float(np.linalg.norm(velocity, axis=-1).mean()),
        float(np.linalg.norm(acceleration, axis=-1).mean()),
        float(np.sqrt(wrists.var(axis=0).sum(axis=-1)).mean()),
        float(head_pitch(motion).mean()))))
