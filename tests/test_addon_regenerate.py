"""Regenerate a range of a take in headless Blender (issue 25, items 3 and 4): the BEAT
rig and the ARKit face, 20 s of real speech, the bundled model. Only the range changes
(every F-curve outside it evaluates as before, every key there stays, the animator's
too), the new keys keep the error bound, the joins carry no jump, Keep the take's face keeps the
face, the animator's keys inside the range are pins, and a take can start from the
character's pose."""

from __future__ import annotations

import numpy as np
import pytest

from addon_fixtures import append_face, bpy, cut_speech, import_beat_armature, reset_scene
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)

import diffsheg_core
from blender_addon.features import regenerate
from blender_addon.scene import takes
from blender_addon.scene.bake import BakeOptions, bake_motion, group_values, plan_keys
from blender_addon.scene.keying import VALUE_TOLERANCE, action_fcurves, animators_keys, fcurves_of
from blender_addon.scene.preset import load_preset
from diffsheg_core.errors import DiffshegError
from diffsheg_core.keyframes import rotation_angle, to_quaternions
from diffsheg_core.lower_body import JOINTS as LOWER_JOINTS

FIRST, LAST = 200, 300  # scene frames at 24 fps: 8.3 s to 12.5 s of the 20 s take
ARM = "RightArm"


@pytest.fixture(scope="module")
def speech(tmp_path_factory):
    return cut_speech(tmp_path_factory.mktemp("speech"), seconds=20.0, name="talk.wav")


@pytest.fixture(scope="module")
def motion(speech):
    """The take, made with the default (fast) sampling (the ranges are sampled with the model's
    own 25 steps all the same: make_plan's `holds`). On it, regenerate seed 9, the pin's
    neighbourhood reached 2.47x the range's median acceleration at the model's frames while
    pipeline.ease_into_pins eased each pin on its own (issue 40); with its least-jerk blend
    0.96x there and 1.83x on the rig. Over takes of either sampling, seeds 0-2, ranges seeds
    7-9: at most 1.62x at the model's frames (before 2.78x); the rig's figure, the change of
    angular speed at 24 fps, is noisier: 0.7-3.5x (before 1.1-9.4x)."""
    return diffsheg_core.generate(str(speech), device="cpu")


def _scene(motion, speech):
    scene = reset_scene(fps=24)
    armature, face = import_beat_armature(), append_face()
    options = BakeOptions(armature=armature, face_meshes=[face], preset=load_preset("beat"), add_sound=False)
    bake_motion(scene, motion, str(speech), options)
    return scene, options


def _targets(options) -> list:
    return [options.armature] + [f.data.shape_keys for f in options.face_meshes]


def _evaluate(id_data, frames) -> dict:
    return {(fc.data_path, fc.array_index): np.array([fc.evaluate(f) for f in frames]) for fc in fcurves_of(id_data)}


def _keys(id_data) -> dict:
    """{(path, index): [(frame, value, left handle, right handle, type)]} of the playing Action."""
    return {(fc.data_path, fc.array_index): [(tuple(p.co), tuple(p.handle_left), tuple(p.handle_right), p.type)
                                             for p in fc.keyframe_points] for fc in fcurves_of(id_data)}


def _regenerate(scene, options, speech, first=FIRST, last=LAST, **kwargs):
    request = regenerate.prepare_range(scene, options, first, last)
    hold_face = kwargs.pop("hold_face", False)
    new = diffsheg_core.regenerate(request.source.motion, str(speech), start=request.start, end=request.end,
                                   hold_face=hold_face, pins=request.pins, device="cpu", **kwargs)
    return request, new, regenerate.apply_range(scene, request, new, options)


def _bone_rotations(scene, motion, options, bone) -> np.ndarray:
    """(T, 4) quaternions the motion gives `bone` at the scene's rate (what keying fits)."""
    group = next(g for g in plan_keys(scene, motion, options).targets[0][1]
                 if g.channels[0].data_path == f'pose.bones["{bone}"].rotation_euler')
    return to_quaternions(group_values(group), options.armature.pose.bones[bone].rotation_mode)


def test_only_the_range_changes_within_the_bound_and_without_a_jump(motion, speech):
    scene, options = _scene(motion, speech)
    armature = options.armature
    armature.pose.bones["LeftArm"].rotation_euler = (0.3, 0.2, 0.1)  # the animator's key outside the range
    armature.pose.bones["LeftArm"].keyframe_insert("rotation_euler", frame=100)
    frames = np.arange(1, 481)
    before = [_evaluate(t, frames) for t in _targets(options)]
    keys_before = [_keys(t) for t in _targets(options)]
    first_take = takes.playing(armature)

    request, new, result = _regenerate(scene, options, speech, seed=7)

    assert result.take == "talk take 2" and takes.playing(armature) == "talk take 2"
    assert takes.playing(options.face_meshes[0].data.shape_keys) == "talk take 2"
    assert takes.takes_of([armature]) == ["talk take 1", "talk take 2"] and first_take == "talk take 1"
    outside = (frames < FIRST) | (frames > LAST)
    changed = 0.0
    for target, old, old_keys in zip(_targets(options), before, keys_before):
        now, now_keys = _evaluate(target, frames), _keys(target)
        for path in old:
            np.testing.assert_allclose(now[path][outside], old[path][outside], atol=1e-5, err_msg=str(path))
            changed = max(changed, np.abs(now[path][~outside] - old[path][~outside]).max())
            # every key outside the range and the cuts beside it is where it was, of its type;
            # the handles too, but for the one reaching into each cut (shortened, same direction)
            far = [k for k in old_keys[path] if k[0][0] < FIRST - 1 or k[0][0] > LAST + 1]
            kept = [k for k in now_keys[path] if k[0][0] < FIRST - 1 or k[0][0] > LAST + 1]
            assert [(k[0], k[3]) for k in far] == [(k[0], k[3]) for k in kept], path
            for side, outer in ((1, lambda k: k[0][0] < FIRST), (2, lambda k: k[0][0] > LAST)):
                np.testing.assert_allclose([k[side] for k in far if outer(k)], [k[side] for k in kept if outer(k)],
                                           atol=1e-5, err_msg=str(path))  # float32 rounding in Blender's update
            assert {k[3] for k in now_keys[path] if FIRST <= k[0][0] <= LAST} <= {"GENERATED"}
    assert changed > 0.1  # radians: the range moves otherwise
    assert ('pose.bones["LeftArm"].rotation_euler', 0) in keys_before[0]
    assert any(k[3] == "KEYFRAME" for k in _keys(armature)[('pose.bones["LeftArm"].rotation_euler', 0)])

    # the new keys stay within the bound of the regenerated motion on every frame of the range
    span = np.arange(FIRST - 1, LAST + 2)
    for (id_data, groups), target in zip(plan_keys(scene, new, options).targets, _targets(options)):
        now = _evaluate(target, span)
        for group in groups:
            if group.channels[0].data_path == 'pose.bones["LeftArm"].rotation_euler':
                continue  # its key at frame 100 is the animator's: the motion there is not
            values = group_values(group)
            keyed = np.stack([now[(c.data_path, c.index)] for c in group.channels], axis=1)
            assert group.error(values)(keyed, span - 1).max() <= group.bound + 1e-4, group.channels[0].data_path

    # the new take keeps its own source: it can be regenerated again
    np.testing.assert_array_equal(takes.source_of("talk take 2").motion.rotations, new.rotations)

    # the joins: mean joint acceleration of the keyed curves over each join's frames against
    # that inside the range, over three seeds, each a new take regenerated from take 1
    # (measured 1.30 / 0.52, 1.14 / 0.56, 1.67 / 0.91 for seeds 5-7; the motion alone 1.13-1.24)
    joins = [_join_ratios(armature, frames)]
    for seed in (5, 6):
        takes.use_take("talk take 1")
        _regenerate(scene, options, speech, seed=seed)
        joins.append(_join_ratios(armature, frames))
    assert takes.takes_of([armature]) == ["talk take 1", "talk take 2", "talk take 3", "talk take 4"]
    left, right = np.mean(joins, axis=0)
    assert left <= 1.5 and right <= 1.5, joins


def _move_keys(id_data, frames: float) -> None:
    """Every key of the Action `id_data` plays moved by `frames` (the Dope Sheet's G on all keys)."""
    for fc in fcurves_of(id_data):
        for point in fc.keyframe_points:
            point.co[0] += frames
            point.handle_left[0] += frames
            point.handle_right[0] += frames
        fc.update()


def test_a_take_moved_in_time_is_regenerated_where_it_is(motion, speech):
    """The animator moved the whole take 12 frames later (every key, on the armature and the
    face): regenerating a range of it finds the take where it is now. None of its keys counts
    as the animator's (before, every one did: pins everywhere, the range 12 frames off), the
    same model frames are sampled anew as in place, and the new take is the one made in place
    with the same seed, 12 frames later. Keys moved apart (the armature, not the face) or by
    part of a frame are refused before anything runs."""
    scene, options = _scene(motion, speech)
    placed, new_placed, _ = _regenerate(scene, options, speech, seed=7)
    frames = np.arange(FIRST - 30, LAST + 30)
    expected = [_evaluate(t, frames) for t in _targets(options)]
    takes.use_take("talk take 1")
    for target in _targets(options):
        _move_keys(target, 12)

    request, new, result = _regenerate(scene, options, speech, first=FIRST + 12, last=LAST + 12, seed=7)

    assert request.source.start_frame == placed.source.start_frame + 12 and request.pins == ()
    assert (request.start, request.end) == (placed.start, placed.end) and not request.notes
    np.testing.assert_array_equal(new.rotations, new_placed.rotations)
    for target, before in zip(_targets(options), expected):
        now = _evaluate(target, frames + 12)
        for path in before:
            np.testing.assert_allclose(now[path], before[path], atol=1e-4, err_msg=str(path))
        assert {k[3] for keys in _keys(target).values() for k in keys} == {"GENERATED"}  # none made the animator's
    assert takes.source_of(result.take).start_frame == placed.source.start_frame + 12

    takes.use_take("talk take 1")
    _move_keys(options.armature, -12)  # the armature back, the face still 12 frames later
    with pytest.raises(DiffshegError, match=r"the keys of take 'talk take 1' were moved apart \(.* by 0, .* by 12 "):
        regenerate.prepare_range(scene, options, FIRST, LAST)
    for target in _targets(options)[1:]:
        _move_keys(target, -11.5)
    _move_keys(options.armature, 0.5)
    with pytest.raises(DiffshegError, match="were moved by 0.5 frames: move them by whole frames"):
        regenerate.prepare_range(scene, options, FIRST, LAST)


def _join_ratios(armature, frames) -> tuple[float, float]:
    curves = _evaluate(armature, frames)
    rotations = np.stack([v for (path, _), v in curves.items() if path.endswith(".rotation_euler")
                          and path.split('"')[1] not in LOWER_JOINTS], axis=1)  # the legs are the take's
    acc = np.abs(np.diff(rotations, 2, axis=0)).mean(axis=1)  # entry i: frame i + 2
    inside = acc[FIRST + 2: LAST - 4].mean()
    return acc[FIRST - 5: FIRST + 1].mean() / inside, acc[LAST - 4: LAST + 2].mean() / inside


def test_hold_face_keeps_every_face_curve(motion, speech):
    scene, options = _scene(motion, speech)
    face = options.face_meshes[0].data.shape_keys
    frames = np.arange(1, 481)
    before = _evaluate(face, frames)
    body = _evaluate(options.armature, frames)
    _regenerate(scene, options, speech, seed=8, hold_face=True)
    after = _evaluate(face, frames)
    for path in before:
        np.testing.assert_allclose(after[path], before[path], atol=1e-5, err_msg=str(path))
    moved = _evaluate(options.armature, frames)
    assert max(np.abs(moved[p] - body[p]).max() for p in body) > 0.1


def test_an_animators_key_inside_the_range_is_a_pin(motion, speech):
    """The right arm raised about 30 degrees at frame 250 with an ordinary key: the
    regenerated motion passes through that pose within 2 degrees and flows in and out of
    it; the key stays as set."""
    scene, options = _scene(motion, speech)
    bone = options.armature.pose.bones[ARM]
    frame = 250
    scene.frame_set(frame)
    bone.rotation_euler = (bone.rotation_euler[0] + 0.4, bone.rotation_euler[1], bone.rotation_euler[2] - 0.3)
    bone.keyframe_insert("rotation_euler", frame=frame)
    pose = to_quaternions(np.array([tuple(bone.rotation_euler)]), bone.rotation_mode)
    set_key = [k for k in _keys(options.armature)[(f'pose.bones["{ARM}"].rotation_euler', 0)] if k[0][0] == frame]

    request, new, result = _regenerate(scene, options, speech, seed=9)

    assert {p.joint for p in request.pins} == {ARM} and len(request.pins) == 2  # 250 lies between model frames
    arm = _bone_rotations(scene, new, options, ARM)
    assert rotation_angle(arm[frame - 1: frame], pose)[0] < 2.0
    # flowed into and out of, at the model's frames (as diffsheg_core's regenerate test measures)
    joint = new.joint_names.index(ARM)
    acc = np.linalg.norm(np.diff(new.rotations[:, joint], 2, axis=0), axis=1)  # entry i: frame i + 1
    k = request.pins[0].frame
    ratio = acc[k - 4: k + 3].max() / np.median(acc[request.start: request.end - 2])
    assert ratio <= 2.0, ratio
    # ... and on the rig at the scene's frames, as keyed: the arm's angular acceleration
    # around the key at most twice the range's median (issue 40, item 3)
    step = rotation_angle(arm[1:], arm[:-1])
    scene_acc = np.abs(np.diff(step))  # entry i: frame i + 1 of the curve
    first, last = (int(round(f * scene.render.fps / new.fps)) for f in (request.start, request.end))
    around = scene_acc[frame - 7: frame + 5].max() / np.median(scene_acc[first: last - 2])
    assert around <= 2.0, around
    now = [k for k in _keys(options.armature)[(f'pose.bones["{ARM}"].rotation_euler', 0)] if k[0][0] == frame]
    assert now == set_key and now[0][3] == "KEYFRAME"


def _unkeyed_frame(armature, bone: str, frames) -> int:
    """The first of `frames` where the take put no key on `bone`'s rotation (a key of the take's
    keyed again unchanged stays the take's: test_a_generated_key_keyed_again_unchanged_is_no_pin)."""
    keyed = {int(p.co[0]) for fc in fcurves_of(armature) if fc.data_path == f'pose.bones["{bone}"].rotation_euler'
             for p in fc.keyframe_points}
    return next(f for f in frames if f not in keyed)


def test_keys_that_cannot_be_pins_are_named(motion, speech):
    scene, options = _scene(motion, speech)
    armature = options.armature
    hips = _unkeyed_frame(armature, "Hips", range(260, 290))
    edge = _unkeyed_frame(armature, ARM, (FIRST, FIRST + 1))
    armature.pose.bones["Hips"].keyframe_insert("rotation_euler", frame=hips)  # the model does not drive it
    armature.pose.bones[ARM].keyframe_insert("rotation_euler", frame=edge)  # on the range's edge
    request = regenerate.prepare_range(scene, options, FIRST, LAST)
    assert request.pins == ()
    assert any(f"Hips at frame {hips}" in n and "does not drive" in n for n in request.notes), request.notes
    assert any(f"{ARM} at frame {edge}" in n and "edge" in n for n in request.notes), request.notes


def _key_again(scene, options, nudge: float, frame: int | None = None) -> int:
    """Key the arm's rotation again at `frame` (default: the first frame of the range, 20 frames
    in, where the take put a key), its pose there turned by `nudge` radians about x and z; the frame."""
    path = f'pose.bones["{ARM}"].rotation_euler'
    if frame is None:
        frame = next(int(p.co[0]) for fc in fcurves_of(options.armature) if fc.data_path == path
                     for p in fc.keyframe_points if FIRST + 20 <= p.co[0] <= LAST - 20)
    bone = options.armature.pose.bones[ARM]
    scene.frame_set(frame)
    bone.rotation_euler = (bone.rotation_euler[0] + nudge, bone.rotation_euler[1], bone.rotation_euler[2] - nudge)
    bone.keyframe_insert("rotation_euler", frame=frame)
    return frame


def _keys_at(id_data, path: str, frame: int) -> dict:
    """{index: (co, left handle, right handle, type)} of the keys of `path` at `frame`."""
    return {index: key for (p, index), keys in _keys(id_data).items() if p == path for key in keys
            if key[0][0] == frame}


def test_a_generated_key_keyed_again_is_the_animators(motion, speech):
    """Keying a frame that holds a generated key keeps its GENERATED type (Blender 5.0): the
    value the animator set tells the key from the take's (issue 40). It is a pin, and in the
    new take the bone's rotation keys at that frame stay as set, typed KEYFRAME; every other
    key of the new take is the take's."""
    scene, options = _scene(motion, speech)
    path = f'pose.bones["{ARM}"].rotation_euler'
    frame = _key_again(scene, options, 0.4)
    set_keys = _keys_at(options.armature, path, frame)
    assert {key[3] for key in set_keys.values()} == {"GENERATED"}  # as Blender 5.0 leaves them

    request, new, result = _regenerate(scene, options, speech, seed=9)

    assert {p.joint for p in request.pins} == {ARM}
    assert _keys_at(options.armature, path, frame) == {i: (*key[:3], "KEYFRAME") for i, key in set_keys.items()}
    action, slot = takes.playing_action(options.armature)
    assert action.name == result.take
    fcurves = action_fcurves(action, slot)
    theirs = {(fc.data_path, float(fc.keyframe_points[int(i)].co[0]))
              for fc, found in zip(fcurves, animators_keys(action, fcurves)) for i in np.flatnonzero(found)}
    assert theirs == {(path, float(frame))}


def test_a_generated_key_keyed_again_unchanged_is_no_pin(motion, speech):
    """Keying the take's own pose again at a generated key, as it is or moved by float noise
    within keying.VALUE_TOLERANCE, leaves the key the take's: no pin."""
    scene, options = _scene(motion, speech)
    path = f'pose.bones["{ARM}"].rotation_euler'
    frame = _key_again(scene, options, 0.0)
    assert regenerate.prepare_range(scene, options, FIRST, LAST).pins == ()
    before = _keys_at(options.armature, path, frame)
    _key_again(scene, options, VALUE_TOLERANCE / 4, frame)
    assert _keys_at(options.armature, path, frame)[0][0] != before[0][0]  # the value did move
    assert regenerate.prepare_range(scene, options, FIRST, LAST).pins == ()


def test_a_take_can_start_from_the_characters_pose(motion, speech):
    scene = reset_scene(fps=24)
    armature = import_beat_armature()
    options = BakeOptions(armature=armature, preset=load_preset("beat"), add_sound=False)
    armature.pose.bones[ARM].rotation_euler = (0.5, -0.2, 0.3)
    armature.pose.bones["Spine"].rotation_euler = (0.1, 0.0, 0.05)
    wanted = {b: to_quaternions(np.array([tuple(armature.pose.bones[b].rotation_euler)]), "XYZ")
              for b in (ARM, "Spine")}
    pins = regenerate.pose_pins(scene, options, motion)
    assert len(pins) >= 40 and {p.frame for p in pins} == {0}
    started = diffsheg_core.generate(str(speech), pins=pins, device="cpu")
    for bone, quaternion in wanted.items():
        assert rotation_angle(_bone_rotations(scene, started, options, bone)[:1], quaternion)[0] < 0.5, bone


@pytest.mark.parametrize("first,last,match", [
    (400, 600, "within the take's frames 1-480"),
    (200, 203, "too short"),
])
def test_bad_ranges_are_refused_before_anything_runs(motion, speech, first, last, match):
    scene, options = _scene(motion, speech)
    with pytest.raises(DiffshegError, match=match):
        regenerate.prepare_range(scene, options, first, last)


def test_a_character_playing_no_take_is_told_to_generate_first(motion, speech):
    scene, options = _scene(motion, speech)
    for target in _targets(options):
        target.animation_data.action = None
    with pytest.raises(DiffshegError, match="plays no take"):
        regenerate.prepare_range(scene, options, FIRST, LAST)


# ---------------------------------------------------------------- through the panel's Generate

def _panel(scene, speech, armature, face):
    s = scene.diffsheg
    s.audio_path = str(speech)
    s.armature = armature
    s.face_meshes.add().object = face
    s.preset = "beat"
    s.device = "CPU"
    return s


def test_generate_with_the_preview_range_regenerates_it_as_a_new_take(speech):
    scene = reset_scene(fps=24)
    armature, face = import_beat_armature(), append_face()
    s = _panel(scene, speech, armature, face)
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    frames = np.arange(1, 481)
    before = _evaluate(armature, frames)
    s.range_mode = "PREVIEW"
    scene.use_preview_range = False
    with pytest.raises(RuntimeError, match="the scene has none"):
        bpy.ops.diffsheg.generate()
    scene.use_preview_range = True
    scene.frame_preview_start, scene.frame_preview_end = FIRST, LAST
    s.seed = 11
    s.audio_path = ""  # a range uses the take's own audio
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    assert takes.playing(armature) == "talk take 2" and s.last_report.startswith("talk take 2: 101 frames")
    after = _evaluate(armature, frames)
    outside = (frames < FIRST) | (frames > LAST)
    for path in before:
        np.testing.assert_allclose(after[path][outside], before[path][outside], atol=1e-5)
    assert max(np.abs(after[p] - before[p]).max() for p in before) > 0.1
    s.range_mode, s.range_start, s.range_end = "FRAMES", 300, 305  # too short, named before generating
    with pytest.raises(RuntimeError, match="too short"):
        bpy.ops.diffsheg.generate()


def test_style_markers_change_the_style_from_their_frame(speech, monkeypatch):
    scene = reset_scene(fps=24)
    armature, face = import_beat_armature(), append_face()
    _panel(scene, speech, armature, face)
    scene.timeline_markers.new("style:calm", frame=1)
    scene.timeline_markers.new("style:animated=0.7,calm=0.3", frame=241)
    scene.timeline_markers.new("intro", frame=100)  # not a style marker
    made = []
    generate = diffsheg_core.generate
    monkeypatch.setattr(diffsheg_core, "generate", lambda *a, **k: made.append(generate(*a, **k)) or made[-1])
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    assert made[0].meta["style_at"] == [[0.0, {"calm": 1.0}], [10.0, {"calm": 0.3, "animated": 0.7}]]
    scene.timeline_markers.new("style:calm=lots", frame=300)
    with pytest.raises(RuntimeError, match="timeline marker 'style:calm=lots' at frame 300"):
        bpy.ops.diffsheg.generate()


def test_start_from_pose_through_the_panel(speech):
    scene = reset_scene(fps=24)
    armature, face = import_beat_armature(), append_face()
    s = _panel(scene, speech, armature, face)
    armature.pose.bones[ARM].rotation_euler = (0.5, -0.2, 0.3)
    wanted = to_quaternions(np.array([[0.5, -0.2, 0.3]]), "XYZ")
    s.start_from_pose = True
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    fc = {f.array_index: f for f in fcurves_of(armature) if f.data_path == f'pose.bones["{ARM}"].rotation_euler'}
    keyed = to_quaternions(np.array([[fc[i].evaluate(1) for i in range(3)]]), "XYZ")
    assert rotation_angle(keyed, wanted)[0] < 1.5  # the key bound (1 degree) and the pin's
