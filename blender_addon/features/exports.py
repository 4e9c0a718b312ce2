"""Engine-ready exports of the take playing: FBX for Unreal and Unity, glTF binary.

Each export writes the armature's animation and the face meshes' shape-key animation
over the scene's frame range (bake_motion sets it to the take), sampled on every frame
and not simplified (Blender's FBX simplification moves generated takes up to 0.5 degree).
Only the armature, the face meshes and the meshes parented to the armature are written:
no lights (bpy 5.0.1's own FBX importer fails on files with one), no cameras. The FBX
keeps the scene's frame times (a take on frames 1-72 at 24 fps spans 1/24 s to 3 s);
engines import the take's own span.

Every file is written whole or not at all: the exporter writes a temporary file in the
same folder, which then replaces the target (os.replace, atomic on one file system). On
any failure neither is left and a DiffshegError says what went wrong. The user's
selection, active object, mode and current frame are put back as they were.
Call from Blender's main thread.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Callable, Iterator

import bpy

from diffsheg_core.errors import DiffshegError

ENGINES = ("unreal", "unity")

# Transform settings of Blender's FBX exporter per engine (bpy.ops.export_scene.fbx).
FBX_ENGINE_SETTINGS: dict[str, dict] = {
    # Unreal is Z up and measures in centimetres. The file is written from a copy of the
    # character in centimetres (its units and the armature's object scale folded into its
    # data) in a scene measured in centimetres (unit scale 0.01, `_in_centimetres`): "All
    # Local" with the unit applied then scales by 1,
    # so the armature's root node has scale 1 and the bones, their animation and the
    # meshes are in centimetres at FBX scale 1.0. (Written from the character at
    # Blender's scale, "All Local" puts the factor 100 on the root node instead, which
    # Unreal keeps on the skeleton's root; "FBX All" writes metres, scale 100 in the file,
    # which Unreal's Convert Scene Unit again turns into a root scale.) The axes Y forward
    # / Z up are no conversion at all: the file keeps Blender's Z-up frame, Unreal's own
    # up axis; Unreal's importer mirrors Y into its left-handed frame, so a character
    # facing Blender's -Y faces +Y as the UE mannequin does. Import in Unreal with the
    # defaults: Convert Scene changes nothing on such a file, Convert Scene Unit off,
    # Import Uniform Scale 1.
    "unreal": dict(axis_forward="Y", axis_up="Z", apply_unit_scale=True,
                   apply_scale_options="FBX_SCALE_NONE", global_scale=1.0),
    # Unity is Y up, +Z forward, and measures in metres. "FBX All" puts the unit in the
    # file's scale (UnitScaleFactor 100: metres), so with Unity's Convert Units (on by
    # default) objects arrive at scale 1 rather than 100. -Z forward / Y up turns Blender's
    # Z-up frame into Unity's Y-up one; a character facing Blender's -Y then faces Unity's
    # +Z. "Apply Transform" (bake_space_transform) stays off: Blender marks it experimental
    # and broken with armatures and animation; the cost is a root rotation of -90 degrees
    # about X that Unity shows on the imported objects, not on what they look like.
    "unity": dict(axis_forward="-Z", axis_up="Y", apply_unit_scale=True,
                  apply_scale_options="FBX_SCALE_ALL", global_scale=1.0),
}

FBX_COMMON_SETTINGS = dict(
    use_selection=True, object_types={"ARMATURE", "MESH"},
    use_space_transform=True, bake_space_transform=False,
    use_mesh_modifiers=False,          # applying modifiers would drop the shape keys
    mesh_smooth_type="FACE",           # smoothing groups: Unreal warns when a file has none
    use_tspace=False, use_custom_props=False,
    add_leaf_bones=False,              # the extra "_end" bones would only add joints to the engine's skeleton
    primary_bone_axis="Y", secondary_bone_axis="X", armature_nodetype="NULL",
    use_armature_deform_only=False,
    bake_anim=True, bake_anim_use_all_bones=True,
    bake_anim_use_nla_strips=False,    # one animation: what plays in the scene's range
    bake_anim_use_all_actions=False,   # not every take in the file
    bake_anim_force_startend_keying=True, bake_anim_step=1.0,
    bake_anim_simplify_factor=0.0,     # every frame as keyed, not simplified
    path_mode="AUTO", embed_textures=False, batch_mode="OFF", use_metadata=True,
)

GLB_SETTINGS = dict(
    export_format="GLB", use_selection=True, export_yup=True, export_apply=False,
    export_skins=True, export_morph=True, export_morph_normal=True,
    export_animations=True, export_morph_animation=True,
    export_animation_mode="SCENE",      # the scene as it plays over its frame range: one animation
    export_anim_scene_split_object=False,
    export_frame_range=True, export_force_sampling=True, export_frame_step=1,
    export_optimize_animation_size=False,
    export_anim_single_armature=True, export_reset_pose_bones=True,
    export_def_bones=False, export_leaf_bone=False,
)


def export_fbx(path, armature, face_meshes, engine: str) -> Path:
    """Write the take playing on `armature` and `face_meshes` as an FBX for `engine`
    ("unreal" or "unity"; see FBX_ENGINE_SETTINGS for the scale and axes of each)."""
    if engine not in ENGINES:
        raise DiffshegError(f"unknown engine {engine!r}: choose one of {', '.join(ENGINES)}")
    settings = {**FBX_COMMON_SETTINGS, **FBX_ENGINE_SETTINGS[engine]}

    def write(tmp: Path):
        if engine != "unreal":
            return bpy.ops.export_scene.fbx(filepath=str(tmp), check_existing=False, **settings)
        with _in_centimetres(bpy.context.scene, export_objects(armature, face_meshes)) as (scene, copies):
            view_layer = scene.view_layers[0]
            for copy in copies:
                copy.select_set(True, view_layer=view_layer)
            view_layer.objects.active = copies[0]
            with bpy.context.temp_override(scene=scene, view_layer=view_layer, selected_objects=copies,
                                           active_object=copies[0], object=copies[0]):
                return bpy.ops.export_scene.fbx(filepath=str(tmp), check_existing=False, **settings)

    return _export(Path(path), ".fbx", armature, face_meshes, write)


def export_glb(path, armature, face_meshes) -> Path:
    """Write the take playing as glTF binary (.glb): the skinned meshes, the armature's
    animation and the shape keys' weights as morph-target weight animation, one glTF
    animation over the scene's frame range (glTF is Y up and in metres by definition)."""
    return _export(Path(path), ".glb", armature, face_meshes,
                   lambda tmp: bpy.ops.export_scene.gltf(filepath=str(tmp), check_existing=False, **GLB_SETTINGS))


# ---------------------------------------------------------------- shared steps

def _export(path: Path, suffix: str, armature, face_meshes, write: Callable[[Path], object]) -> Path:
    """Check the targets and the path, then write atomically with the objects selected."""
    objects = export_objects(armature, face_meshes)
    _check_target(path)
    scene = bpy.context.scene
    with _scene_kept(scene), _selected(objects):
        _write_atomically(path, suffix, write)
    return path


def export_objects(armature, face_meshes) -> list:
    """The armature, the face meshes and every mesh parented to the armature, once each."""
    if armature is None:
        raise DiffshegError("no armature to export: choose the character's armature")
    if getattr(armature, "type", None) != "ARMATURE":
        raise DiffshegError(f"'{getattr(armature, 'name', armature)}' is not an armature: "
                            "choose the character's armature to export")
    objects = [armature]
    for ob in [*face_meshes, *armature.children_recursive]:
        if ob.type == "MESH" and ob not in objects:
            objects.append(ob)
    for ob in face_meshes:
        if ob.type != "MESH":
            raise DiffshegError(f"'{ob.name}' is not a mesh: face meshes must be meshes with shape keys")
    view_layer = bpy.context.view_layer
    missing = [ob.name for ob in objects if view_layer.objects.get(ob.name) != ob]
    if missing:
        raise DiffshegError(f"{', '.join(missing)} not in the view layer '{view_layer.name}': "
                            "link them to the scene (or include their collection) to export them")
    return objects


def _check_target(path: Path) -> None:
    """Fail early, naming the problem, where writing cannot succeed."""
    if path.is_dir():
        raise DiffshegError(f"{path} is a folder: give a file name to export to")
    folder = path.parent
    if not folder.is_dir():
        raise DiffshegError(f"the folder {folder} does not exist: create it or export elsewhere")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise DiffshegError(f"cannot write in {folder}: choose a folder you may write to")


def _write_atomically(path: Path, suffix: str, write: Callable[[Path], object]) -> None:
    """`write(tmp)` to a new temporary file beside `path`, then os.replace; on failure
    no temporary is left and `path` is untouched."""
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".partial{suffix}", dir=path.parent)
    except OSError as e:
        raise DiffshegError(f"cannot write in {path.parent} ({e.strerror}): choose a folder you may write to") from e
    os.close(fd)
    tmp = Path(name)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # as a file made by open(): mkstemp makes it private
        try:
            result = write(tmp)
        except DiffshegError:
            raise
        except Exception as e:  # bpy.ops raise RuntimeError with the exporter's report
            raise DiffshegError(f"exporting {path.name} failed: {_last_line(e)}") from e
        if result is not None and "FINISHED" not in result:
            raise DiffshegError(f"exporting {path.name} was cancelled by Blender's exporter (see its report)")
        if not tmp.is_file() or tmp.stat().st_size == 0:
            raise DiffshegError(f"exporting {path.name} wrote nothing: see Blender's report for why")
        try:
            os.replace(tmp, path)
        except OSError as e:
            raise DiffshegError(f"cannot put {path} in place ({e.strerror}): "
                                "remove what is there or choose another name") from e
    finally:
        tmp.unlink(missing_ok=True)


def _last_line(error: Exception) -> str:
    """The exporter's own message: the last line of a report or traceback."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else type(error).__name__


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def _selected(objects: list) -> Iterator[None]:
    """Exactly `objects` selected, the armature active, in Object mode; the user's
    selection, active object and mode back afterwards (also after an error)."""
    view_layer = bpy.context.view_layer
    active = view_layer.objects.active
    mode = active.mode if active is not None else "OBJECT"
    before = [ob for ob in view_layer.objects if ob.select_get()]
    if mode != "OBJECT" and bpy.ops.object.mode_set.poll():
        bpy.ops.object.mode_set(mode="OBJECT")
    try:
        for ob in before:
            ob.select_set(False)
        for ob in objects:
            ob.select_set(True)
        view_layer.objects.active = objects[0]
        yield
    finally:
        for ob in view_layer.objects:
            ob.select_set(ob in before)
        view_layer.objects.active = active
        if active is not None and active.mode != mode and bpy.ops.object.mode_set.poll():
            bpy.ops.object.mode_set(mode=mode)


CENTIMETRE = 0.01  # Unreal's unit, in metres


@contextlib.contextmanager
def _in_centimetres(scene, objects: list) -> Iterator[tuple]:
    """A scene of its own measured in centimetres (unit scale 0.01) and in it copies of
    `objects` (the armature first) in centimetres: their data scaled by the centimetres in
    one of `scene`'s units (its unit scale over 0.01), and the armature's by its world
    scale too, so the armature copy's root has scale 1 whatever the character's units or
    object scale. The copies have the originals' names and the animation `scene` plays
    over its frame range, keyed on every frame: the armature's bones from the evaluated
    pose (constraints, drivers and NLA included), every copy's object transform from the
    original's (its world motion where its parent is not exported), the meshes' shape keys
    playing as the originals' do. Meanwhile the originals (and the scene) carry other
    names; afterwards the copies, their data and the scene are removed and every name is
    back, so the user's file is as it was."""
    from mathutils import Matrix

    factor = scene.unit_settings.scale_length / CENTIMETRE
    up, down = Matrix.Scale(factor, 4), Matrix.Scale(1 / factor, 4)
    armature = objects[0]
    size = _uniform_scale(armature)
    temp = bpy.data.scenes.new(scene.name)
    temp.unit_settings.system, temp.unit_settings.scale_length = "METRIC", CENTIMETRE
    temp.render.fps, temp.render.fps_base = scene.render.fps, scene.render.fps_base
    temp.frame_start, temp.frame_end = scene.frame_start, scene.frame_end
    temp.frame_current = scene.frame_current
    made, renamed = [temp], []
    try:
        copies = {}
        for ob in objects:
            copy = ob.copy()
            copy.data = ob.data.copy()
            made += [copy, copy.data]
            if getattr(copy.data, "shape_keys", None) is not None:
                made.append(copy.data.shape_keys)
            copy.animation_data_clear()
            copy.data.animation_data_clear()
            _clear_constraints(copy)
            copy.rotation_mode = "QUATERNION"
            temp.collection.objects.link(copy)
            copies[ob] = copy
        for ob, copy in copies.items():
            if ob.parent is not None and ob.parent not in copies:
                copy.parent = None
            elif ob.parent is not None:
                copy.parent = copies[ob.parent]
                # under the armature copy, whose data carries the armature's scale
                unscaled = Matrix.Scale(size, 4) if ob.parent is armature else Matrix()
                copy.matrix_parent_inverse = unscaled @ up @ ob.matrix_parent_inverse @ down
            for modifier in copy.modifiers:
                if modifier.type == "ARMATURE" and modifier.object in copies:
                    modifier.object = copies[modifier.object]
            if ob.type == "MESH":
                copy.data.transform(up, shape_keys=True)
            else:
                copy.data.transform(up @ Matrix.Scale(size, 4))
        made += _bake(scene, copies, up, down, size)
        for ob, copy in copies.items():  # the copies go by the originals' names
            for original, duplicate in ((ob, copy), (ob.data, copy.data)):
                name = original.name
                renamed.append((original, name))
                original.name = f"{name}.diffsheg-export"
                duplicate.name = name
        renamed.append((scene, scene.name))
        scene.name, temp.name = f"{scene.name}.diffsheg-export", renamed[-1][1]
        yield temp, list(copies.values())
    finally:
        bpy.data.batch_remove(made)
        for original, name in renamed:
            original.name = name


def _uniform_scale(ob) -> float:
    """`ob`'s world scale, one number: the Unreal copy folds it into the armature's data."""
    scale = ob.matrix_world.to_scale()
    if ob.matrix_world.is_negative or max(scale) > min(scale) * (1 + 1e-4):
        raise DiffshegError(f"'{ob.name}' is scaled unevenly or mirrored (world scale "
                            f"{', '.join(f'{s:g}' for s in scale)}): apply its scale (Object > Apply > Scale) "
                            "or give it one positive scale before exporting for Unreal")
    return sum(scale) / 3


def _bake(scene, copies: dict, up, down, size: float) -> list:
    """Key every copy of `copies` (original -> copy, the armature first) on every frame of
    the scene's range as its original is there: the object transform (its local one under
    an exported parent, else its world one; `up` @ matrix @ `down` in the copy's units, the
    armature's without its world scale `size`) and the armature copy's pose bones (their
    local transforms, constraints and drivers applied, in units of the armature's data:
    `size` x `up`). Location, quaternion and scale keys; returns the new Actions."""
    import numpy as np
    from mathutils import Matrix

    from ..scene.keying import new_action, write_channels

    frames = range(scene.frame_start, scene.frame_end + 1)
    armature = next(iter(copies))
    bones = list(armature.pose.bones)
    data_up = up @ Matrix.Scale(size, 4)
    data_down = Matrix.Scale(1 / size, 4) @ down
    unscale = Matrix.Scale(1 / size, 4)
    # (frames, channels owners, 10): location 3, quaternion 4, scale 3; the objects first
    samples = np.empty((len(frames), len(copies) + len(bones), 10))
    for f, frame in enumerate(frames):
        scene.frame_set(frame)
        matrices = [up @ ob.matrix_basis @ down if copy.parent else
                    up @ ob.matrix_world @ down @ (unscale if ob is armature else Matrix())
                    for ob, copy in copies.items()]
        matrices += [data_up @ armature.convert_space(pose_bone=bone, matrix=bone.matrix, from_space="POSE",
                                                      to_space="LOCAL") @ data_down for bone in bones]
        for i, matrix in enumerate(matrices):
            location, rotation, scale = matrix.decompose()
            quaternion = np.array(rotation)
            if f and quaternion @ samples[f - 1, i, 3:7] < 0:
                quaternion = -quaternion  # the last key's hemisphere: no flip between frames
            samples[f, i] = (*location, *quaternion, *scale)
    for bone in copies[armature].pose.bones:
        _clear_constraints(bone)
        bone.rotation_mode = "QUATERNION"
    actions = []
    for i, (ob, copy) in enumerate(copies.items()):
        channels = _transform_channels("", samples[:, i], "Object Transforms")
        if ob is armature:
            for b, bone in enumerate(bones):
                base = f'pose.bones["{bpy.utils.escape_identifier(bone.name)}"].'
                channels += _transform_channels(base, samples[:, len(copies) + b], bone.name)
        action, slot = new_action(copy, f"{ob.name} in centimetres", [])
        write_channels(action, slot, channels, frames.start)
        actions.append(action)
    return actions


def _transform_channels(base: str, samples, group: str) -> list:
    """Location, quaternion and scale channels at `base` of (frames, 10) `samples`."""
    from ..scene.keying import Channel

    return [Channel(f"{base}{path}", i, samples[:, first + i], group)
            for path, first, width in (("location", 0, 3), ("rotation_quaternion", 3, 4), ("scale", 7, 3))
            for i in range(width)]


def _clear_constraints(owner) -> None:
    """No constraints on `owner` (an object or pose bone): its motion is baked."""
    for constraint in list(owner.constraints):
        owner.constraints.remove(constraint)


@contextlib.contextmanager
def _scene_kept(scene) -> Iterator[None]:
    """The current frame as it was: the exporters step through the frame range."""
    frame, subframe = scene.frame_current, scene.frame_subframe
    try:
        yield
    finally:
        scene.frame_set(frame, subframe=subframe)
