"""Retargeting onto real rigs with real mocap (headless bpy): the BEAT take keyed by the
add-on reproduces Blender's own BVH import; bone rolls do not change the result; presets
and shape-key names match as users name them."""

from __future__ import annotations

import numpy as np
import pytest

from addon_fixtures import (angle_between, append_face, armature_pose_matrices, bpy, build_smplx_armature,
                            build_unreal_armature, cut_speech, head_direction, import_beat_armature, import_readyplayerme,
                            mocap_motion, reset_scene, set_fps, smplx_mocap_motion, world_delta,
                            world_direction)
from addon_fixtures import exit_before_blender_teardown, rigify_blend  # noqa: F401 (fixtures)

from blender_addon.scene.bake import BakeOptions, bake_motion
from blender_addon.scene.keying import fcurves_of
from blender_addon.scene.preset import available_presets, find_name, load_preset, normalise_name
from blender_addon.scene.retarget import layout_parents, map_armature, map_shape_keys
from diffsheg_core.errors import DiffshegError
from diffsheg_core.rigs import BEAT_JOINTS


PRESETS = ("beat", "smplx", "rigify", "metahuman", "mixamo", "unreal", "readyplayerme", "vrm")


def test_presets_load_and_cover_the_beat_layout():
    assert set(PRESETS) <= set(available_presets())
    skeleton = set(layout_parents("beat"))
    for name in PRESETS:
        preset = load_preset(name)
        joints = preset.joint_map("beat")
        assert {"Spine", "Neck", "RightArm", "LeftArm", "RightForeArm", "LeftHand"} <= set(joints)
        assert set(joints) <= skeleton
        assert set(preset.joint_map("smplx")) <= set(layout_parents("smplx"))
    assert load_preset("metahuman").joint_map("beat") == load_preset("unreal").joint_map("beat")  # extends
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
    result = bake_motion(scene, motion, None, BakeOptions(every_frame=True, 
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
        bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=ob, preset=preset, add_sound=False))
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
                    BakeOptions(every_frame=True, armature=ob, preset=load_preset("mixamo"), add_sound=False))
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
    bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=smplx, preset=load_preset("smplx"), add_sound=False))
    result = bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=beat, preset=load_preset("beat"), add_sound=False))
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
    bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=rig, preset=load_preset("rigify"), add_sound=False))
    bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=beat, preset=load_preset("beat"), add_sound=False))
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
    result = bake_motion(scene, speech_motion, None, BakeOptions(every_frame=True, 
        armature=None, face_meshes=[face], preset=load_preset("beat"), start_frame=1, add_sound=False))
    assert any("move no vertex, skipped (1): jawOpen" in n for n in result.notes)
    assert any("Fcl_MTH_A" in n and "driven from the ARKit weights" in n for n in result.notes)
    curves = {fc.data_path: fc for fc in fcurves_of(face.data.shape_keys)}
    assert 'key_blocks["jawOpen"].value' not in curves
    mouth = curves['key_blocks["Fcl_MTH_A"].value']
    values = np.array([k.co[1] for k in mouth.keyframe_points])
    assert values.max() > 0.2 and 'key_blocks["Fcl_EYE_Close_L"].value' in curves
    # the vowels are VMC's: the same A and O a VRM avatar gets live, never more than one vowel
    from diffsheg_core.live.vmc import preset_weights
    from blender_addon.scene.retarget import map_shape_keys

    derived = dict(map_shape_keys(face, load_preset("beat"), speech_motion).curves(speech_motion.face))
    presets = np.array([preset_weights(f) for f in speech_motion.face])
    np.testing.assert_allclose(derived["Fcl_MTH_A"], presets[:, 2], atol=1e-12)
    np.testing.assert_allclose(derived["Fcl_MTH_O"], presets[:, 6], atol=1e-12)
    assert (derived["Fcl_MTH_A"] + derived["Fcl_MTH_O"]).max() <= 1.0 + 1e-9
    # at the jaw's peak the mouth's vertices have moved
    peak = int(mouth.keyframe_points[int(values.argmax())].co[0])
    scene.frame_set(peak)
    moved = face.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
    assert max(abs(v.co.z) for v in moved.vertices) > 0.02


def test_a_face_with_arkit_keys_ignores_its_visemes(speech_motion):
    scene = reset_scene()
    face = _viseme_face("RPMFace", {"jawOpen": True, "viseme_aa": True})
    bake_motion(scene, speech_motion, None, BakeOptions(every_frame=True, 
        armature=None, face_meshes=[face], preset=load_preset("beat"), start_frame=1, add_sound=False))
    paths = {fc.data_path for fc in fcurves_of(face.data.shape_keys)}
    assert 'key_blocks["jawOpen"].value' in paths and 'key_blocks["viseme_aa"].value' not in paths


# (Unreal bone, its child, the BEAT joints they stand for): what an arm points at
ARM_SEGMENTS = [(f"{a}_{side}", f"{b}_{side}", f"{beat}{A}", f"{beat}{B}")
                for side, beat in (("l", "Left"), ("r", "Right"))
                for a, b, A, B in (("upperarm", "lowerarm", "Arm", "ForeArm"), ("lowerarm", "hand", "ForeArm", "Hand"),
                                   ("hand", "middle_01", "Hand", "HandMiddle1"))]


def _compare_with_beat(scene, rig, beat, frames, head="head", chest=None):
    """Largest arm-direction and head-rotation differences (degrees) to the BEAT skeleton."""
    arms, heads, chests = [], [], []
    for f in frames:
        scene.frame_set(f)
        arms += [angle_between(head_direction(rig, a, b), head_direction(beat, A, B)) for a, b, A, B in ARM_SEGMENTS]
        heads.append(angle_between(world_delta(rig, head), world_delta(beat, "Head")))
        if chest:
            chests.append(angle_between(world_delta(rig, chest), world_delta(beat, "Spine3")))
    return max(arms), max(heads), max(chests, default=0.0)


@pytest.mark.parametrize("spine_bones, neck_02, arms_down", [(5, True, 0.0), (3, False, 40.0)])
def test_unreal_rig_whose_bone_axes_miss_their_children_keys_like_the_beat_skeleton(spine_bones, neck_02, arms_down):
    """An Unreal-style rig as an FBX import without automatic bone orientation makes it:
    every bone's own axis points anywhere. Rest alignment by the chain puts the arms where
    the BEAT skeleton's are; spine_01-05 share the model's spine (the chest ends up exact);
    a UE4-like rig without neck_02 gets its turn in the head, so the head does not roll."""
    scene = reset_scene(fps=15)
    beat = import_beat_armature()
    rig = build_unreal_armature(beat, spine_bones=spine_bones, neck_02=neck_02, arms_down=arms_down)
    motion = mocap_motion(frames=300)
    bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=beat, preset=load_preset("beat"), add_sound=False))
    result = bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=rig, preset=load_preset("unreal"), add_sound=False))
    assert result.unmatched_bones == []
    assert (("Neck1 (neck_02 not on the rig) passed on to head" in result.notes) == (not neck_02))
    arm, head, chest = _compare_with_beat(scene, rig, beat, range(1, 300, 23), chest=f"spine_{spine_bones:02d}")
    assert arm < 10.0 and head < 3.0 and chest < 1.0, (arm, head, chest)
    scene.frame_set(120)
    turns = [angle_between(world_delta(rig, f"spine_{k:02d}"), world_delta(rig, f"spine_{k - 1:02d}")
                           if k > 1 else np.eye(3)) for k in range(1, spine_bones + 1)]
    assert min(turns) > 0.2 * max(turns)  # the bend is spread, not all in spine_01


def test_the_old_bone_axis_alignment_would_have_crossed_the_arms():
    """The same rig keyed with the bone's own axis as its rest direction (what the rest
    alignment did before): the arms are far off, so the test above measures the fix."""
    from blender_addon.scene import retarget

    scene = reset_scene(fps=15)
    beat = import_beat_armature()
    rig = build_unreal_armature(beat)
    motion = mocap_motion(frames=60)
    bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=beat, preset=load_preset("beat"), add_sound=False))
    chained = retarget._rest_directions
    try:
        retarget._rest_directions = lambda bones, chains, axes: {
            k: (v[0], retarget._rest(bones[k])[:, 1]) for k, v in chained(bones, chains, axes).items()}
        bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=rig, preset=load_preset("unreal"), add_sound=False))
    finally:
        retarget._rest_directions = chained
    arm, _, _ = _compare_with_beat(scene, rig, beat, [1, 30, 59])
    assert arm > 30.0


def test_a_joint_missing_from_a_chain_passes_its_rotation_on():
    """SMPL-X-named rig without its elbows: each forearm rotation goes into the wrist, so the
    hands keep the orientation they have on the full rig."""
    scene = reset_scene(fps=30)
    full = build_smplx_armature(name="full")
    gap = build_smplx_armature(name="gap")
    with bpy.context.temp_override(active_object=gap):
        bpy.ops.object.mode_set(mode="EDIT")
        for side in ("left", "right"):
            bones = gap.data.edit_bones
            bones[f"{side}_wrist"].parent = bones[f"{side}_shoulder"]
            bones.remove(bones[f"{side}_elbow"])
        bpy.ops.object.mode_set(mode="OBJECT")
    motion = smplx_mocap_motion(frames=90)
    preset = load_preset("smplx")
    bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=full, preset=preset, add_sound=False))
    result = bake_motion(scene, motion, None, BakeOptions(every_frame=True, armature=gap, preset=preset, add_sound=False))
    assert "left_elbow (left_elbow not on the rig) passed on to left_wrist" in result.notes
    assert result.unmatched_bones == []
    for f in (1, 45, 90):
        scene.frame_set(f)
        for bone in ("left_wrist", "right_index2", "head"):
            assert angle_between(world_delta(gap, bone), world_delta(full, bone)) < 0.01


def test_auto_picks_the_preset_whose_names_the_rig_has(rigify_blend):
    from blender_addon.scene.preset import choose_preset

    def rig_names(names):
        return choose_preset("beat", names, [])[0].name

    reset_scene()
    beat = import_beat_armature()
    assert rig_names(beat.data.bones.keys()) == "beat"
    assert rig_names(build_unreal_armature(beat).data.bones.keys()) == "unreal"
    assert rig_names(build_smplx_armature().data.bones.keys()) == "smplx"
    rpm = import_readyplayerme()[0].data.bones.keys()  # Mixamo's skeleton, without the prefix
    assert rig_names(rpm) == "readyplayerme"
    assert rig_names([f"mixamorig:{n}" for n in rpm]) == "mixamo"
    vroid = ["J_Bip_C_Hips", "J_Bip_C_Spine", "J_Bip_C_Chest", "J_Bip_C_UpperChest", "J_Bip_C_Neck",
             "J_Bip_C_Head", "J_Bip_L_UpperArm", "J_Bip_L_LowerArm", "J_Bip_L_Hand"]
    assert rig_names(vroid) == "vrm"
    assert rig_names(["hips", "spine", "chest", "neck", "head", "leftUpperArm", "leftLowerArm", "leftHand"]) == "vrm"
    bpy.ops.wm.open_mainfile(filepath=str(rigify_blend))
    assert rig_names(bpy.data.objects["rig"].data.bones.keys()) == "rigify"
    preset, note = choose_preset("beat", [], ["Basis", "jawOpen"])
    assert preset.name == "beat" and "for the face" in note
    with pytest.raises(DiffshegError, match="no rig preset fits this rig"):
        choose_preset("beat", ["Bone", "Bone.001"], [])


def test_a_preset_may_drive_several_keys_from_one_channel(tmp_path, speech_motion):
    """also_drives: one channel keys its own shape key and the others listed (eyelashes)."""
    import json

    path = tmp_path / "lashes.json"
    path.write_text(json.dumps({"extends": "beat", "name": "lashes"}))
    with pytest.raises(DiffshegError, match="is not a preset beside this file"):
        load_preset(str(path))
    mine = tmp_path / "mine.json"
    mine.write_text(json.dumps({"name": "mine", "bones": {"beat": {"Neck": "neck"}},
                                "also_drives": {"eyeBlinkLeft": ["Lashes_Blink_L"]}}))
    scene = reset_scene()
    face = _viseme_face("CCFace", {"eyeBlinkLeft": True, "Lashes_Blink_L": True, "jawOpen": True})
    bake_motion(scene, speech_motion, None, BakeOptions(every_frame=True, 
        armature=None, face_meshes=[face], preset=load_preset(str(mine)), start_frame=1, add_sound=False))
    curves = {fc.data_path: fc for fc in fcurves_of(face.data.shape_keys)}
    blink, lashes = curves['key_blocks["eyeBlinkLeft"].value'], curves['key_blocks["Lashes_Blink_L"].value']
    assert [k.co[1] for k in blink.keyframe_points] == [k.co[1] for k in lashes.keyframe_points]
