"""Retargeting: match a preset's names on a rig and convert rotations to its bones.

Rotations come out of the model in each joint's parent frame, with every joint's
rest frame aligned with the model's canonical axes (x = character's left, y = up,
z = forward). A target bone has its own rest frame (bone roll, import axes, object
transform), so each rotation is conjugated into that frame; optionally a rest
correction turns the model's T-pose arms into the rig's rest pose (A-pose rigs).

Only bpy data are read here (names, rest matrices); nothing is written. Presets
themselves are in preset.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diffsheg_core.errors import DiffshegError
from diffsheg_core.motion import Motion
from diffsheg_core.rotations import axis_angle_to_matrix, convert, quaternion_sequence_continuous

from .preset import JawDrive, Preset, find_name
from .visemes import derived_keys

# Landmark vectors of each layout's rest skeleton in its canonical frame, used to find
# the canonical axes on a target rig: "up" from the first to the second joint, "left"
# from the character's right to its left. BEAT numbers are the joint offsets of the
# BEAT skeleton (Spine -> Neck, RightArm -> LeftArm); SMPL-X's rest spine is upright.
LANDMARKS: dict[str, dict[str, tuple[str, str, tuple[float, float, float]]]] = {
    "beat": {"up": ("Spine", "Neck", (0.0, 54.064122, -1.675537)),
             "left": ("RightArm", "LeftArm", (1.0, 0.0, 0.0))},
    "smplx": {"up": ("spine1", "neck", (0.0, 1.0, 0.0)),
              "left": ("right_shoulder", "left_shoulder", (1.0, 0.0, 0.0))},
}

# Joints whose model rest direction is known (T-pose arms): used by presets with
# "align_rest" to turn the model's T-pose into the rig's own rest pose.
TPOSE_DIRECTIONS: dict[str, tuple[float, float, float]] = {
    **{f"{side}{j}": ((-1.0 if side == "Right" else 1.0), 0.0, 0.0)
       for side in ("Right", "Left") for j in ("Arm", "ForeArm", "Hand")},
    **{f"{side}_{j}": ((-1.0 if side == "right" else 1.0), 0.0, 0.0)
       for side in ("right", "left") for j in ("shoulder", "elbow", "wrist")},
}


# ---------------------------------------------------------------- rotation maths

def swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation matrix turning direction `a` onto direction `b`."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return axis_angle_to_matrix(np.pi * perp / np.linalg.norm(perp))
    return axis_angle_to_matrix(axis / s * np.arctan2(s, c))


def _frame(left: np.ndarray, up: np.ndarray) -> np.ndarray:
    x = left / np.linalg.norm(left)
    y = up - np.dot(up, x) * x
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


# ---------------------------------------------------------------- mapping onto a rig

@dataclass
class BoneTarget:
    """One keyed bone: where its rotations come from and how to convert them."""

    bone: str
    joint: str | None         # motion joint; None when driven by a face weight (jaw)
    left: np.ndarray           # 3x3: L_t = left @ R_t @ right
    right: np.ndarray
    rotation_mode: str


@dataclass
class ArmatureMapping:
    armature: str
    targets: list[BoneTarget]
    unmatched: list[str]       # canonical joints of the preset with no bone on the rig
    jaw_source: int | None = None   # face channel driving the jaw target, if any
    jaw: JawDrive | None = None


def map_armature(armature, preset: Preset, motion: Motion) -> ArmatureMapping:
    """Match the preset's bones on `armature` (a bpy Object) and prepare conversions.

    Raises DiffshegError when nothing matches, naming the preset and the rig.
    """
    joint_map = preset.joint_map(motion.rig)
    bones = armature.data.bones
    matched: dict[str, str] = {}
    unmatched: list[str] = []
    for joint, bone in joint_map.items():
        if joint not in motion.joint_names:
            continue
        found = find_name([bone], bones.keys())
        if found is None:
            unmatched.append(f"{joint} -> {bone}")
        else:
            matched[joint] = found
    jaw_bone = None
    if preset.jaw and preset.jaw.source in motion.face_names and "jaw" not in matched:
        jaw_bone = find_name([preset.jaw.bone], bones.keys())
        if jaw_bone is None:
            unmatched.append(f"jaw (from {preset.jaw.source}) -> {preset.jaw.bone}")
    if not matched and jaw_bone is None:
        raise DiffshegError(
            f"armature '{armature.name}' has none of the bones of preset '{preset.name}' "
            f"(e.g. {', '.join(list(joint_map.values())[:3])}): pick the preset that fits the rig")

    axes = _canonical_axes(armature, motion.rig, matched)
    rest = {name: _rest(bones[name]) for name in set(matched.values()) | ({jaw_bone} - {None})}
    tpose = {matched[j]: TPOSE_DIRECTIONS[j] for j in matched if preset.align_rest and j in TPOSE_DIRECTIONS}
    correction = _rest_corrections(armature, rest, axes, tpose)

    def target(bone: str, joint: str | None) -> BoneTarget:
        b = rest[bone]
        parent = _mapped_ancestor(bones[bone], correction)
        d_parent = correction[parent] if parent else np.eye(3)
        d_own = correction[bone]
        return BoneTarget(
            bone=bone, joint=joint,
            left=b.T @ d_parent @ axes, right=axes.T @ d_own.T @ b,
            rotation_mode=armature.pose.bones[bone].rotation_mode)

    targets = [target(bone, joint) for joint, bone in matched.items()]
    if jaw_bone is not None:
        targets.append(target(jaw_bone, None))
    return ArmatureMapping(
        armature=armature.name, targets=targets, unmatched=unmatched,
        jaw_source=motion.face_names.index(preset.jaw.source) if jaw_bone else None,
        jaw=preset.jaw if jaw_bone else None)


def _rest(bone) -> np.ndarray:
    """Bone rest orientation in armature space, 3x3 without scale."""
    m = np.array(bone.matrix_local.to_3x3(), dtype=np.float64)
    return m / np.linalg.norm(m, axis=0, keepdims=True)


def _canonical_axes(armature, layout: str, matched: dict[str, str]) -> np.ndarray:
    """3x3 taking the model's canonical axes to the armature's space (from landmarks)."""
    marks = LANDMARKS.get(layout)
    bones = armature.data.bones
    vectors = {}
    for key, (a, b, model_vec) in (marks or {}).items():
        if a in matched and b in matched:
            rig_vec = np.array(bones[matched[b]].head_local - bones[matched[a]].head_local)
            if np.linalg.norm(rig_vec) > 1e-9:
                vectors[key] = (np.array(model_vec), rig_vec)
    if len(vectors) < 2:
        # Without landmarks assume the usual Blender character: Z up, facing -Y.
        obj = np.array(armature.matrix_world.to_3x3().normalized(), dtype=np.float64)
        return obj.T @ _blender_axes()
    model = _frame(vectors["left"][0], vectors["up"][0])
    rig = _frame(vectors["left"][1], vectors["up"][1])
    return rig @ model.T


def _blender_axes() -> np.ndarray:
    """Columns: the canonical left, up, forward of a character standing on Blender's
    Z axis and facing -Y (front view), in world space."""
    return np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


def _rest_corrections(armature, rest: dict, axes: np.ndarray, tpose: dict) -> dict[str, np.ndarray]:
    """Per mapped bone, the rotation turning the model's rest pose into the rig's: a
    swing from the model's T-pose direction where one is known, else the correction of
    the nearest mapped ancestor (so a whole hand follows its wrist), else identity."""
    bones = armature.data.bones
    out: dict[str, np.ndarray] = {}
    for bone in sorted(rest, key=lambda name: len(bones[name].parent_recursive)):
        if bone in tpose:
            out[bone] = swing(axes @ np.array(tpose[bone]), rest[bone][:, 1])
        else:
            parent = _mapped_ancestor(bones[bone], out)
            out[bone] = out[parent] if parent else np.eye(3)
    return out


def _mapped_ancestor(bone, mapped) -> str | None:
    parent = bone.parent
    while parent is not None:
        if parent.name in mapped:
            return parent.name
        parent = parent.parent
    return None


def bone_quaternions(motion: Motion, mapping: ArmatureMapping) -> dict[str, np.ndarray]:
    """Per target bone, (T, 4) local rotations (w, x, y, z) with hemisphere continuity."""
    out = {}
    for t in mapping.targets:
        if t.joint is not None:
            rotvec = motion.rotations[:, motion.joint_names.index(t.joint)]
        else:
            weight = np.clip(motion.face[:, mapping.jaw_source], 0.0, 1.0)
            axis = np.asarray(mapping.jaw.axis, dtype=np.float64)
            rotvec = weight[:, None] * np.radians(mapping.jaw.degrees) * axis / np.linalg.norm(axis)
        local = t.left @ axis_angle_to_matrix(rotvec) @ t.right
        out[t.bone] = quaternion_sequence_continuous(convert(local, "matrix", "quaternion"))
    return out


# ---------------------------------------------------------------- shape keys

@dataclass
class ShapeKeyMapping:
    mesh: str
    pairs: list[tuple[int, str]]   # (face channel index, shape key name)
    unmatched: list[str]
    derived: list[tuple[dict[int, float], str]] = field(default_factory=list)  # (weights, key): see visemes
    empty: list[str] = field(default_factory=list)  # keys named like a channel that move no vertex

    def curves(self, face: np.ndarray) -> list[tuple[str, np.ndarray]]:
        """(shape key, weights over time) for every key this mapping drives."""
        out = [(key, face[:, index]) for index, key in self.pairs]
        out += [(key, np.clip(sum(w * face[:, i] for i, w in weights.items()), 0.0, 1.0))
                for weights, key in self.derived]
        return out


def moves_vertices(key_block) -> bool:
    """Whether a shape key displaces any vertex from the key it is relative to."""
    n = len(key_block.data)
    here, base = np.empty(3 * n), np.empty(3 * n)
    key_block.data.foreach_get("co", here)
    key_block.relative_key.data.foreach_get("co", base)
    return bool(np.abs(here - base).max(initial=0.0) > 1e-7)


def map_shape_keys(mesh, preset: Preset, motion: Motion) -> ShapeKeyMapping:
    """Match the motion's face channels to `mesh`'s shape keys (case-insensitive, aliases)."""
    keys = mesh.data.shape_keys
    if keys is None or len(keys.key_blocks) < 2:
        raise DiffshegError(
            f"mesh '{mesh.name}' has no shape keys: pick the face mesh with the expression "
            f"shape keys (e.g. ARKit jawOpen, eyeBlinkLeft)")
    working = [kb.name for kb in keys.key_blocks[1:] if moves_vertices(kb)]
    empty = [kb.name for kb in keys.key_blocks[1:] if kb.name not in working]
    pairs, unmatched = [], []
    for i, name in enumerate(motion.face_names):
        found = find_name([name] + preset.shape_key_aliases.get(name, []), working)
        if found is None:
            unmatched.append(name)
        else:
            pairs.append((i, found))
    used = {key for _, key in pairs}
    derived = []
    for names, weights in derived_keys({motion.face_names[i] for i, _ in pairs}, motion.face_names):
        found = find_name(list(names), [k for k in working if k not in used])
        if found is not None and weights:
            derived.append((weights, found))
            used.add(found)
    if not pairs and not derived:
        raise DiffshegError(
            f"mesh '{mesh.name}' has no shape key matching the model's face channels "
            f"({', '.join(motion.face_names[:3])}, ...): rename its shape keys or add aliases "
            f"to preset '{preset.name}'")
    empty = [k for k in empty if find_name([k], motion.face_names) is not None]
    return ShapeKeyMapping(mesh=mesh.name, pairs=pairs, unmatched=unmatched, derived=derived, empty=empty)
