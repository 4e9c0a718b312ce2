"""Forward kinematics of the arms, layout-free: where the wrists are, and how fast they move.

Both wrists' positions in the chest frame come from forward kinematics of the collar,
upper-arm and forearm rotations over the layout's rest offsets, with lengths divided by
upper arm + forearm ("arm lengths"), so BEAT and SMPL-X motion give comparable figures.
The runtime uses it for the QC report's gesture energy (`wrist_speed`); the training
metrics (diffsheg_core.training.metrics.posture) build their naturalness figures on it.
numpy only: it runs inside Blender.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .errors import DiffshegError
from .motion import Motion
from .rotations import axis_angle_to_matrix

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
def rest_offsets(layout: str) -> dict[str, np.ndarray]:
    """Rest offset of each arm joint from its parent, in canonical axes."""
    if layout == "beat":
        from .bvh import beat_skeleton

        skeleton = beat_skeleton()
        return {n: skeleton.offsets[i].astype(np.float64) for i, n in enumerate(skeleton.joint_names)}
    if layout == "smplx":
        return {f"{side}_{j}": np.array(v) * (1.0 if side == "left" else np.array([-1.0, 1.0, 1.0]))
                for side in ("left", "right") for j, v in _SMPLX_ARM.items()}
    raise DiffshegError(f"no arm chain known for the '{layout}' layout")


def local_rotations(motion: Motion, joint: str) -> np.ndarray:
    """(T, 3, 3) local rotations of `joint`; identity for joints the motion does not move."""
    if joint in motion.joint_names:
        return axis_angle_to_matrix(motion.rotations[:, motion.joint_names.index(joint)].astype(np.float64))
    return np.broadcast_to(np.eye(3), (motion.n_frames, 3, 3))


def wrist_positions(motion: Motion) -> np.ndarray:
    """(T, 2, 3) left and right wrist positions in the chest frame, in arm lengths."""
    if motion.rig not in CHAINS:
        raise DiffshegError(f"no arm chain known for the '{motion.rig}' layout")
    offsets = rest_offsets(motion.rig)
    out = []
    for collar, upper, fore, wrist in CHAINS[motion.rig]["arms"]:
        length = np.linalg.norm(offsets[fore]) + np.linalg.norm(offsets[wrist])
        frame = local_rotations(motion, collar)
        position = np.einsum("tij,j->ti", frame, offsets[upper])
        for joint, child in ((upper, fore), (fore, wrist)):
            frame = frame @ local_rotations(motion, joint)
            position = position + np.einsum("tij,j->ti", frame, offsets[child])
        out.append(position / length)
    return np.stack(out, axis=1)


def wrist_speed(wrists: np.ndarray, fps: float) -> float:
    """Mean |velocity| of (T, 2, 3) wrist positions (`wrist_positions`), in arm lengths per
    second at `fps`; 0.0 for fewer than two frames."""
    if len(wrists) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(wrists, axis=0) * fps, axis=-1).mean())
