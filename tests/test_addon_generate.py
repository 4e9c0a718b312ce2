"""End to end in headless Blender: real speech -> diffsheg_core.generate -> keys on real
rigs (BEAT BVH import, SMPL-X-named, Rigify-generated) and the real ARKit face mesh."""

from __future__ import annotations

import os
import sys
import threading
from dataclasses import replace

import numpy as np
import pytest

from addon_fixtures import (HAS_AUDIO, MISNAMED_MP3, append_face, build_smplx_armature, bpy, cut_speech,
                            import_beat_armature, report_text, reset_scene, scene_state, set_fps,
                            world_direction)
from addon_fixtures import exit_before_blender_teardown, rigify_blend  # noqa: F401 (fixtures)

import diffsheg_core
from blender_addon.scene.bake import BakeOptions, bake_motion
from blender_addon.scene.keying import action_fcurves, fcurves_of
from blender_addon.features.generate import GenerationJob, Request
from blender_addon.scene.preset import load_preset
from blender_addon.scene.sound import sound_strips
from diffsheg_core.checkpoints import load_model
from diffsheg_core.errors import Cancelled
from diffsheg_core.settings import GenerateSettings

STEPS = 5


@pytest.fixture(scope="module")
def speech(tmp_path_factory):
    return cut_speech(tmp_path_factory.mktemp("speech"), seconds=3.0)


@pytest.fixture(scope="module")
def speech_motion(speech):
    return diffsheg_core.generate(str(speech), steps=STEPS, device="cpu")


def _configure(scene, speech, armature, preset, face=None, start=1):
    s = scene.diffsheg
    s.audio_path = str(speech)
    s.armature = armature
    s.preset = preset
    s.set_steps, s.steps = True, STEPS
    s.device = "CPU"
    s.start_at_scene_start = False
    s.start_frame = start
    if face is not None:
        s.face_meshes.add().object = face
    return s


def _keys(fc) -> np.ndarray:
    co = np.empty(2 * len(fc.keyframe_points), dtype=np.float32)
    fc.keyframe_points.foreach_get("co", co)
    return co.reshape(-1, 2)


def _check_frames(frames: np.ndarray, start: int, n_frames: int) -> None:
    """Sparse keys on whole frames from the first frame of the motion to its last."""
    assert frames[0] == start and frames[-1] == start + n_frames - 1
    assert np.all(np.diff(frames) >= 1) and np.all(frames == np.round(frames))


def _check_keys(ob, face, bones: list[str], start: int, n_frames: int):
    curves = {(fc.data_path, fc.array_index): fc for fc in fcurves_of(ob)}
    for bone in bones:
        mode = ob.pose.bones[bone].rotation_mode
        prop, n = {"QUATERNION": ("rotation_quaternion", 4), "AXIS_ANGLE": ("rotation_axis_angle", 4)}.get(
            mode, ("rotation_euler", 3))
        values = []
        for i in range(n):
            fc = curves[(f'pose.bones["{bone}"].{prop}', i)]
            co = _keys(fc)
            _check_frames(co[:, 0], start, n_frames)
            assert np.all(np.isfinite(co[:, 1]))
            values.append(co[:, 1])
        if mode == "QUATERNION":
            norms = np.linalg.norm(np.array(values), axis=0)
            np.testing.assert_allclose(norms, 1.0, atol=1e-5)
    blocks = face.data.shape_keys.key_blocks
    face_curves = fcurves_of(face.data.shape_keys)
    assert len(face_curves) == 51
    for fc in face_curves:
        co = _keys(fc)
        name = fc.data_path.split('"')[1]
        _check_frames(co[:, 0], start, n_frames)
        assert np.all(np.isfinite(co[:, 1]))
        assert co[:, 1].min() >= blocks[name].slider_min and co[:, 1].max() <= blocks[name].slider_max


def _check_sound(scene, settings, start: int):
    """One sound strip at the first key; a Blender without audio support says why there is none."""
    strips = sound_strips(scene)
    if HAS_AUDIO:
        assert len(strips) == 1 and strips[0].frame_start == start
    else:
        assert strips == [] and "no audio support" in report_text()


def _run_operator(scene, settings):
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    default = load_model()  # the bundled default; a placeholder would be labelled UNTRAINED
    assert default.model_id in settings.model_label
    assert ("UNTRAINED" in settings.model_label) == (not default.trained)
    return round(3.0 * scene.render.fps / scene.render.fps_base)


def test_generate_onto_beat_armature_and_arkit_face(speech):
    scene = reset_scene(fps=24)
    ob = import_beat_armature()
    face = append_face()
    settings = _configure(scene, speech, ob, "beat", face, start=10)
    n_frames = _run_operator(scene, settings)
    bones = _bones(load_preset("beat"))
    _check_keys(ob, face, bones, 10, n_frames)
    assert ob.animation_data.action.name.startswith(speech.stem)
    _check_sound(scene, settings, 10)
    assert (scene.frame_start, scene.frame_end) == (10, 10 + n_frames - 1)


def _bones(preset, layout: str = "beat") -> list[str]:
    return [bone for chain in preset.joint_map(layout).values() for bone in chain]


def _keyed_bones(ob) -> set[str]:
    return {fc.data_path.split('"')[1] for fc in fcurves_of(ob)}


def test_generate_onto_smplx_armature_drives_the_jaw_bone_unless_a_jaw_shape_key_does(speech):
    """The jaw bone opens the mouth from jawOpen; with a face whose jawOpen shape key opens it,
    the bone stays at rest (else the mouth would open twice) and the report says so."""
    scene = reset_scene(fps=30)
    ob = build_smplx_armature(roll_seed=3)
    settings = _configure(scene, speech, ob, "smplx")
    _run_operator(scene, settings)
    assert "jaw" in _keyed_bones(ob)
    ob.animation_data_clear()
    face = append_face()
    settings.face_meshes.add().object = face
    n_frames = _run_operator(scene, settings)
    _check_keys(ob, face, [b for b in _bones(load_preset("smplx")) if b in ob.pose.bones], 1, n_frames)  # no legs
    assert "jaw" not in _keyed_bones(ob)
    assert "jaw bone jaw left at rest: the jawOpen shape key of Neutral opens the mouth" in report_text()


def test_generate_onto_rigify_fk_controls_moves_the_deform_bones(speech, rigify_blend):
    bpy.ops.wm.open_mainfile(filepath=str(rigify_blend))
    scene = bpy.context.scene
    set_fps(scene, 25)
    rig = bpy.data.objects["rig"]
    face = append_face()
    settings = _configure(scene, speech, rig, "rigify", face)
    scene.frame_set(1)
    rest_dir = world_direction(rig, "DEF-forearm.L")
    n_frames = _run_operator(scene, settings)
    preset = load_preset("rigify")
    _check_keys(rig, face, _bones(preset), 1, n_frames)
    assert preset.jaw.bone not in _keyed_bones(rig)  # the face's jawOpen key opens the mouth
    assert rig.pose.bones["upper_arm_parent.L"]["IK_FK"] == 1.0  # arms in FK
    moved = []
    for f in range(5, n_frames, 10):
        scene.frame_set(f)
        moved.append(np.degrees(np.arccos(np.clip(rest_dir @ world_direction(rig, "DEF-forearm.L"), -1, 1))))
    assert max(moved) > 1.0  # the deform bones follow the keyed FK controls


@pytest.mark.parametrize("fps", [24.0, 25.0, 29.97, 60.0])
def test_last_key_lands_at_the_audio_duration(speech_motion, speech, fps):
    scene = reset_scene(fps=fps)
    face = append_face()
    ob = import_beat_armature()
    result = bake_motion(scene, speech_motion, str(speech), BakeOptions(
        armature=ob, face_meshes=[face], preset=load_preset("beat"), start_frame=1))
    duration = 3.0 * scene.render.fps / scene.render.fps_base
    for fc in fcurves_of(ob) + fcurves_of(face.data.shape_keys):
        last = fc.keyframe_points[-1].co[0]
        assert abs((last - 1) - duration) <= 1.0
    assert result.n_frames == round(duration)


def test_user_action_is_kept_in_the_nla(speech_motion, speech):
    scene = reset_scene(fps=24)
    ob = import_beat_armature()
    user = bpy.data.actions.new("my_wave")
    ob.animation_data_create().action = user
    for f, angle in ((1, 0.0), (20, 0.8), (40, 0.0)):
        ob.pose.bones["RightArm"].rotation_euler = (0, 0, angle)
        ob.pose.bones["RightArm"].rotation_mode = "XYZ"
        ob.pose.bones["RightArm"].keyframe_insert("rotation_euler", frame=f)
    before = [(fc.data_path, fc.array_index, _keys(fc).tolist()) for fc in fcurves_of(ob)]
    bake_motion(scene, speech_motion, str(speech), BakeOptions(armature=ob, preset=load_preset("beat")))
    assert ob.animation_data.action.name != "my_wave"
    strips = [s for t in ob.animation_data.nla_tracks for s in t.strips]
    assert [s.action.name for s in strips] == ["my_wave"]
    kept = [(fc.data_path, fc.array_index, _keys(fc).tolist())
            for fc in action_fcurves(user, getattr(strips[0], "action_slot", None))]
    assert kept == before


def test_cancel_midway_leaves_the_scene_unchanged(tmp_path):
    scene = reset_scene()
    ob = import_beat_armature()
    face = append_face()
    speech = cut_speech(tmp_path, seconds=20.0)
    _configure(scene, speech, ob, "beat", face)
    before = scene_state(scene)
    job = GenerationJob(Request(speech, None, GenerateSettings(steps=25, device="cpu"))).start()
    while job.fraction == 0.0 and not job.done:
        threading.Event().wait(0.01)
    job.cancel.set()
    job.wait()
    assert isinstance(job.error, Cancelled) and job.motion is None
    assert scene_state(scene) == before


def test_bad_audio_is_reported_and_leaves_the_scene_unchanged(tmp_path):
    scene = reset_scene()
    ob = import_beat_armature()
    face = append_face()
    bad = tmp_path / "broken.wav"
    bad.write_bytes(b"RIFF\x10\x00\x00\x00WAVEjunk" + bytes(200))
    _configure(scene, bad, ob, "beat", face)
    before = scene_state(scene)
    with pytest.raises(RuntimeError, match="broken.wav") as err:
        bpy.ops.diffsheg.generate()
    assert "Traceback" not in str(err.value)
    assert scene_state(scene) == before


def test_misnamed_mp3_generates(tmp_path):
    """The shared 'wav' that holds MP3 data is decoded (or rejected with a clear message)."""
    scene = reset_scene()
    face = append_face()
    _configure(scene, MISNAMED_MP3, None, "beat", face)
    scene.diffsheg.add_sound = False
    try:
        bpy.ops.diffsheg.generate()
    except RuntimeError as exc:  # a clear message, never a traceback
        assert "Traceback" not in str(exc) and "mp3" in str(exc).lower()
        return
    assert len(fcurves_of(face.data.shape_keys)) == 51


def test_save_and_reopen_keeps_keys_and_sound(speech, tmp_path):
    scene = reset_scene(fps=24)
    ob = import_beat_armature()
    face = append_face()
    settings = _configure(scene, speech, ob, "beat", face, start=5)
    settings.seed = 1234
    _run_operator(scene, settings)
    keys = {(fc.data_path, fc.array_index): _keys(fc) for fc in fcurves_of(ob)}
    path = tmp_path / "saved.blend"
    names = ob.name, face.name
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    ob, face = scene.objects[names[0]], scene.objects[names[1]]
    reopened = {(fc.data_path, fc.array_index): _keys(fc) for fc in fcurves_of(ob)}
    assert reopened.keys() == keys.keys()
    for k in keys:
        np.testing.assert_array_equal(reopened[k], keys[k])
    assert len(fcurves_of(face.data.shape_keys)) == 51
    _check_sound(scene, scene.diffsheg, 5)
    assert scene.diffsheg.seed == 1234 and scene.diffsheg.preset == "beat"


def test_panel_options_are_the_models_defaults_until_set(speech):
    """Overlap, guidance and gesture energy: a switched-off "Set ..." toggle is the model's
    default (None), switched on the value means what it means everywhere (guidance 1 and
    gesture energy 0 are off)."""
    from blender_addon.features.generate import generate_settings

    settings = reset_scene().diffsheg
    plain = generate_settings(settings)
    assert (plain.steps, plain.overlap, plain.guidance, plain.skip_guidance) == (None, None, None, None)
    settings.set_gesture_energy, settings.set_overlap, settings.set_guidance = True, True, True
    settings.gesture_energy, settings.overlap, settings.guidance = 0.0, 6, 1.0
    assert (generate_settings(settings).skip_guidance, generate_settings(settings).overlap) == (0.0, 6)
    settings.gesture_energy = 0.25
    settings.steps, settings.device = STEPS, "CPU"
    assert generate_settings(settings).steps is None  # the panel's Steps counts only once ticked
    settings.set_steps, settings.set_guidance = True, False
    motion = diffsheg_core.generate(str(speech), settings=generate_settings(settings))
    assert motion.meta["skip_guidance"] == 0.25 and motion.meta["overlap"] == 6 and motion.meta["steps"] == STEPS


def test_the_language_menu_lists_the_model_s_own_faces_and_generate_runs_the_chosen_one(speech, tmp_path):
    """Issue 42: Language offers the model's shared face ("All languages", the default) and each
    language's own face its file carries (the bundled model: Mandarin), read from the file's
    metadata; the choice is GenerateSettings.language, and the take records it."""
    import diffsheg_core.checkpoints as checkpoints
    from blender_addon.features.generate import generate_settings
    from blender_addon.ui.properties import _language_items
    from diffsheg_core.training.faces import remove_face

    settings = reset_scene().diffsheg
    menu = [(identifier, name) for identifier, name, _ in _language_items(settings, bpy.context)]
    assert menu == [("__shared__", "All languages"), ("zh", "Mandarin")]
    assert settings.language == "__shared__" and generate_settings(settings).language is None
    settings.language = "zh"
    chosen = generate_settings(settings)
    assert chosen.language == "zh"
    motion = diffsheg_core.generate(str(speech), settings=replace(chosen, steps=STEPS))
    assert motion.meta["language"] == "zh"
    settings.model_path = str(checkpoints.save_checkpoint(remove_face(load_model(), "zh"), tmp_path / "m.safetensors"))
    assert [identifier for identifier, *_ in _language_items(settings, bpy.context)] == ["__shared__"]


def test_the_panels_sampling_is_fast_unless_quality_is_chosen(speech):
    """Issue 39, item 5: the Sampling sub-panel's Sampling (Fast, the default, or Quality)
    is GenerateSettings.sampling; the greyed-out Steps shows the chosen sampling's own count
    until Set steps is ticked, and a ticked count stays whatever the sampling."""
    import json

    from blender_addon.features.generate import generate_settings
    from blender_addon.ui.properties import DIFFSHEG_PG_settings, SAMPLING_STEPS
    from diffsheg_core.checkpoints import _stored_metadata
    from diffsheg_core.foppas import FAST_TIMESTEPS

    # the numpy-free counts the panel shows are the core's
    assert SAMPLING_STEPS == {"FAST": len(FAST_TIMESTEPS),
                              "QUALITY": json.loads(_stored_metadata(None)["sampling"])["steps"]}
    settings = reset_scene().diffsheg
    items = DIFFSHEG_PG_settings.bl_rna.properties["sampling"].enum_items
    assert [(i.identifier, i.name) for i in items] == [("FAST", "Fast"), ("QUALITY", "Quality")]
    fast = items["FAST"].description
    assert "distilled student" in fast and "5.5 times faster" in fast and "25 steps" in items["QUALITY"].description
    assert (settings.sampling, settings.steps, settings.set_steps) == ("FAST", 5, False)
    assert (generate_settings(settings).sampling, generate_settings(settings).steps) == ("fast", None)
    settings.sampling = "QUALITY"
    assert (generate_settings(settings).sampling, generate_settings(settings).steps) == ("quality", None)
    assert settings.steps == 25  # what applies, greyed out
    settings.set_steps, settings.steps = True, 7
    settings.sampling = "FAST"
    assert settings.steps == 7 and (generate_settings(settings).sampling, generate_settings(settings).steps) == (
        "fast", 7)

    short = cut_speech(speech.parent, seconds=1.0, name="short.wav")
    settings.set_steps, settings.device = False, "CPU"
    for choice, steps in (("QUALITY", 25), ("FAST", 5)):
        settings.sampling = choice
        motion = diffsheg_core.generate(str(short), settings=generate_settings(settings))
        assert (motion.meta["sampling"], motion.meta["steps"]) == (choice.lower(), steps)
    assert motion.meta["timesteps"] == list(FAST_TIMESTEPS)


def test_own_face_seed_keys_the_same_face_for_a_new_seed(speech):
    scene = reset_scene()
    face = append_face()
    settings = _configure(scene, speech, None, "beat", face)
    settings.use_face_seed, settings.face_seed = True, 11

    def jaw_keys():
        assert bpy.ops.diffsheg.generate() == {"FINISHED"}
        curves = {fc.data_path: _keys(fc)[:, 1] for fc in fcurves_of(face.data.shape_keys)}
        return curves['key_blocks["jawOpen"].value']

    first = jaw_keys()
    settings.seed = 5
    second = jaw_keys()
    assert np.array_equal(first, second)
    settings.use_face_seed = False
    assert not np.array_equal(jaw_keys(), second)


def test_keys_start_at_the_scenes_start_frame_by_default(speech):
    """Film pipelines start at 1001, at 29.97 fps: the first key and the sound strip land there."""
    scene = reset_scene(fps=29.97)
    scene.frame_start = 1001
    ob, face = import_beat_armature(), append_face()
    settings = _configure(scene, speech, ob, "beat", face)
    settings.start_at_scene_start = True
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    first = min(_keys(fc)[0, 0] for fc in fcurves_of(ob))
    assert first == 1001 and min(_keys(fc)[0, 0] for fc in fcurves_of(face.data.shape_keys)) == 1001
    if HAS_AUDIO:
        assert [s.frame_start for s in sound_strips(scene)] == [1001]


@pytest.mark.skipif(not HAS_AUDIO, reason="this Blender build has no audio support")
def test_generating_again_replaces_this_addons_sound_strip_and_keeps_the_users(speech):
    scene = reset_scene()
    ob = import_beat_armature()
    _configure(scene, speech, ob, "beat")
    editor = scene.sequence_editor_create()
    strips = editor.strips if hasattr(editor, "strips") else editor.sequences
    strips.new_sound("mine", str(speech), channel=5, frame_start=40)  # the user's own strip of the audio
    for _ in range(3):
        assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    names = sorted(s.name for s in sound_strips(scene))
    assert len(names) == 2 and "mine" in names  # one of the add-on's, and the user's


def test_linked_objects_are_refused_by_name(speech, tmp_path):
    library = tmp_path / "library.blend"
    reset_scene()
    import_beat_armature().name = "LinkedRig"
    bpy.ops.wm.save_as_mainfile(filepath=str(library))
    scene = reset_scene()
    with bpy.data.libraries.load(str(library), link=True) as (source, target):
        target.objects = ["LinkedRig"]
    rig = target.objects[0]
    scene.collection.objects.link(rig)
    _configure(scene, speech, rig, "beat")
    before = scene_state(scene)
    with pytest.raises(RuntimeError, match="'LinkedRig' is linked from .*library.blend.*Make Local"):
        bpy.ops.diffsheg.generate()
    assert scene_state(scene) == before


def _moved_by(ob, key: str) -> float:
    """Largest vertex displacement (m) the shape key `key` makes in the evaluated mesh now."""
    def coords():
        mesh = ob.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
        co = np.empty(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
        return co
    block = ob.data.shape_keys.key_blocks[key]
    with_key = coords()
    block.mute = True
    without = coords()
    block.mute = False
    return float(np.abs(with_key - without).max())


def _peak_frame(ob, key: str) -> int:
    fc = next(fc for fc in fcurves_of(ob.data.shape_keys) if fc.data_path == f'key_blocks["{key}"].value')
    co = _keys(fc)
    return int(co[int(co[:, 1].argmax()), 0])


def test_ready_player_me_avatar_through_the_panel(speech):
    """The real Ready Player Me avatar, Auto preset, a 29.97 fps scene starting at 1001:
    Auto picks readyplayerme, keys start at 1001, the arms follow the BEAT skeleton keyed
    with the same motion, and jawOpen opens the mouth at its peak."""
    from addon_fixtures import angle_between, head_direction, import_readyplayerme

    from blender_addon.features.generate import generate_settings

    scene = reset_scene(fps=29.97)
    scene.frame_start = 1001
    rig, faces = import_readyplayerme()
    settings = _configure(scene, speech, rig, "auto", faces[0])
    settings.face_meshes.add().object = faces[1]
    settings.start_at_scene_start = True
    _run_operator(scene, settings)
    assert "preset readyplayerme" in settings.last_report and len(settings.last_report) <= 120
    assert "preset Auto chose 'readyplayerme'" in report_text()
    assert min(fc.keyframe_points[0].co[0] for fc in fcurves_of(rig)) == 1001

    beat = import_beat_armature()
    motion = diffsheg_core.generate(str(speech), settings=generate_settings(settings))
    bake_motion(scene, motion, None, BakeOptions(armature=beat, preset=load_preset("beat"), start_frame=1001,
                                                 add_sound=False, set_frame_range=False))
    worst = 0.0
    for f in range(1001, 1001 + 85, 7):
        scene.frame_set(f)
        for side in ("Left", "Right"):
            for a, b in (("Arm", "ForeArm"), ("ForeArm", "Hand")):
                worst = max(worst, angle_between(head_direction(rig, side + a, side + b),
                                                 head_direction(beat, side + a, side + b)))
    assert worst < 10.0, worst
    scene.frame_set(_peak_frame(faces[0], "jawOpen"))
    assert _moved_by(faces[0], "jawOpen") > 0.003  # metres: the mouth opens


def test_ready_player_me_face_without_arkit_keys_talks_through_its_visemes(speech_motion):
    from addon_fixtures import import_readyplayerme
    from diffsheg_core.rigs import ARKIT52

    scene = reset_scene(fps=30)
    _, faces = import_readyplayerme()
    head = faces[0]
    for name in ARKIT52:
        head.shape_key_remove(head.data.shape_keys.key_blocks[name])
    result = bake_motion(scene, speech_motion, None, BakeOptions(armature=None, face_meshes=[head], add_sound=False))
    assert any("viseme_aa" in n and "driven from the ARKit weights" in n for n in result.notes)
    for key in ("viseme_aa", "viseme_O"):
        scene.frame_set(_peak_frame(head, key))
        assert _moved_by(head, key) > 0.002, key


def test_the_demo_character_shows_its_face(speech_motion, tmp_path):
    """The main job's character: every ARKit key of its face moves vertices, the preview is
    640x360 and cuts to a close-up in which the face fills much of the picture."""
    from blender_addon.scene import demo
    from blender_addon.scene.retarget import moves_vertices
    from diffsheg_core.rigs import ARKIT51

    scene = reset_scene(fps=24)
    armature = demo.build_beat_armature()
    face = demo.build_face(armature)
    demo.setup_preview(scene, armature)
    blocks = face.data.shape_keys.key_blocks
    assert [b.name for b in blocks[1:]] == list(ARKIT51) and all(moves_vertices(b) for b in blocks[1:])
    assert (scene.render.resolution_x, scene.render.resolution_y) == (640, 360)
    result = bake_motion(scene, speech_motion, None, BakeOptions(armature=armature, face_meshes=[face],
                                                                 add_sound=False))
    assert "preset Auto chose 'beat'" in result.preset_notes[0] and not result.unmatched_shape_keys[face.name]
    cut = round(demo.CUT_SECONDS * 24)
    assert {m.frame: m.camera.name for m in scene.timeline_markers if m.frame <= cut + 1} == {
        1: "DemoCamera", 1 + cut: "DemoCloseUp"}
    skin = []
    if "media_type" in scene.render.image_settings.bl_rna.properties:  # Blender 5.0
        scene.render.image_settings.media_type = "IMAGE"
    scene.render.image_settings.file_format = "PNG"
    for frame in (10, cut + 10):
        scene.frame_set(frame)
        scene.render.filepath = str(tmp_path / f"shot{frame}.png")
        bpy.ops.render.render(write_still=True)
        image = bpy.data.images.load(scene.render.filepath)
        rgba = np.array(image.pixels[:]).reshape(-1, 4)
        skin.append(float(np.mean((rgba[:, 0] > rgba[:, 2] + 0.08) & (rgba[:, 0] > 0.3))))  # warm skin tones
    assert skin[1] > 0.08 and skin[1] > 5 * skin[0], skin  # measured 0.10 and 0.007


def test_the_demo_speaker_is_a_person_skinned_to_its_skeleton():
    """The main job's speaker is MakeHuman's base mesh fitted to the BEAT skeleton: a person
    1.6-1.9 m tall whose head, hands and feet lie at those bones, and who follows its bones:
    with the left arm raised and the head turned, the hand's and the face's vertices keep to
    their bones within 2 cm."""
    from mathutils import Quaternion

    from blender_addon.scene import demo

    reset_scene(fps=24)
    armature = demo.build_beat_armature()
    body = demo.body_of(armature)
    bones = armature.data.bones

    def vertices():
        mesh = body.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
        co = np.empty(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
        body.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh_clear()
        return co.reshape(-1, 3) @ np.array(body.matrix_world)[:3, :3].T + np.array(body.matrix_world)[:3, 3]

    def owned(name):  # the vertices a bone weighs most
        group = body.vertex_groups[name].index
        return np.array([max(v.groups, key=lambda g: g.weight).group == group if v.groups else False
                         for v in body.data.vertices])

    rest = vertices()
    assert len(rest) > 10000 and 1.6 < np.ptp(rest[:, 2]) < 1.9, np.ptp(rest[:, 2])
    parts = {name: owned(name) for name in ("Head", "LeftHand", "RightHand", "LeftFoot", "RightFoot")}
    for name, mask in parts.items():
        centre = rest[mask].mean(axis=0)
        assert np.linalg.norm(centre - np.array(armature.matrix_world @ bones[name].head_local)) < 0.15, name
    before = {name: rest[parts[name]] - np.array(armature.matrix_world @ bones[name].head_local)
              for name in ("Head", "LeftHand")}
    armature.pose.bones["LeftArm"].rotation_quaternion = Quaternion((1, 0, 0), 1.0)
    armature.pose.bones["Head"].rotation_quaternion = Quaternion((0, 1, 0), 0.5)
    bpy.context.view_layer.update()
    posed = vertices()
    for name, offsets in before.items():
        pose = armature.matrix_world @ armature.pose.bones[name].matrix
        turned = offsets @ np.array(pose.to_3x3().normalized() @ bones[name].matrix_local.to_3x3().inverted()).T
        moved = posed[parts[name]] - (np.array(pose.translation) + turned)
        assert np.percentile(np.linalg.norm(moved, axis=1), 90) < 0.02, name


def test_the_demo_close_up_keeps_the_head_in_frame():
    """The main job's take (the bundled sample speech, hips swaying and stepping): at every
    frame the Head bone's head (the skull's base) and tail (eye level) seen through the
    close-up camera stay inside the picture with a 15 % margin, and the face is big in it;
    the same with the hips pushed 30 cm along each of their axes."""
    from bpy_extras.object_utils import world_to_camera_view

    from blender_addon.scene import demo
    from diffsheg_core.audio import SAMPLE_SPEECH

    scene = reset_scene(fps=24)
    armature = demo.build_beat_armature()
    face = demo.build_face(armature)
    demo.setup_preview(scene, armature)
    bake_motion(scene, diffsheg_core.generate(str(SAMPLE_SPEECH), seed=0, device="cpu"), None,
                BakeOptions(armature=armature, face_meshes=[face], add_sound=False))
    close = scene.objects["DemoCloseUp"]
    head = armature.pose.bones["Head"]
    hips = armature.pose.bones["Hips"]

    def seen():
        points = [world_to_camera_view(scene, close, armature.matrix_world @ p) for p in (head.head, head.tail)]
        return np.array([(p.x, p.y) for p in points]), min(p.z for p in points)

    worst, sizes = 0.0, []
    for frame in range(scene.frame_start, scene.frame_end + 1):
        scene.frame_set(frame)
        xy, depth = seen()
        assert depth > 0.3, (frame, depth)  # in front of the camera
        worst = max(worst, float(np.max(np.abs(xy - 0.5))))
        sizes.append(float(np.linalg.norm(xy[1] - xy[0])))
    print(f"head in the close-up: at most {worst:.3f} from the centre, skull base to eyes {min(sizes):.2f}-"
          f"{max(sizes):.2f} of the frame")
    assert worst < 0.35 and min(sizes) > 0.1
    for shift in ((0.3, 0, 0), (-0.3, 0, 0), (0, 0.3, 0), (0, -0.3, 0), (0, 0, 0.3), (0, 0, -0.3)):
        scene.frame_set(scene.frame_start + 100)
        hips.location = shift
        bpy.context.view_layer.update()
        xy, _ = seen()
        assert np.max(np.abs(xy - 0.5)) < 0.35, (shift, xy)
        hips.location = (0.0, 0.0, 0.0)


def test_panel_styles_come_from_the_model_and_mix(tmp_path):
    """The style menu lists the model's style names (indices for a model without any);
    a second style with the mix slider gives weights, the strength the style guidance."""
    from blender_addon.features.generate import generate_settings
    from blender_addon.ui.properties import style_names
    from diffsheg_core.checkpoints import load_model, save_checkpoint

    settings = reset_scene().diffsheg
    bundle = load_model()
    assert style_names(settings) == (bundle.style_names or ["0"])
    assert generate_settings(settings).style is None  # "Default": the model's own default style
    named = tmp_path / "named.safetensors"
    save_checkpoint(replace(bundle, info={**bundle.info, "style_names": ["calm", "lively", "wild"]}), named)
    settings.model_path = str(named)
    assert style_names(settings) == ["calm", "lively", "wild"]
    settings.style, settings.mix_style, settings.style_mix = "calm", "lively", 0.25
    settings.style_strength = 1.5
    chosen = generate_settings(settings)
    assert chosen.style == {"calm": 0.75, "lively": 0.25} and chosen.style_guidance == 1.5
    settings.mix_style, settings.style_strength = "__none__", 1.0
    assert generate_settings(settings).style == "calm" and generate_settings(settings).style_guidance is None


def test_the_style_menu_offers_exactly_the_models_styles(golden_dir, tmp_path, monkeypatch):
    """A model without style names offers its own style count (3 for the bundled network),
    the official SHOW checkpoint its 4 speakers and BEAT its 30, read without torch; the
    menu asks on every redraw, the file is read once per version."""
    import torch
    from safetensors.torch import load_file

    import diffsheg_core.checkpoints as checkpoints
    from blender_addon.ui.properties import _style_items

    settings = reset_scene().diffsheg
    bundle = load_model()
    unnamed = checkpoints.save_checkpoint(replace(bundle, info={}), tmp_path / "unnamed.safetensors")
    official = {}
    for name in ("beat", "show"):
        official[name] = tmp_path / f"{name}_official.pth"
        torch.save({"encoder": load_file(str(golden_dir / f"{name}_small.safetensors"))}, official[name])
    reads = []
    names = checkpoints.stored_style_names
    monkeypatch.setattr(checkpoints, "stored_style_names", lambda path: reads.append(path) or names(path))
    monkeypatch.setitem(sys.modules, "torch", None)  # `import torch` fails, as without GPU support

    def menu() -> list[str]:
        return [identifier for identifier, *_ in _style_items(settings, bpy.context)]

    for path, n in ((unnamed, 3), (official["show"], 4), (official["beat"], 30)):
        settings.model_path = str(path)
        for _ in range(3):  # redraws
            assert menu() == ["__default__"] + [str(i) for i in range(n)]
    assert len(reads) == 3
    settings.model_path = str(unnamed)  # the file changes: it is read again
    checkpoints.save_checkpoint(replace(bundle, info={"style_names": ["a", "b", "c"]}), unnamed)
    stat = unnamed.stat()
    os.utime(unnamed, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # a newer version, whatever the clock
    assert menu() == ["__default__", "a", "b", "c"] and len(reads) == 4
