"""Write a generated Motion into the scene: Actions, sound strip, frame range.

Everything that can fail (resampling, matching the rig, converting rotations) runs
before the first change to Blender data; the changes themselves are recorded and
undone in reverse if anything still goes wrong, so the scene is left as it was.
Call only from Blender's main thread.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import bpy
import numpy as np

from diffsheg_core.errors import DiffshegError
from diffsheg_core.keyframes import ErrorFn, Keys, fit_keys, rotation_error, value_error
from diffsheg_core.motion import Motion, resample_motion, smooth_frames

from . import takes
from .keying import (Channel, Undo, action_fcurves, new_action, record_baked, rotation_channels,
                     shape_key_channel, undone_on_error, write_channels)
from .feet import plant_feet, scene_spans
from .preset import AUTO, available_presets, choose_preset, load_preset, preset_fit
from .retarget import ArmatureMapping, Preset, ShapeKeyMapping, bone_quaternions, map_armature, map_shape_keys
from .sound import NO_AUDIO_NOTE, add_sound_strip, audio_supported, remove_strips, strips_added_for


@dataclass
class BakeOptions:
    """What to key and how. By default sparse Bezier keys on the motion's turning points,
    within `max_error` degrees per bone and `max_face_error` per shape key on every frame;
    `every_frame` keys each frame instead (baked curves for game export). `smoothing` is
    a Gaussian sigma in scene frames. With `nla_strip` (Generate for Sound Strips: the sound
    strip's name) the take plays from the sound-strips NLA track instead of as the active
    Action (takes.play_in_sequence), so each line's take plays at its own frames."""

    armature: object | None
    face_meshes: list = field(default_factory=list)
    preset: Preset | None = None   # None: Auto, the preset whose names the rig has
    start_frame: int = 1
    every_frame: bool = False
    max_error: float = 1.0          # degrees, the angle between keyed and generated rotation
    max_face_error: float = 0.02    # shape-key weight
    smoothing: float = 0.0
    add_sound: bool = True
    set_frame_range: bool = True
    nla_strip: str | None = None    # play the take from the sound-strips NLA track, as this strip

    def __post_init__(self):
        for name, value in (("max_error", self.max_error), ("max_face_error", self.max_face_error),
                            ("smoothing", self.smoothing)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) \
                    or value < 0 or (value == 0 and name != "smoothing"):
                raise DiffshegError(f"{name.replace('_', ' ')} must be a number "
                                    f"{'>= 0' if name == 'smoothing' else 'above 0'}, got {value!r}")


def keying_options(scene, armature, faces: list, preset: str, start_frame: int | None, **keying) -> BakeOptions:
    """BakeOptions from choices made by name, as a command line or a studio line makes them:
    the preset's name or file (AUTO: the preset whose names the rig has) and the first frame
    (None: the scene's start); `keying` is the rest of BakeOptions."""
    return BakeOptions(armature=armature, face_meshes=faces, preset=None if preset == AUTO else load_preset(preset),
                       start_frame=scene.frame_start if start_frame is None else start_frame, **keying)


@dataclass
class BakeResult:
    take: str
    preset: str
    actions: list[str]
    n_frames: int
    n_keys: int
    unmatched_bones: list[str]
    unmatched_shape_keys: dict[str, list[str]]
    sound_strip: str | None
    notes: list[str] = field(default_factory=list)          # warnings: what may need the animator
    preset_notes: list[str] = field(default_factory=list)   # how Auto chose the preset


MIN_FRAME, MAX_FRAME = -1_048_574, 1_048_574  # Blender's frame range


def check_frames(start: int, n_frames: int = 1) -> None:
    """Refuse a start frame from which `n_frames` keys would leave Blender's frame range
    (keys, frame range and sound strip would fall out of step)."""
    last = start + n_frames - 1
    if start < MIN_FRAME or last > MAX_FRAME:
        raise DiffshegError(f"start frame {start} with {n_frames} frames of motion ends at frame {last}, "
                            f"outside Blender's frames {MIN_FRAME} to {MAX_FRAME}: choose a start frame "
                            f"from {MIN_FRAME} to {MAX_FRAME - n_frames + 1}")


def check_range_start(options: BakeOptions) -> None:
    """Refuse keys before frame 0 when the scene's frame range is to follow them: a scene's
    range cannot start there (Blender would silently start it at 0)."""
    if options.set_frame_range and options.start_frame < 0:
        raise DiffshegError(f"start frame {options.start_frame} is before frame 0, where a scene's frame range "
                            "must start: start at 0 or later, or keep the scene's frame range as it is "
                            "(--keep-frame-range; 'Frame range' off in the panel) to key before it")


def check_local(objects) -> None:
    """Refuse objects whose animation would not be saved with the file: linked from a
    library, or library overrides (the override's Action lives in the linked file's data)."""
    for ob in objects:
        if ob is None:
            continue
        for block in (ob, ob.data, getattr(ob.data, "shape_keys", None)):
            if block is None:
                continue
            if block.library is not None:
                raise DiffshegError(f"'{ob.name}' is linked from {block.library.filepath}: keys on it would "
                                    "not be saved. Make it local (Object > Relations > Make Local) first")
            if getattr(block, "override_library", None) is not None:
                raise DiffshegError(f"'{ob.name}' is a library override: keys on it are lost when the "
                                    "library reloads. Make it local (Object > Relations > Make Local) first")


def scene_fps(scene) -> float:
    return scene.render.fps / scene.render.fps_base


@dataclass
class Group:
    """Channels keyed on shared frames (one bone's rotation, or one shape key): their dense
    values, one per scene frame from the start frame, and how far keys may stray from them."""

    channels: list[Channel]
    error: Callable[[np.ndarray], ErrorFn]   # the group's (T, C) values -> its ErrorFn
    bound: float


@dataclass
class Plan:
    """What keying a motion will write, worked out before any change to Blender data."""

    motion: Motion                     # at the scene's rate
    options: BakeOptions               # with the preset chosen
    targets: list[tuple[object, list[Group]]]   # (Object or shape-key Key, its groups)
    unmatched_bones: list[str]
    unmatched_shape_keys: dict[str, list[str]]
    notes: list[str]
    preset_notes: list[str]
    keyed_joints: frozenset[str] = frozenset()   # the model's joints keyed on the armature


@dataclass
class TargetMap:
    """The options' armature and face meshes matched to a motion's layout, once: what keying
    and Live (live.py) turn the motion's frames into bone rotations and shape-key values with."""

    options: BakeOptions                          # with the preset chosen
    armature: ArmatureMapping | None
    faces: list[tuple[object, ShapeKeyMapping]]   # (face mesh, its mapping)
    preset_notes: list[str]


def resolve_preset(layout: str, options: BakeOptions) -> tuple[BakeOptions, list[str]]:
    """The options with their preset chosen (Auto: the one whose names the rig has) and checked
    against the armature, and notes on how Auto chose. Raises DiffshegError (nothing changed)
    for no target, a linked target or a preset that does not fit the rig."""
    if options.armature is None and not options.face_meshes:
        raise DiffshegError("no target: choose an armature and/or a face mesh in the panel")
    check_local([options.armature, *options.face_meshes])
    notes: list[str] = []
    if options.preset is None:
        preset, note = auto_preset(layout, options.armature, options.face_meshes)
        options, notes = replace(options, preset=preset), [note]
    if options.armature is not None:
        check_preset_fits(options.preset, layout, options.armature)
    return options, notes


def map_targets(motion: Motion, options: BakeOptions, preset_notes: list[str] = ()) -> TargetMap:
    """The preset of `options` (chosen by `resolve_preset`) matched on their armature and face
    meshes for `motion`'s layout (only its names are read). Raises DiffshegError (nothing
    changed) when nothing can be matched."""
    faces = [(mesh, map_shape_keys(mesh, options.preset, motion)) for mesh in options.face_meshes]
    mapping = None
    if options.armature is not None:
        mapping = map_armature(options.armature, options.preset, motion, jaw_shape_keys=[k for _, k in faces])
    return TargetMap(options, mapping, faces, list(preset_notes))


def body_pose(mapping: ArmatureMapping, motion: Motion,
              smoothing: float = 0.0) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Per driven bone its (T, 4) local quaternions, and the hips bone's (T, 3) location (None
    where the mapping keys none); over the motion's contact spans (meta "contacts") each leg
    is solved again on the rig's bones so the contact foot stays put, the hips lowered where a
    leg needs them to reach (feet.py)."""
    quaternions = bone_quaternions(motion, mapping)
    if smoothing > 0:
        for bone, quats in quaternions.items():
            quats = smooth_frames(quats, smoothing)
            quaternions[bone] = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    if mapping.root is None:
        return quaternions, None
    location = motion.root_translation.astype(np.float64) @ mapping.root.matrix.T
    if smoothing > 0:
        location = smooth_frames(location, smoothing)
    contacts = motion.meta.get("contacts") or {}
    spans = {leg.side: scene_spans(contacts.get(leg.side, []), motion.meta.get("source_fps", motion.fps),
                                   motion.fps, motion.n_frames) for leg in mapping.legs}
    if any(spans.values()):
        displacement = mapping.root.displacement(location)
        legs, lowered = plant_feet(mapping.legs, displacement, quaternions, mapping.root.bone, spans, motion.fps)
        quaternions.update(legs)
        if lowered is not displacement:  # the hips came down for a pinned foot to reach
            location = mapping.root.location(lowered)
    return quaternions, location


def location_channels(bone: str, location: np.ndarray) -> list[Channel]:
    """The three channels of a pose bone's location."""
    path = f'pose.bones["{bpy.utils.escape_identifier(bone)}"].location'
    return [Channel(path, i, location[:, i], group=bone) for i in range(3)]


FOOT_BOUND_M = 0.0005  # metres: how far the keys of the hips or of a thigh or shin may move a foot (a standing foot stays still)


def metres_per_unit(armature) -> float:
    """Metres of the scene per armature-space unit (object scale and scene unit scale)."""
    scale = np.linalg.norm(np.array(armature.matrix_world.to_3x3()), axis=0).mean()
    return float(scale * bpy.context.scene.unit_settings.scale_length)


def leg_bounds(armature, mapping: ArmatureMapping, max_error: float) -> tuple[dict[str, float], float]:
    """Key error bounds that keep each foot within FOOT_BOUND_M of the motion's per keyed bone:
    degrees for the hips, thighs and shins (by their reach to the ankle), and the hips
    location's bound in its own units; other bones keep `max_error`."""
    metres = metres_per_unit(armature)
    reach: dict[str, float] = {}
    for leg in mapping.legs:
        for k, bone in enumerate((mapping.root.bone, *leg.bones[:2])):
            lever = np.linalg.norm(leg.heads[3] - leg.heads[k]) * metres
            reach[bone] = max(reach.get(bone, 0.0), lever)
    degrees = {bone: min(max_error, float(np.degrees(FOOT_BOUND_M / lever))) for bone, lever in reach.items()}
    location = FOOT_BOUND_M / (metres * np.linalg.norm(mapping.root.rest, axis=0).mean())
    return degrees, float(location)


def face_channels(mesh, keys: ShapeKeyMapping, face: np.ndarray, smoothing: float = 0.0) -> list[Channel]:
    """One channel per shape key of `mesh` that `keys` drives, from (T, C) face weights,
    within each key's slider range."""
    face = smooth_frames(face, smoothing) if smoothing > 0 else face
    blocks = mesh.data.shape_keys.key_blocks
    return [shape_key_channel(name, np.clip(weights, blocks[name].slider_min, blocks[name].slider_max))
            for name, weights in keys.curves(face)]


def plan_keys(scene, motion: Motion, options: BakeOptions) -> Plan:
    """The groups of channels `motion` gives the options' armature and face meshes at the
    scene's rate. Raises DiffshegError (nothing changed) when nothing can be keyed."""
    options, preset_notes = resolve_preset(motion.rig, options)
    motion = resample_motion(motion, scene_fps(scene))
    check_frames(options.start_frame, motion.n_frames)
    check_range_start(options)
    matched = map_targets(motion, options, preset_notes)

    targets: list[tuple[object, list[Group]]] = []
    unmatched_bones: list[str] = []
    notes: list[str] = []
    if matched.armature is not None:
        unmatched_bones, notes = matched.armature.unmatched, list(matched.armature.notes)
        groups = []
        quaternions, location = body_pose(matched.armature, motion, options.smoothing)
        bounds, location_bound = (leg_bounds(options.armature, matched.armature, options.max_error)
                                  if location is not None else ({}, 0.0))
        for bone, quats in quaternions.items():
            mode = options.armature.pose.bones[bone].rotation_mode
            groups.append(Group(rotation_channels(bone, mode, quats), lambda v, m=mode: rotation_error(v, m),
                                bounds.get(bone, options.max_error)))
        if location is not None:
            groups.append(Group(location_channels(matched.armature.root.bone, location), value_error,
                                location_bound))
        targets.append((options.armature, groups))
    unmatched_keys: dict[str, list[str]] = {}
    for mesh, keys in matched.faces:
        unmatched_keys[mesh.name] = keys.unmatched
        if keys.empty:
            notes.append(f"{mesh.name}: shape keys that move no vertex, skipped ({len(keys.empty)}): "
                         f"{', '.join(keys.empty)}")
        if keys.derived:
            notes.append(f"{mesh.name}: {', '.join(k for _, k in keys.derived)} driven from the ARKit weights")
        groups = [Group([channel], value_error, options.max_face_error)
                  for channel in face_channels(mesh, keys, motion.face, options.smoothing)]
        targets.append((mesh.data.shape_keys, groups))
    notes += [f"warning: {w}" for w in motion.meta.get("warnings", [])]
    keyed = frozenset(j for t in matched.armature.targets for j in t.joints) if matched.armature else frozenset()
    return Plan(motion, options, targets, unmatched_bones, unmatched_keys, notes, matched.preset_notes, keyed)


def bake_motion(scene, motion: Motion, audio_path: str | None, options: BakeOptions,
                undo: list[Undo] | None = None) -> BakeResult:
    """Key `motion` onto the options' armature and face meshes from `start_frame`, as a new
    take that keeps `motion` as its source (takes.store_source). `undo` collects the steps
    that take the change back (run in reverse: the batch keys one line after another into
    the same character).

    Raises DiffshegError (scene unchanged) when nothing can be keyed.
    """
    plan = plan_keys(scene, motion, options)
    options = plan.options
    audio_name = Path(audio_path or motion.meta.get("audio_file") or "speech").stem
    with undone_on_error("the animation", undo) as undo:
        actions, n_keys = [], 0
        number = takes.next_number(audio_name)
        take = takes.take_name(audio_name, number)
        for id_data, groups in plan.targets:
            action, slot = new_action(id_data, takes.action_name(take, id_data), undo)
            takes.mark(action, take, audio_name, number, id_data)
            channels = [ch for g in groups for ch in (g.channels if options.every_frame else with_keys(g))]
            n_keys += write_channels(action, slot, channels, options.start_frame)
            record_baked(action, action_fcurves(action, slot))
            if options.nla_strip is not None:
                takes.play_in_sequence(id_data, options.nla_strip, undo)
            actions.append(action.name)
        takes.store_source(bpy.data.actions[actions[0]],
                           takes.TakeSource(motion, str(audio_path or ""), options.start_frame))
        if options.armature is not None:
            _set_properties(options.armature, options.preset.properties_for(plan.keyed_joints), undo)
        strip, notes, replaced = _sound_and_range(scene, audio_path, options, plan.motion.n_frames, undo)
    remove_strips(scene, replaced)  # only once everything else has succeeded
    return BakeResult(take=take, preset=options.preset.name, actions=actions, n_frames=plan.motion.n_frames,
                      n_keys=n_keys, unmatched_bones=plan.unmatched_bones,
                      unmatched_shape_keys=plan.unmatched_shape_keys, sound_strip=strip,
                      preset_notes=plan.preset_notes, notes=notes + plan.notes)


def _sound_and_range(scene, audio_path: str | None, options: BakeOptions, n_frames: int,
                     undo: list[Undo]) -> tuple[str | None, list[str], list]:
    """The sound strip and the frame range, as the options ask; returns the strip's name,
    notes, and the strips an earlier run added for the same audio, for the caller to
    remove once everything else has succeeded."""
    strip, notes, replaced = None, [], []
    if options.add_sound and audio_path:
        if audio_supported():
            replaced = strips_added_for(scene, audio_path)  # an earlier run's strip of this audio
            strip = add_sound_strip(scene, audio_path, options.start_frame, undo).name
        else:
            notes.append(NO_AUDIO_NOTE)
    if options.set_frame_range:
        _set_frame_range(scene, options.start_frame, options.start_frame + n_frames - 1, undo)
    return strip, notes, replaced


def with_keys(group: Group) -> list[Channel]:
    """The group's channels with sparse keys on shared frames, within its bound on every frame."""
    values = group_values(group)
    keys = fit_keys(values, group.error(values), group.bound)
    return [replace(ch, keys=Keys(keys.frames, keys.values[:, i:i + 1], keys.slopes[:, i:i + 1]))
            for i, ch in enumerate(group.channels)]


def group_values(group: Group) -> np.ndarray:
    """(T, C) values of the group's channels."""
    return np.stack([ch.values for ch in group.channels], axis=1)


def auto_preset(layout: str, armature, face_meshes) -> tuple[Preset, str]:
    """The preset whose bone (and alias shape-key) names the targets have, and a note saying which."""
    bones = armature.data.bones.keys() if armature is not None else []
    keys = [kb.name for mesh in face_meshes if mesh.data.shape_keys is not None
            for kb in mesh.data.shape_keys.key_blocks]
    return choose_preset(layout, bones, keys)


def check_preset_fits(preset: Preset, layout: str, armature) -> None:
    """Refuse a preset that finds fewer than half of the model's joints on the armature,
    naming the preset that fits it best (a wrong preset keys a few bones and looks broken)."""
    bones = armature.data.bones.keys()
    fit = preset_fit(preset, layout, bones, [])
    total = fit.bones + fit.missing if fit is not None else 0
    if fit is not None and (2 * fit.bones >= total or fit.bones == 0):
        return  # none at all: map_armature names the bones it looked for
    fits = {name: preset_fit(load_preset(name), layout, bones, []) for name in available_presets()}
    best = max((n for n in fits if fits[n] is not None), key=lambda n: fits[n].key(), default=None)
    hint = (f"preset '{best}' finds {fits[best].bones} of {fits[best].bones + fits[best].missing}: choose it "
            "or Auto" if best and best != preset.name and fits[best].bones else
            "no preset fits it better: write one for this rig (see presets/)")
    raise DiffshegError(f"preset '{preset.name}' finds only {fit.bones if fit else 0} of the model's "
                        f"{total or 'joints'} joints on armature '{armature.name}'; {hint}")


def _set_properties(armature, properties: dict, undo: list[Undo]) -> None:
    """Custom properties a preset needs on the rig (e.g. Rigify arms switched to FK)."""
    for bone_name, props in properties.items():
        bone = armature.pose.bones.get(bone_name)
        if bone is None:
            continue
        for key, value in props.items():
            if key in bone:
                old = bone[key]
                undo.append(lambda b=bone, k=key, v=old: b.__setitem__(k, v))
                bone[key] = value


def _set_frame_range(scene, start: int, end: int, undo: list[Undo]) -> None:
    old = (scene.frame_start, scene.frame_end)

    def restore() -> None:
        scene.frame_start, scene.frame_end = old

    undo.append(restore)
    scene.frame_start, scene.frame_end = int(start), int(end)
