"""Retargeting: match a preset's names on a rig and convert rotations to its bones.

Rotations come out of the model in each joint's parent frame, with every joint's
rest frame aligned with the model's canonical axes (x = character's left, y = up,
z = forward). A target bone has its own rest frame (bone roll, import axes, object
transform), so each rotation is conjugated into that frame; optionally a rest
correction turns the model's T-pose arms into the rig's rest pose (A-pose rigs),
measured along each bone's chain. A joint may be spread over a chain of the rig's bones
(several spine bones for the model's one), and a joint the rig lacks passes its rotation
on to the joints below it, so the bones further down still point where the model's do.

Only bpy data are read here (names, rest matrices); nothing is written. Presets
themselves are in preset.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diffsheg_core.bvh import beat_skeleton
from diffsheg_core.errors import DiffshegError
from diffsheg_core.lower_body.leg_ik import swing
from diffsheg_core.lower_body import JOINTS as LOWER_JOINTS, LEGS, canonical_leg_length
from diffsheg_core.motion import Motion
from diffsheg_core.rigs import SMPLX_JOINTS, SMPLX_PARENTS
from diffsheg_core.rotations import axis_angle_to_matrix, convert, quaternion_sequence_continuous

from .preset import JawDrive, Preset, find_name
from .visemes import DerivedKey, derived_keys

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

# Joints whose model rest direction is known (T-pose arms), with the child joint whose
# head the direction points at: presets with "align_rest" turn the model's T-pose into
# the rig's rest pose, measured on the rig from the bone's head to its child's.
ALIGN: dict[str, tuple[tuple[float, float, float], str]] = {
    **{f"{side}{j}": (((-1.0 if side == "Right" else 1.0), 0.0, 0.0), f"{side}{child}")
       for side in ("Right", "Left")
       for j, child in (("Arm", "ForeArm"), ("ForeArm", "Hand"), ("Hand", "HandMiddle1"))},
    **{f"{side}_{j}": (((-1.0 if side == "right" else 1.0), 0.0, 0.0), f"{side}_{child}")
       for side in ("right", "left")
       for j, child in (("shoulder", "elbow"), ("elbow", "wrist"), ("wrist", "middle1"))},
    # the canonical body's legs point straight down at rest (lower_body's BEAT skeleton)
    **{f"{side}{j}": ((0.0, -1.0, 0.0), f"{side}{child}")
       for side in ("Right", "Left") for j, child in (("UpLeg", "Leg"), ("Leg", "Foot"))},
}

# Joints that keep the rig's rest orientation in the world when the model's is at rest,
# whatever the correction of the bones above them: a foot stands flat on the floor as the
# rig's does (its bone points at the toes, at a slope that depends on the ankle's height).
LEVEL: frozenset[str] = frozenset({"RightFoot", "LeftFoot"})

# The legs of the `beat` layout, (thigh, shin, foot) per side, and the root joint whose
# translation (Motion.root_translation) moves the body: the core's lower body.
ROOT = LOWER_JOINTS[0]
LOWER_BODY: frozenset[str] = frozenset(LOWER_JOINTS)
"""Joints turned about level axes (the world's up), so the feet stay on the floor of a rig
whose spine leans otherwise than the model's."""


def layout_parents(layout: str) -> dict[str, str | None]:
    """Each joint of a layout's whole skeleton -> its parent joint (None for the root),
    also the joints the model does not move (BEAT's Head, SMPL-X's pelvis)."""
    if layout == "smplx":
        return {n: (SMPLX_JOINTS[p] if p >= 0 else None) for n, p in zip(SMPLX_JOINTS, SMPLX_PARENTS)}
    if layout == "beat":
        skeleton = beat_skeleton()
        return {n: (skeleton.joint_names[p] if p >= 0 else None)
                for n, p in zip(skeleton.joint_names, skeleton.parents)}
    raise DiffshegError(f"no skeleton known for the '{layout}' layout: use a model of the beat or smplx layout")


# ---------------------------------------------------------------- rotation maths

def _frame(left: np.ndarray, up: np.ndarray) -> np.ndarray:
    x = left / np.linalg.norm(left)
    y = up - np.dot(up, x) * x
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


# ---------------------------------------------------------------- mapping onto a rig

@dataclass
class BoneTarget:
    """One keyed bone: where its rotation comes from and how to convert it.

    The rotations of `joints` are composed in order (joints the rig lacks first, passed
    on to this bone) and `share` of the result is taken (a joint spread over a chain of
    bones); no joints: a jaw driven by a face weight."""

    bone: str
    joints: tuple[str, ...]
    share: float
    left: np.ndarray           # 3x3: L_t = left @ R_t @ right
    right: np.ndarray
    rotation_mode: str


@dataclass
class RootTarget:
    """The hips bone's location from the motion's root translation: `matrix` (3x3) takes a
    displacement in the canonical axes, in metres of the canonical body, to the pose bone's
    location (its rest frame, armature units, scaled by the rig's legs over the body's)."""

    bone: str
    matrix: np.ndarray
    rest: np.ndarray   # 3x3: the bone's location to a displacement in armature space

    def displacement(self, location: np.ndarray) -> np.ndarray:
        """(T, 3) pose-bone locations as displacements in armature space (feet.py works in these)."""
        return location @ self.rest.T

    def location(self, displacement: np.ndarray) -> np.ndarray:
        """(T, 3) displacements in armature space back to pose-bone locations."""
        return np.linalg.solve(self.rest, displacement.T).T


@dataclass
class LegRig:
    """One leg of the rig, for planting its foot (feet.py): bone names, and at rest the hips
    bone's and the leg's rest orientations (armature space, 3x3 with scale removed) and the
    heads of the hips, thigh, knee and ankle (armature space)."""

    side: str
    bones: tuple[str, str, str]        # thigh, shin, foot
    rest: tuple[np.ndarray, ...]       # hips, thigh, shin, foot orientations
    heads: np.ndarray                  # (4, 3) hips, thigh, knee and ankle heads
    left: np.ndarray                   # (3,) the canonical left in armature space


@dataclass
class ArmatureMapping:
    armature: str
    targets: list[BoneTarget]
    unmatched: list[str]       # canonical joints of the preset with no bone on the rig
    jaw_source: int | None = None   # face channel driving the jaw target, if any
    jaw: JawDrive | None = None
    notes: list[str] = field(default_factory=list)
    root: RootTarget | None = None  # the hips' location, where the motion moves the root
    legs: list[LegRig] = field(default_factory=list)   # legs keyed whole (thigh, shin and foot)


def map_armature(armature, preset: Preset, motion: Motion,
                 jaw_shape_keys: list["ShapeKeyMapping"] = ()) -> ArmatureMapping:
    """Match the preset's bones on `armature` (a bpy Object) and prepare conversions.

    A joint the rig lacks passes its rotation on to the nearest joints below it that the
    rig has (the model's Neck1 into the head of a rig without a second neck bone). The
    jaw bone is driven from its face weight only where none of the face meshes'
    `jaw_shape_keys` mappings has a key following that weight (else the mouth opens twice).
    Raises DiffshegError when nothing matches, naming the preset and the rig.
    """
    parents = layout_parents(motion.rig)
    bones = armature.data.bones
    chains, missing = _match_chains(preset, motion.rig, parents, bones)
    moving = set(motion.joint_names)
    passed_to: dict[str, list[str]] = {}
    sources: dict[str, tuple[str, ...]] = {}
    for joint in chains:
        passed, above = [], parents[joint]
        while above is not None and above not in chains:
            if above in missing and above in moving:
                passed.insert(0, above)
                passed_to.setdefault(above, []).append(chains[joint][0])
            above = parents[above]
        own = [joint] if joint in moving else []
        if passed + own:
            sources[joint] = tuple(passed + own)
    unmatched = [f"{j} -> {', '.join(missing[j])}" for j in missing if j in moving and j not in passed_to]
    notes = [f"{j} ({', '.join(missing[j])} not on the rig) passed on to {', '.join(to)}"
             for j, to in passed_to.items()]
    jaw_bone = None
    if preset.jaw and preset.jaw.source in motion.face_names and "jaw" not in sources:
        jaw_bone = preset.find_bone(preset.jaw.bone, bones.keys())
        channel = motion.face_names.index(preset.jaw.source)
        by_keys = [m.mesh for m in jaw_shape_keys if m.drives(channel)]
        if jaw_bone is None:
            unmatched.append(f"jaw (from {preset.jaw.source}) -> {preset.jaw.bone}")
        elif by_keys:
            notes.append(f"jaw bone {preset.jaw.bone} left at rest: the {preset.jaw.source} shape key of "
                         f"{', '.join(by_keys)} opens the mouth")
            jaw_bone = None
    if not sources and jaw_bone is None:
        wanted = [b for chain in preset.joint_map(motion.rig).values() for b in chain]
        raise DiffshegError(
            f"armature '{armature.name}' has none of the bones of preset '{preset.name}' "
            f"(e.g. {', '.join(wanted[:3])}): pick the preset that fits the rig, or Auto")

    axes = _canonical_axes(armature, motion.rig, {j: c[0] for j, c in chains.items()})
    level = _level_axes(armature, axes)
    frames = {j: level if j in LOWER_BODY else axes for j in chains}
    keyed = [b for j in sources for b in chains[j]] + ([jaw_bone] if jaw_bone else [])
    rest = {name: _rest(bones[name]) for name in keyed}
    directions = _rest_directions(bones, chains, frames) if preset.align_rest else {}
    flat = {chains[j][0] for j in LEVEL if j in chains} if preset.align_rest else set()
    correction = _rest_corrections(bones, rest, directions, flat)

    def target(bone: str, joints: tuple[str, ...], share: float, frame: np.ndarray) -> BoneTarget:
        b = rest[bone]
        parent = _mapped_ancestor(bones[bone], correction)
        d_parent = correction[parent] if parent else np.eye(3)
        d_own = correction[bone]
        return BoneTarget(
            bone=bone, joints=joints, share=share,
            left=b.T @ d_parent @ frame, right=frame.T @ d_own.T @ b,
            rotation_mode=armature.pose.bones[bone].rotation_mode)

    targets = [target(bone, joints, 1.0 / len(chains[joint]), frames[joint])
               for joint, joints in sources.items() for bone in chains[joint]]
    if jaw_bone is not None:
        targets.append(target(jaw_bone, (), 1.0, axes))
    legs = _leg_rigs(bones, chains, sources, level)
    root = _root_target(bones, chains, sources, level, legs, motion, notes)
    return ArmatureMapping(
        armature=armature.name, targets=targets, unmatched=unmatched,
        jaw_source=motion.face_names.index(preset.jaw.source) if jaw_bone else None,
        jaw=preset.jaw if jaw_bone else None, notes=notes, root=root, legs=legs)


def _leg_rigs(bones, chains: dict, sources: dict, axes: np.ndarray) -> list[LegRig]:
    """The rig's legs whose thigh, shin and foot are each one keyed bone, under a keyed hips."""
    if ROOT not in sources or len(chains[ROOT]) != 1:
        return []
    hips = chains[ROOT][0]
    out = []
    for side, joints in LEGS.items():
        if not all(j in sources and len(chains[j]) == 1 for j in joints):
            continue
        names = (hips, *(chains[j][0] for j in joints))
        out.append(LegRig(side=side, bones=names[1:], rest=tuple(_rest(bones[n]) for n in names),
                          heads=np.array([bones[n].head_local for n in names], dtype=np.float64),
                          left=axes[:, 0].copy()))
    return out


def leg_length(leg: LegRig) -> float:
    """Thigh and shin of a rig's leg together, hip to ankle at rest (armature units)."""
    return float(np.linalg.norm(leg.heads[2] - leg.heads[1]) + np.linalg.norm(leg.heads[3] - leg.heads[2]))


def _root_target(bones, chains: dict, sources: dict, axes: np.ndarray, legs: list[LegRig], motion: Motion,
                 notes: list[str]) -> RootTarget | None:
    """The hips bone's location target, where the motion has a root translation, the rig keys
    the hips and has a leg to scale it by (the translation moves the body over its legs: in
    proportion to their length the legs' turns keep the feet where the motion plants them)."""
    if motion.root_translation is None or ROOT not in sources:
        return None
    if not legs:
        notes.append(f"hips location not keyed: no leg of the rig to scale it by (thigh, shin and foot of "
                     f"{' or '.join(' '.join(j) for j in LEGS.values())})")
        return None
    height = motion.meta.get("hips_height")
    if not isinstance(height, (int, float)) or not height > 0:
        raise DiffshegError("the motion has a root translation but no hips height (meta 'hips_height', "
                            "metres): generate it again, or with upper_body_only")
    scale = np.mean([leg_length(leg) for leg in legs]) / canonical_leg_length(float(height))
    bone = bones[chains[ROOT][0]]
    local = np.array(bone.matrix_local.to_3x3(), dtype=np.float64)
    return RootTarget(bone=bone.name, matrix=np.linalg.solve(local, axes) * scale, rest=local)


def _match_chains(preset: Preset, layout: str, parents: dict, bones) -> tuple[dict, dict]:
    """({joint: its bones on the rig, parent first}, {joint: its preset bones, none on the rig})
    over the joints of the layout's skeleton that the preset maps."""
    chains, missing = {}, {}
    for joint, wanted in preset.joint_map(layout).items():
        if joint not in parents:
            continue
        found = [b for b in dict.fromkeys(preset.find_bone(w, bones.keys()) for w in wanted) if b]
        if found:
            chains[joint] = sorted(found, key=lambda name: len(bones[name].parent_recursive))
        else:
            missing[joint] = wanted
    return chains, missing


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


def _level_axes(armature, axes: np.ndarray) -> np.ndarray:
    """The canonical axes on the rig made level: up is the world's up (Blender's Z) in the
    armature's space, left the landmarks' left made horizontal, forward their cross."""
    world = np.array(armature.matrix_world.to_3x3(), dtype=np.float64)
    return _frame(axes[:, 0], np.linalg.solve(world, [0.0, 0.0, 1.0]))


def _blender_axes() -> np.ndarray:
    """Columns: the canonical left, up, forward of a character standing on Blender's
    Z axis and facing -Y (front view), in world space."""
    return np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


def _rest_directions(bones, chains: dict, frames: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per aligned bone: (the model's T-pose direction, the rig's rest direction), both
    in armature space. The rig's is from the bone's head to its child's head, because a
    bone's own axis need not point at its child (FBX imports without automatic bone
    orientation); the bone's own Y axis only where the child is not on the rig."""
    out = {}
    for joint, (model_dir, child) in ALIGN.items():
        if joint not in chains:
            continue
        bone = bones[chains[joint][0]]
        child_bone = bones[chains[child][0]] if child in chains else None
        rig_dir = (np.array(child_bone.head_local - bone.head_local)
                   if child_bone is not None and bone in child_bone.parent_recursive else None)
        if rig_dir is None or np.linalg.norm(rig_dir) < 1e-9:
            rig_dir = _rest(bone)[:, 1]
        out[bone.name] = (frames[joint] @ np.array(model_dir), rig_dir)
    return out


def _rest_corrections(bones, rest: dict, directions: dict, level: set[str] = frozenset()) -> dict[str, np.ndarray]:
    """Per keyed bone, the rotation turning the model's rest pose into the rig's: identity for
    the `level` bones, a swing from the model's T-pose direction where one is known, else the
    correction of the nearest keyed ancestor (so a whole hand follows its wrist), else identity."""
    out: dict[str, np.ndarray] = {}
    for bone in sorted(rest, key=lambda name: len(bones[name].parent_recursive)):
        if bone in level:
            out[bone] = np.eye(3)
        elif bone in directions:
            out[bone] = swing(*directions[bone])
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
        if t.joints:
            rotation = np.eye(3)
            for joint in t.joints:
                rotation = rotation @ axis_angle_to_matrix(motion.rotations[:, motion.joint_names.index(joint)])
            if t.share != 1.0:
                rotation = axis_angle_to_matrix(t.share * convert(rotation, "matrix", "axis_angle"))
        else:
            weight = np.clip(motion.face[:, mapping.jaw_source], 0.0, 1.0)
            axis = np.asarray(mapping.jaw.axis, dtype=np.float64)
            rotation = axis_angle_to_matrix(weight[:, None] * np.radians(mapping.jaw.degrees) * axis
                                            / np.linalg.norm(axis))
        local = t.left @ rotation @ t.right
        out[t.bone] = quaternion_sequence_continuous(convert(local, "matrix", "quaternion"))
    return out


def joint_rotation(target: BoneTarget, local: np.ndarray, passed: np.ndarray | None = None) -> np.ndarray:
    """The inverse of `bone_quaternions` for one bone and one frame: the axis-angle rotation
    of the target's own joint (its last) that gives the bone the local rotation matrix
    `local`, the rotations of the joints passed on to it being `passed` (3x3, their product;
    None: at rest). Raises DiffshegError for a bone no joint drives (a jaw)."""
    if not target.joints:
        raise DiffshegError(f"bone {target.bone} follows a face weight, not a joint of the model")
    rotation = target.left.T @ local @ target.right.T
    if target.share != 1.0:
        rotation = axis_angle_to_matrix(convert(rotation, "matrix", "axis_angle") / target.share)
    if passed is not None:
        rotation = passed.T @ rotation
    return convert(rotation, "matrix", "axis_angle")


def passed_rotation(target: BoneTarget, motion: Motion, frame: int) -> np.ndarray:
    """3x3 product of the rotations of the joints passed on to `target` at `frame` of `motion`."""
    rotation = np.eye(3)
    for joint in target.joints[:-1]:
        rotation = rotation @ axis_angle_to_matrix(motion.rotations[frame, motion.joint_names.index(joint)])
    return rotation


# ---------------------------------------------------------------- shape keys

@dataclass
class ShapeKeyMapping:
    mesh: str
    pairs: list[tuple[int, str]]   # (face channel index, shape key name)
    unmatched: list[str]
    derived: list[tuple[DerivedKey, str]] = field(default_factory=list)  # (how it follows the face, key): visemes
    empty: list[str] = field(default_factory=list)  # keys named like a channel that move no vertex

    def drives(self, channel: int) -> bool:
        """Whether some key of this mapping follows face channel `channel`."""
        return any(i == channel for i, _ in self.pairs) or any(channel in d.channels for d, _ in self.derived)

    def curves(self, face: np.ndarray) -> list[tuple[str, np.ndarray]]:
        """(shape key, weights over time) for every key this mapping drives."""
        out = [(key, face[:, index]) for index, key in self.pairs]
        out += [(key, derived.values(face)) for derived, key in self.derived]
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
        names = [name] + preset.shape_key_aliases.get(name, [])
        found = find_name(names, working)
        if found is not None:
            pairs.append((i, found))
        elif find_name(names, empty) is None:  # a key that moves no vertex is reported as such, not as missing
            unmatched.append(name)
    used = {key for _, key in pairs}
    for i, _ in list(pairs):
        for extra in preset.also_drives.get(motion.face_names[i], []):
            found = find_name([extra], [k for k in working if k not in used])
            if found is not None:
                pairs.append((i, found))
                used.add(found)
    derived = []
    for names, how in derived_keys({motion.face_names[i] for i, _ in pairs}, motion.face_names):
        found = find_name(list(names), [k for k in working if k not in used])
        if found is not None:
            derived.append((how, found))
            used.add(found)
    if not pairs and not derived:
        raise DiffshegError(
            f"mesh '{mesh.name}' has no shape key matching the model's face channels "
            f"({', '.join(motion.face_names[:3])}, ...): rename its shape keys or add aliases "
            f"to preset '{preset.name}'")
    empty = [k for k in empty if find_name([k], motion.face_names) is not None]
    return ShapeKeyMapping(mesh=mesh.name, pairs=pairs, unmatched=unmatched, derived=derived, empty=empty)
