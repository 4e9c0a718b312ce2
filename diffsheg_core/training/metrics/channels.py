"""Channels of a Motion that the metrics read, whatever the layout."""

from __future__ import annotations

import numpy as np

from ...errors import DiffshegError
from ...motion import Motion
from ...qc import mouth_curve as mouth_opening  # noqa: F401 (the metrics' name for it)
from ...rigs import Layout


def face_channel(motion: Motion, name: str) -> np.ndarray:
    """(T,) weight of the face channel `name` (ARKit names match in any case)."""
    lowered = [n.lower() for n in motion.face_names]
    if name.lower() not in lowered:
        raise DiffshegError(
            f"the motion has no face channel '{name}' (rig '{motion.rig}'); "
            "this metric needs ARKit blendshape weights")
    return motion.face[:, lowered.index(name.lower())].astype(np.float64)


def has_face_channels(motion: Motion, *names: str) -> bool:
    lowered = {n.lower() for n in motion.face_names}
    return all(n.lower() in lowered for n in names)


def has_mouth(motion: Motion) -> bool:
    """Whether `mouth_opening` can read this motion (a body-only capture cannot)."""
    return has_face_channels(motion, "jawOpen") or "jaw" in motion.joint_names


def gesture_array(motion: Motion, layout: Layout) -> np.ndarray:
    """(T, gesture_dim) axis-angle of the layout's gesture joints, matched by name; works for
    body-only motion (e.g. a BVH capture without a face)."""
    missing = [j for j in layout.gesture_joints if j not in motion.joint_names]
    if missing:
        raise DiffshegError(
            f"the motion (rig '{motion.rig}') lacks joints of layout '{layout.name}': "
            f"{', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''}")
    index = [motion.joint_names.index(j) for j in layout.gesture_joints]
    return motion.rotations[:, index].reshape(motion.n_frames, -1).astype(np.float64)


def blink_signal(motion: Motion) -> np.ndarray:
    """(T,) mean of ARKit eyeBlinkLeft and eyeBlinkRight."""
    return 0.5 * (face_channel(motion, "eyeBlinkLeft") + face_channel(motion, "eyeBlinkRight"))


def layout_array(motion: Motion, layout: Layout) -> np.ndarray:
    """(T, D) model-space array of `motion` in `layout` order, joints and face channels
    matched by name (face names in any case)."""
    missing = [j for j in layout.joint_names if j not in motion.joint_names]
    lowered = {n.lower(): i for i, n in enumerate(motion.face_names)}
    missing += [f for f in layout.face_names if f.lower() not in lowered]
    if missing:
        raise DiffshegError(
            f"the motion (rig '{motion.rig}') lacks channels of layout '{layout.name}': "
            f"{', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''}")
    rotations = motion.rotations[:, [motion.joint_names.index(j) for j in layout.joint_names]]
    face = motion.face[:, [lowered[f.lower()] for f in layout.face_names]]
    return layout.join(rotations, face).astype(np.float64)
