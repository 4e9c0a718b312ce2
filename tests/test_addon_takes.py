"""Takes (issue 25, item 2) in headless Blender: generating again makes a named take the
animator can switch between; no `.001` copies, no NLA track per run, the user's Action kept."""

from __future__ import annotations

import numpy as np
import pytest

from addon_fixtures import append_face, bpy, cut_speech, import_beat_armature, reset_scene
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)

import diffsheg_core
from blender_addon.scene import takes
from blender_addon.scene.bake import BakeOptions, bake_motion
from blender_addon.scene.keying import BAKED, action_fcurves, animators_keys, fcurves_of
from blender_addon.scene.preset import load_preset


@pytest.fixture(scope="module")
def speech(tmp_path_factory):
    return cut_speech(tmp_path_factory.mktemp("speech"), seconds=3.0, name="talk.wav")


@pytest.fixture(scope="module")
def motions(speech):
    return [diffsheg_core.generate(str(speech), seed=seed, steps=5, device="cpu") for seed in range(3)]


def _keys(fc) -> list:
    co = np.empty(2 * len(fc.keyframe_points), dtype=np.float32)
    fc.keyframe_points.foreach_get("co", co)
    return co.tolist()


def _user_action(ob):
    user = bpy.data.actions.new("my_wave")
    ob.animation_data_create().action = user
    ob.pose.bones["RightArm"].rotation_mode = "XYZ"
    for f, angle in ((1, 0.0), (20, 0.8), (40, 0.0)):
        ob.pose.bones["RightArm"].rotation_euler = (0, 0, angle)
        ob.pose.bones["RightArm"].keyframe_insert("rotation_euler", frame=f)
    return user, [(fc.data_path, fc.array_index, _keys(fc)) for fc in fcurves_of(ob)]


def test_three_generations_make_three_takes_and_the_last_plays(speech, motions, tmp_path):
    scene = reset_scene(fps=24)
    ob, face = import_beat_armature(), append_face()
    user, user_keys = _user_action(ob)
    options = BakeOptions(armature=ob, face_meshes=[face], preset=load_preset("beat"), add_sound=False)
    results = [bake_motion(scene, m, str(speech), options) for m in motions]

    assert [r.take for r in results] == ["talk take 1", "talk take 2", "talk take 3"]
    assert results[2].actions == ["talk take 3", "talk take 3 (Neutral)"]
    assert ob.animation_data.action.name == "talk take 3"
    assert face.data.shape_keys.animation_data.action.name == "talk take 3 (Neutral)"
    assert takes.takes_of([ob]) == ["talk take 1", "talk take 2", "talk take 3"]
    assert takes.takes_of([face.data.shape_keys]) == takes.takes_of([ob])
    assert not [a.name for a in bpy.data.actions if ".0" in a.name]
    # the user's Action went onto the NLA once, untouched; the takes added no track
    tracks = ob.animation_data.nla_tracks
    assert [s.action.name for t in tracks for s in t.strips] == ["my_wave"]
    assert len(face.data.shape_keys.animation_data.nla_tracks) == 0
    strip = tracks[0].strips[0]
    assert [(fc.data_path, fc.array_index, _keys(fc))
            for fc in action_fcurves(user, getattr(strip, "action_slot", None))] == user_keys

    # switch back to take 1 from the panel's button: body and face
    assert bpy.ops.diffsheg.use_take(take="talk take 1") == {"FINISHED"}
    assert ob.animation_data.action.name == "talk take 1"
    assert face.data.shape_keys.animation_data.action.name == "talk take 1 (Neutral)"
    assert takes.playing(ob) == "talk take 1"
    scene.frame_set(10)
    with pytest.raises(RuntimeError, match="no take 'no such take' in this file"):
        bpy.ops.diffsheg.use_take(take="no such take")

    # takes not playing are saved with the file
    path, name = tmp_path / "takes.blend", ob.name
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    ob = bpy.data.objects[name]
    assert takes.takes_of([ob]) == ["talk take 1", "talk take 2", "talk take 3"]
    assert takes.playing(ob) == "talk take 1"
    assert bpy.ops.diffsheg.use_take(take="talk take 2") == {"FINISHED"}
    assert ob.animation_data.action.name == "talk take 2"


def _animators(target) -> set:
    """(data path, index, frame) of the keys of the Action `target` plays that are the animator's."""
    action, slot = takes.playing_action(target)
    fcurves = action_fcurves(action, slot)
    return {(fc.data_path, fc.array_index, float(fc.keyframe_points[int(i)].co[0]))
            for fc, found in zip(fcurves, animators_keys(action, fcurves)) for i in np.flatnonzero(found)}


def test_what_a_take_baked_is_saved_with_the_file(speech, motions, tmp_path):
    """The record of the keys a take baked (keying.record_baked) is kept in the .blend: after
    reopening, every key of the take is still the take's, and a generated key whose value the
    animator changed (its type stays GENERATED) is the animator's, with the rest of that
    rotation's keys at its frame (issue 40). A take saved before the record: by type alone."""
    scene = reset_scene(fps=24)
    ob, face = import_beat_armature(), append_face()
    options = BakeOptions(armature=ob, face_meshes=[face], preset=load_preset("beat"), add_sound=False)
    bake_motion(scene, motions[0], str(speech), options)
    path, names = tmp_path / "baked.blend", (ob.name, face.name)
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    ob, face = (bpy.data.objects[n] for n in names)
    assert _animators(ob) == set() and _animators(face.data.shape_keys) == set()
    arm = 'pose.bones["RightArm"].rotation_euler'
    key = next(fc for fc in fcurves_of(ob) if (fc.data_path, fc.array_index) == (arm, 0)).keyframe_points[1]
    key.co[1] += 0.3
    assert key.type == "GENERATED" and _animators(ob) == {(arm, i, key.co[0]) for i in range(3)}
    del ob.animation_data.action[BAKED]
    assert _animators(ob) == set()


def test_a_take_number_skips_names_already_used(speech, motions):
    """An Action the user named like a take is not overwritten nor copied as `.001`."""
    scene = reset_scene(fps=24)
    ob = import_beat_armature()
    mine = bpy.data.actions.new("talk take 1")
    result = bake_motion(scene, motions[0], str(speech), BakeOptions(armature=ob, preset=load_preset("beat"),
                                                                    add_sound=False))
    assert result.take == "talk take 2" and mine.name == "talk take 1" and not takes.is_take(mine)


def test_report_line_and_text_and_sync_to_audio(speech):
    """The Ready Player Me avatar: one line of at most 120 characters, the details (skipped
    shape keys grouped per mesh) in the "DiffSHEG report" Text; playback syncs to the audio."""
    from addon_fixtures import HAS_AUDIO, import_readyplayerme, report_text

    scene = reset_scene(fps=24)
    rig, faces = import_readyplayerme()
    s = scene.diffsheg
    s.audio_path, s.armature, s.set_steps, s.steps = str(speech), rig, True, 5
    for face in faces:
        s.face_meshes.add().object = face
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    assert len(s.last_report) <= 120 and s.last_report.startswith("talk take 1: 72 frames")
    assert "preset readyplayerme" in s.last_report and "see DiffSHEG report" in s.last_report
    text = report_text()
    assert "preset Auto chose 'readyplayerme'" in text
    skipped = [line for line in text.splitlines() if "move no vertex" in line]
    assert skipped and all(line.count("Wolf3D_") == 1 for line in skipped)  # one line per mesh
    # the teeth's keys that move nothing are said once, as such, not also as missing keys
    assert not [line for line in text.splitlines() if "Wolf3D_Teeth" in line and "without a shape key" in line]
    assert bpy.ops.diffsheg.show_report() == {"FINISHED"}
    if HAS_AUDIO:
        assert scene.sync_mode == "AUDIO_SYNC"


def test_a_preset_that_finds_few_joints_is_refused_naming_the_best(speech, motions):
    from addon_fixtures import import_readyplayerme

    from diffsheg_core.errors import DiffshegError

    scene = reset_scene(fps=24)
    rig, _ = import_readyplayerme()
    before = sorted(bpy.data.actions.keys())
    with pytest.raises(DiffshegError, match=r"preset 'rigify' finds only \d+ of the model's \d+ joints on "
                                            r"armature 'Armature'; preset '(readyplayerme|mixamo)' finds"):
        bake_motion(scene, motions[0], str(speech), BakeOptions(armature=rig, preset=load_preset("rigify"),
                                                                add_sound=False))
    assert sorted(bpy.data.actions.keys()) == before
