"""Retargeting onto real rigs with real mocap (headless bpy): the BEAT take keyed by the
add-on reproduces Blender's own BVH import; bone rolls do not change the result; presets
and shape-key names match as users name them."""

from __future__ import annotations

import numpy as np
import pytest

from addon_fixtures import (append_face, armature_pose_matrices, bpy, build_smplx_armature, cut_speech,
                            import_beat_armature, mocap_motion, reset_scene, set_fps,
                            smplx_mocap_motion, world_direction)
from addon_fixtures import exit_before_blender_teardown, rigify_blend  # noqa: F401 (fixtures)

from blender_addon.bake import BakeOptions, bake_motion
from blender_addon.keying import fcurves_of
from blender_addon.preset import available_presets, find_name, load_preset, normalise_name
from blender_addon.retarget import map_armature, map_shape_keys
from diffsheg_core.errors import DiffshegError
from diffsheg_core.rigs import BEAT_JOINTS


def test_presets_load_and_cover_the_beat_layout():
    assert {"beat", "smplx", "rigify", "metahuman", "mixamo"} <= set(available_presets())
    for name in ("beat", "smplx", "rigify", "metahuman", "mixamo"):
        preset = load_preset(name)
        joints = preset.joint_map("beat")
        assert {"Spine", "Neck", "RightArm", "LeftArm", "RightForeArm", "LeftHand"} <= set(joints)
        assert set(joints) <= set(BEAT_JOINTS)
    with pytest.raises(DiffshegError, match="no rig preset 'nope'"):
        load_preset("nope")


def test_names_match_across_tools():
    keys = ["Basis", "JawOpen", "A14_Eye_Blink_Left", "eye_blink_right", "mouthSmile_L"]
    assert find_name(["jawOpen"], keys) == "JawOpen"
    assert find_name(["eyeBlinkLeft"], keys) == "A14_Eye_Blink_Left"
    assert find_name(["eyeBlinkRight"], keys) == "eye_blink_right"
    assert find_name(["mouthSmileLeft", "mouthSmile_L"], keys) == "mouthSmile_L"
    assert find_name(["mixamorig:Hips"], ["mixamorig1:Hips"]) == "mixamorig1:Hips"
    assert normalise_name("A25_Jaw_Open") == normalise_name("jawOpen") == "jawopen"


def test_bvh_mocap_keyed_by_the_addon_matches_blenders_bvh_import():
    """The beat preset on the imported BEAT skeleton: our conversion of the model's
    axis-angle into bone-local rotations gives exactly the importer's pose."""
    scene = reset_scene(fps=15)
    ob = import_beat_armature(animated=True)
    frames = [2, 40, 300, 900]
    reference = []
    for f in frames:
        scene.frame_set(f)
        reference.append(armature_pose_matrices(ob, list(BEAT_JOINTS)))
    motion = mocap_motion()
    result = bake_motion(scene, motion, None, BakeOptions(
        armature=ob, preset=load_preset("beat"), start_frame=2, add_sound=False))
    assert result.unmatched_bones == []
    assert result.n_frames == motion.n_frames
    for f, ref in zip(frames, reference):
        scene.frame_set(f)
        ours = armature_pose_matrices(ob, list(BEAT_JOINTS))
        assert np.abs(ours - ref).max() < 1e-4, f"frame {f}"


def _world_deltas(ob, bones):
    """Per bone: posed orientation times rest orientation inverse (independent of roll)."""
    out = []
    for b in bones:
        pose = np.array(ob.pose.bones[b].matrix.to_3x3())
        rest = np.array(ob.data.bones[b].matrix_local.to_3x3())
        out.append(pose @ np.linalg.inv(rest))
    return np.array(out)


def test_bone_rolls_and_rotation_modes_do_not_change_the_motion():
    scene = reset_scene(fps=25)
    plain = build_smplx_armature(roll_seed=0, name="plain")
    rolled = build_smplx_armature(roll_seed=7, name="rolled")
    for bone, mode in (("left_elbow", "AXIS_ANGLE"), ("spine1", "YXZ"), ("right_wrist", "ZXY"), ("head", "XYZ")):
        rolled.pose.bones[bone].rotation_mode = mode
    rolls = [rolled.data.bones[b].matrix_local.to_3x3() for b in ("left_elbow", "spine2")]
    assert any(abs(r[0][0] - 1.0) > 0.1 for r in rolls)  # rolls really differ
    motion = mocap_motion(frames=120)
    preset = load_preset("smplx")
    for ob in (plain, rolled):
        bake_motion(scene, motion, None, BakeOptions(armature=ob, preset=preset, add_sound=False))
    bones = ["spine1", "neck", "head", "left_shoulder", "left_elbow", "right_wrist", "right_index2", "jaw"]
    moved = False
    for f in (10, 60, 150):
        scene.frame_set(f)
        a, b = _world_deltas(plain, bones), _world_deltas(rolled, bones)
        assert np.abs(a - b).max() < 1e-4
        moved |= np.abs(a - np.eye(3)).max() > 0.05
    assert moved


def test_rig_matching_nothing_is_a_clear_error_and_leaves_no_action():
    scene = reset_scene()
    bpy.ops.object.armature_add()
    ob = bpy.context.object
    before = set(bpy.data.actions.keys())
    with pytest.raises(DiffshegError, match="none of the bones of preset 'mixamo'"):
        bake_motion(scene, mocap_motion(frames=30), None,
                    BakeOptions(armature=ob, preset=load_preset("mixamo"), add_sound=False))
    assert set(bpy.data.actions.keys()) == before
    assert ob.animation_data is None


def test_shape_keys_match_renamed_arkit_keys_and_report_the_rest():
    reset_scene()
    face = append_face()
    blocks = face.data.shape_keys.key_blocks
    blocks["jawOpen"].name = "A25_Jaw_Open"
    blocks["eyeBlinkLeft"].name = "EyeBlink_Left"
    blocks["mouthSmileLeft"].name = "Smile"
    mapping = map_shape_keys(face, load_preset("beat"), mocap_motion(frames=10))
    names = dict((i, n) for i, n in mapping.pairs)
    from diffsheg_core.rigs import ARKIT51
    assert names[ARKIT51.index("jawOpen")] == "A25_Jaw_Open"
    assert names[ARKIT51.index("eyeBlinkLeft")] == "EyeBlink_Left"
    assert mapping.unmatched == ["mouthSmileLeft"]
    assert len(mapping.pairs) == 50


def test_unmatched_bones_are_listed():
    reset_scene()
    ob = build_smplx_armature()
    mapping = map_armature(ob, load_preset("smplx"), mocap_motion(frames=5))
    assert {t.bone for t in mapping.targets} >= {"spine1", "left_elbow", "right_thumb3", "jaw"}
    assert mapping.unmatched == []
    with bpy.context.temp_override(active_object=ob):
        bpy.ops.object.mode_set(mode="EDIT")
        ob.data.edit_bones.remove(ob.data.edit_bones["left_pinky3"])
        bpy.ops.object.mode_set(mode="OBJECT")
    mapping = map_armature(ob, load_preset("smplx"), mocap_motion(frames=5))
    assert mapping.unmatched == ["LeftHandPinky3 -> left_pinky3"]


def test_smplx_layout_motion_keys_smplx_and_beat_rigs_alike():
    """Real SMPL-X motion (BEAT2 take) on the SMPL-X-named rig and, through the beat
    preset's smplx section, on the BEAT skeleton: the forearms point the same way."""
    scene = reset_scene(fps=30)
    smplx = build_smplx_armature(roll_seed=2)
    beat = import_beat_armature()
    motion = smplx_mocap_motion(frames=90)
    bake_motion(scene, motion, None, BakeOptions(armature=smplx, preset=load_preset("smplx"), add_sound=False))
    result = bake_motion(scene, motion, None, BakeOptions(armature=beat, preset=load_preset("beat"), add_sound=False))
    assert result.unmatched_bones == []
    for f in (1, 45, 90):
        scene.frame_set(f)
        for a, b in (("left_elbow", "LeftForeArm"), ("right_shoulder", "RightArm")):
            assert world_direction(smplx, a) @ world_direction(beat, b) > np.cos(np.radians(5))


def test_same_motion_looks_the_same_on_rigify_and_beat(rigify_blend):
    """The Rigify preset keys FK controls; the deform bones the mesh follows then point
    where the BEAT skeleton's bones point (arms in T-pose-to-rest alignment)."""
    bpy.ops.wm.open_mainfile(filepath=str(rigify_blend))
    scene = bpy.context.scene
    set_fps(scene, 15)
    rig = bpy.data.objects["rig"]
    beat = import_beat_armature()
    motion = mocap_motion(frames=200)
    bake_motion(scene, motion, None, BakeOptions(armature=rig, preset=load_preset("rigify"), add_sound=False))
    bake_motion(scene, motion, None, BakeOptions(armature=beat, preset=load_preset("beat"), add_sound=False))
    pairs = [("DEF-upper_arm.L", "LeftArm"), ("DEF-forearm.L", "LeftForeArm"),
             ("DEF-upper_arm.R", "RightArm"), ("DEF-forearm.R", "RightForeArm")]
    for f in range(1, 200, 25):
        scene.frame_set(f)
        for a, b in pairs:
            assert world_direction(rig, a) @ world_direction(beat, b) > np.cos(np.radians(1)), (f, a)


@pytest.fixture(scope="module")
def speech_motion(tmp_path_factory):
    import diffsheg_core

    return diffsheg_core.generate(str(cut_speech(tmp_path_factory.mktemp("speech"), seconds=3.0)), steps=5)


def _viseme_face(name: str, keys: dict[str, bool]):
    """A mesh with a Basis and the given shape keys; True: the key moves vertices."""
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=4, y_subdivisions=4)
    ob = bpy.context.object
    ob.name = name
    ob.shape_key_add(name="Basis", from_mix=False)
    for key, moves in keys.items():
        block = ob.shape_key_add(name=key, from_mix=False)
        if moves:
            for point in block.data[:5]:
                point.co.z += 0.1
    return ob


def test_a_vroid_style_face_talks_and_blinks_through_its_own_keys(speech_motion):
    """jawOpen that moves nothing is skipped; the mouth and eye-close keys are driven from
    the ARKit weights instead, and the report says so."""
    scene = reset_scene()
    face = _viseme_face("VRoidFace", {"jawOpen": False, "Fcl_MTH_A": True, "Fcl_MTH_O": True,
                                      "Fcl_EYE_Close_L": True, "Fcl_EYE_Close_R": True})
    result = bake_motion(scene, speech_motion, None, BakeOptions(
        armature=None, face_meshes=[face], preset=load_preset("beat"), start_frame=1, add_sound=False))
    assert any("jawOpen moves no vertex" in n for n in result.notes)
    assert any("Fcl_MTH_A" in n and "driven from the ARKit weights" in n for n in result.notes)
    curves = {fc.data_path: fc for fc in fcurves_of(face.data.shape_keys)}
    assert 'key_blocks["jawOpen"].value' not in curves
    mouth = curves['key_blocks["Fcl_MTH_A"].value']
    values = np.array([k.co[1] for k in mouth.keyframe_points])
    assert values.max() > 0.2 and 'key_blocks["Fcl_EYE_Close_L"].value' in curves
    # at the jaw's peak the mouth's vertices have moved
    peak = int(mouth.keyframe_points[int(values.argmax())].co[0])
    scene.frame_set(peak)
    moved = face.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
    assert max(abs(v.co.z) for v in moved.vertices) > 0.02


def test_a_face_with_arkit_keys_ignores_its_visemes(speech_motion):
    scene = reset_scene()
    face = _viseme_face("RPMFace", {"jawOpen": True, "viseme_aa": True})
    bake_motion(scene, speech_motion, None, BakeOptions(
        armature=None, face_meshes=[face], preset=load_preset("beat"), start_frame=1, add_sound=False))
    paths = {fc.data_path for fc in fcurves_of(face.data.shape_keys)}
    assert 'key_blocks["jawOpen"].value' in paths and 'key_blocks["viseme_aa"].value' not in paths
