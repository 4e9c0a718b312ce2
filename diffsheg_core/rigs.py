"""Canonical channel layouts of the models: which joint and face channel sits where.

A model works on one flat vector per frame, gesture first, then expression.
A `Layout` says how that vector splits into joint rotations (axis-angle, radians,
each joint in its parent's frame) and face weights, and what each one is called.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import DiffshegError

_HAND_BEAT = (
    "Middle1", "Middle2", "Middle3",
    "Ring", "Ring1", "Ring2", "Ring3",
    "Pinky", "Pinky1", "Pinky2", "Pinky3",
    "Index", "Index1", "Index2", "Index3",
    "Thumb1", "Thumb2", "Thumb3",
)


def _beat_side(side: str) -> tuple[str, ...]:
    arm = (f"{side}Shoulder", f"{side}Arm", f"{side}ForeArm", f"{side}Hand")
    return arm + tuple(f"{side}Hand{finger}" for finger in _HAND_BEAT)


BEAT_JOINTS: tuple[str, ...] = ("Spine", "Neck", "Neck1") + _beat_side("Right") + _beat_side("Left")

BEAT_LOWER_JOINTS: tuple[str, ...] = ("Hips", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
                                      "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase")
"""The BEAT skeleton's hips and legs, below the `beat` layout's joints."""

ARKIT52: tuple[str, ...] = (
    "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
    "eyeBlinkLeft", "eyeBlinkRight", "eyeLookDownLeft", "eyeLookDownRight",
    "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight",
    "eyeLookUpLeft", "eyeLookUpRight", "eyeSquintLeft", "eyeSquintRight",
    "eyeWideLeft", "eyeWideRight",
    "jawForward", "jawLeft", "jawOpen", "jawRight",
    "mouthClose", "mouthDimpleLeft", "mouthDimpleRight", "mouthFrownLeft", "mouthFrownRight",
    "mouthFunnel", "mouthLeft", "mouthLowerDownLeft", "mouthLowerDownRight",
    "mouthPressLeft", "mouthPressRight", "mouthPucker", "mouthRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthSmileLeft", "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthUpperUpLeft", "mouthUpperUpRight", "noseSneerLeft", "noseSneerRight",
    "tongueOut",
)
"""The 52 ARKit blendshapes, alphabetical."""

ARKIT51: tuple[str, ...] = tuple(n for n in ARKIT52 if n != "tongueOut")
"""The BEAT expression channels: ARKit-52 without tongueOut, alphabetical."""

SMPLX_JOINTS: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
    "left_eye_smplhf", "right_eye_smplhf",
) + tuple(
    f"{side}_{finger}{i}"
    for side in ("left", "right")
    for finger in ("index", "middle", "pinky", "ring", "thumb")
    for i in (1, 2, 3)
)
"""All 55 SMPL-X joints in SMPL-X order, named as the SMPL-X Blender add-on names bones."""

SMPLX_PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
) + tuple(wrist if i % 3 == 0 else 25 + 15 * side + i - 1
          for side, wrist in ((0, 20), (1, 21)) for i in range(15))
"""Parent index of each of SMPLX_JOINTS (the SMPL-X kinematic tree; -1 for the pelvis)."""

_SMPLX_GESTURE_IDS = (3, 6, 9) + tuple(range(12, 22)) + tuple(range(25, 55))
SMPLX_GESTURE_JOINTS: tuple[str, ...] = tuple(SMPLX_JOINTS[i] for i in _SMPLX_GESTURE_IDS)
SMPLX_EXPRESSION: tuple[str, ...] = tuple(f"Exp{i:03d}" for i in range(100))


@dataclass(frozen=True)
class Layout:
    """How a model's flat motion vector maps to named joints and face channels.

    `face_rotation_joints` are joints whose axis-angle rotations sit at the start of
    the expression part (SMPL-X's jaw); they join `joint_names` in a Motion. With
    `root_translation` the gesture part ends with the hips' translation (metres, 3
    channels), a Motion's `root_translation`. `skeleton` is the rig a Motion of the layout
    is on (its `rig`): the layout's name unless a layout widens another's joints.
    """

    name: str
    fps: float
    gesture_joints: tuple[str, ...]
    face_names: tuple[str, ...]
    face_rotation_joints: tuple[str, ...] = ()
    root_translation: bool = False
    skeleton: str = ""

    @property
    def rig(self) -> str:
        return self.skeleton or self.name

    @property
    def gesture_dim(self) -> int:
        return 3 * len(self.gesture_joints) + 3 * self.root_translation

    @property
    def expression_dim(self) -> int:
        return 3 * len(self.face_rotation_joints) + len(self.face_names)

    @property
    def dim(self) -> int:
        return self.gesture_dim + self.expression_dim

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.gesture_joints + self.face_rotation_joints

    def split(self, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T, dim) model-space motion -> rotations (T, J, 3) and face weights (T, K)."""
        if motion.ndim != 2 or motion.shape[1] != self.dim:
            raise DiffshegError(
                f"motion of shape {motion.shape} does not fit layout '{self.name}' "
                f"({self.dim} channels per frame)")
        gesture, expression = motion[:, : self.joint_channels], motion[:, self.gesture_dim :]
        n_face_rot = 3 * len(self.face_rotation_joints)
        rotations = np.concatenate([gesture, expression[:, :n_face_rot]], axis=1)
        return rotations.reshape(len(motion), rotations.shape[1] // 3, 3), expression[:, n_face_rot:]

    def root(self, motion: np.ndarray) -> np.ndarray | None:
        """(T, 3) hips translation of (T, dim) model-space motion (None: the layout has none)."""
        return motion[:, self.joint_channels:self.gesture_dim] if self.root_translation else None

    def join(self, rotations: np.ndarray, face: np.ndarray, root: np.ndarray | None = None) -> np.ndarray:
        """Inverse of `split` (and `root`: the layout's hips translation, which it needs)."""
        if self.root_translation and root is None:
            raise DiffshegError(f"layout '{self.name}' holds the hips' translation: the motion has none")
        flat = rotations.reshape(len(rotations), -1)
        gesture, face_rot = flat[:, : self.joint_channels], flat[:, self.joint_channels :]
        parts = [gesture] + ([root.reshape(len(flat), 3)] if self.root_translation else []) + [face_rot, face]
        return np.concatenate(parts, axis=1)

    def widened_channels(self, narrower: "Layout") -> np.ndarray | None:
        """Where each channel of `narrower` sits in this layout, when this one widens it (the
        same gesture joints first, more joints or the hips' translation after them, the
        same face); else None. A model of `narrower` can be fine-tuned into one of this."""
        if (self.gesture_joints[:len(narrower.gesture_joints)] != narrower.gesture_joints or narrower.root_translation
                or self.face_names != narrower.face_names or self.face_rotation_joints != narrower.face_rotation_joints
                or self.dim <= narrower.dim):
            return None
        return np.concatenate([np.arange(narrower.gesture_dim), self.gesture_dim + np.arange(narrower.expression_dim)])

    @property
    def joint_channels(self) -> int:
        """Channels of the gesture joints' rotations (the gesture part less any translation)."""
        return 3 * len(self.gesture_joints)


BEAT = Layout(name="beat", fps=15.0, gesture_joints=BEAT_JOINTS, face_names=ARKIT51)
BEAT_BODY = Layout(name="beat_body", fps=15.0, gesture_joints=BEAT_JOINTS + BEAT_LOWER_JOINTS, face_names=ARKIT51,
                   root_translation=True, skeleton="beat")
"""The whole body on the BEAT skeleton: `beat`'s joints, then the hips and legs, then the
hips' translation (171 gesture channels); a Motion of it is a `beat` Motion with legs."""
SMPLX = Layout(
    name="smplx", fps=15.0, gesture_joints=SMPLX_GESTURE_JOINTS,
    face_names=SMPLX_EXPRESSION, face_rotation_joints=("jaw",),
)
LAYOUTS: dict[str, Layout] = {BEAT.name: BEAT, BEAT_BODY.name: BEAT_BODY, SMPLX.name: SMPLX}


def get_layout(name: str) -> Layout:
    try:
        return LAYOUTS[name]
    except KeyError:
        raise DiffshegError(
            f"unknown rig layout '{name}': choose one of {', '.join(sorted(LAYOUTS))}") from None
