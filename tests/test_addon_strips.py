"""Generate for Sound Strips (issue 28, item 6) in headless Blender, with real speech: every
sound strip of the Video Sequencer (or the selected ones) keyed onto the panel's character
from the strip's own frame, one take per strip, no sound strip added, every strip's take
playing from the sound-strips NLA track at its own frames (a rerun replaces a line's take
there, a range of one line regenerates in place); a strip whose file is gone (or whose sound
is packed) fails by name while the others are keyed; Esc keeps the strips already keyed and
leaves nothing of the one under way."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from addon_fixtures import (HAS_AUDIO, SPEECH, SPEECH_2, append_face, bpy, cut_speech, import_beat_armature,
                            report_text, reset_scene)
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)

from blender_addon.scene import takes
from blender_addon.scene.keying import action_fcurves
from blender_addon.features.strips import StripsRun
from blender_addon.ui.panel import DIFFSHEG_PT_generate
from blender_addon.scene.sound import sound_strips

pytestmark = pytest.mark.skipif(not HAS_AUDIO, reason="this Blender has no audio support: no sound strips")

SECONDS = 2.0
FRAMES = round(SECONDS * 24)  # at the scene's 24 fps


@pytest.fixture(scope="module")
def speech(tmp_path_factory):
    """Two real recordings: 'talk' (two strips play it) and 'other'."""
    folder = tmp_path_factory.mktemp("strips")
    return (cut_speech(folder, SECONDS, SPEECH, name="talk.wav"),
            cut_speech(folder, SECONDS, SPEECH_2, name="other.wav"))


def _scene(strips: list[tuple[str, object, int]]):
    """The BEAT armature and the ARKit face as the panel's character, and sound strips
    (name, file, frame) on channel 1; fast settings."""
    scene = reset_scene()
    ob, face = import_beat_armature(), append_face()
    s = scene.diffsheg
    s.armature, s.preset = ob, "beat"
    s.face_meshes.add().object = face
    s.set_steps, s.steps, s.device = True, 5, "CPU"
    editor = scene.sequence_editor_create()
    for name, path, frame in strips:
        editor.strips.new_sound(name, str(path), channel=1, frame_start=frame)
    return scene, ob, face


def _strip_state(scene) -> list:
    return [(s.name, s.frame_start, s.channel) for s in sound_strips(scene)]


def _first_keys(take: str, ob, face) -> set[float]:
    """The first key frame of every curve of the take, on the armature and on the face."""
    firsts, targets = set(), set()
    for action in bpy.data.actions:
        if takes.is_take(action) and action[takes.TAKE] == take:
            targets.add(action[takes.TARGET])
            for fc in action_fcurves(action, action.slots[0] if len(getattr(action, "slots", ())) else None):
                firsts.add(fc.keyframe_points[0].co[0])
    assert targets == {ob, face.data.shape_keys}, take
    return firsts


def test_one_take_per_strip_keyed_at_the_strips_frame(speech):
    talk, other = speech
    scene, ob, face = _scene([("Line A", talk, 1), ("Line B", other, 200), ("Line C", talk, 500)])
    before = _strip_state(scene)
    assert bpy.ops.diffsheg.generate_strips() == {"FINISHED"}
    assert takes.takes_of([ob, face.data.shape_keys]) == ["other take 1", "talk take 1", "talk take 2"]
    assert _first_keys("talk take 1", ob, face) == {1.0}
    assert _first_keys("other take 1", ob, face) == {200.0}
    assert _first_keys("talk take 2", ob, face) == {500.0}
    assert _strip_state(scene) == before  # no sound strip added (or moved)
    assert (scene.frame_start, scene.frame_end) == (1, 500 + FRAMES - 1)
    s = scene.diffsheg
    assert s.last_report.startswith("3 of 3 sound strips keyed (talk take 1, other take 1, talk take 2)")
    assert not s.last_failed
    details = report_text()
    for name, frame, take in (("Line A", 1, "talk take 1"), ("Line B", 200, "other take 1"),
                              ("Line C", 500, "talk take 2")):
        assert f"strip '{name}' at frame {frame}: {take}: {FRAMES} frames" in details
    assert "style and emotion: the panel's, changed from their frames" in details


BONE = "RightArm"
ROTATION = f'pose.bones["{BONE}"].rotation_euler'


def _sequence(id_data) -> dict[str, tuple[int, str]]:
    """{NLA strip name: (first frame, take)} on the sound-strips tracks of `id_data`."""
    return {s.name: (int(s.frame_start), s.action[takes.TAKE]) for t in id_data.animation_data.nla_tracks
            if t.name.startswith(takes.SEQUENCE_TRACK) for s in t.strips}


def _played(scene, ob, frames) -> np.ndarray:
    """(F, 3) the bone's rotation as the scene plays it (NLA evaluated), at `frames`."""
    played = []
    for frame in frames:
        scene.frame_set(int(frame))
        played.append(tuple(ob.pose.bones[BONE].rotation_euler))
    return np.array(played)


def _keyed(take: str, ob, frames) -> np.ndarray:
    """(F, 3) the bone's rotation as take `take`'s own F-curves give it."""
    action = next(a for a in bpy.data.actions if takes.is_take(a) and a[takes.TAKE] == take
                  and a[takes.TARGET] == ob)
    curves = {fc.array_index: fc for fc in action_fcurves(action, action.slots[0] if len(
        getattr(action, "slots", ())) else None) if fc.data_path == ROTATION}
    return np.array([[curves[i].evaluate(f) for i in range(3)] for f in frames])


def test_every_strips_take_plays_at_its_own_frames_and_a_rerun_replaces_its_line(speech):
    talk, other = speech
    scene, ob, face = _scene([("Line A", talk, 1), ("Line B", other, 200), ("Line C", talk, 500)])
    targets = [ob, face.data.shape_keys]
    assert bpy.ops.diffsheg.generate_strips() == {"FINISHED"}
    lines = {"Line A": (1, "talk take 1"), "Line B": (200, "other take 1"), "Line C": (500, "talk take 2")}
    for target in targets:
        assert target.animation_data.action is None  # the track plays
        assert _sequence(target) == lines
    for frame, take in ((10, "talk take 1"), (210, "other take 1"), (510, "talk take 2")):
        frames = np.arange(frame, frame + 30)
        np.testing.assert_allclose(_played(scene, ob, frames), _keyed(take, ob, frames), atol=1e-5)
        assert takes.first_playing(targets, frame) == take
    after_a = _played(scene, ob, [100])  # between lines the last pose holds
    np.testing.assert_allclose(after_a, _keyed("talk take 1", ob, [FRAMES]), atol=1e-5)

    for strip in sound_strips(scene):
        strip.select = strip.name == "Line B"
    assert bpy.ops.diffsheg.generate_strips(selected_only=True) == {"FINISHED"}
    for target in targets:
        assert _sequence(target) == {**lines, "Line B": (200, "other take 2")}
    assert "other take 1" in takes.takes_of(targets)  # kept in the file, not playing
    frames = np.arange(200, 200 + FRAMES)
    np.testing.assert_allclose(_played(scene, ob, frames), _keyed("other take 2", ob, frames), atol=1e-5)

    assert bpy.ops.diffsheg.use_take(take="other take 1") == {"FINISHED"}  # off the track: plays over it
    assert ob.animation_data.action[takes.TAKE] == "other take 1"
    assert takes.first_playing(targets, 510) == "other take 1"
    assert bpy.ops.diffsheg.use_take(take="talk take 2") == {"FINISHED"}  # on the track: the track plays
    assert ob.animation_data.action is None and scene.frame_current == 500
    assert takes.first_playing(targets, 510) == "talk take 2"


def test_a_range_of_one_line_regenerates_in_its_strip(speech):
    talk, other = speech
    scene, ob, face = _scene([("Line A", talk, 1), ("Line B", other, 200)])
    targets = [ob, face.data.shape_keys]
    assert bpy.ops.diffsheg.generate_strips() == {"FINISHED"}
    frames = np.concatenate([np.arange(1, FRAMES + 1), np.arange(200, 200 + FRAMES)])
    before = _played(scene, ob, frames)
    s = scene.diffsheg
    s.range_mode, s.range_start, s.range_end, s.seed = "FRAMES", 210, 235, 7
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    assert s.last_report.startswith("other take 2: 26 frames"), s.last_report
    for target in targets:
        assert target.animation_data.action is None
        assert _sequence(target) == {"Line A": (1, "talk take 1"), "Line B": (200, "other take 2")}
    after = _played(scene, ob, frames)
    outside = (frames < 210) | (frames > 235)
    np.testing.assert_allclose(after[outside], before[outside], atol=1e-5)
    assert np.abs(after - before).max() > 0.05

    strip = next(st for t in ob.animation_data.nla_tracks if t.name.startswith(takes.SEQUENCE_TRACK)
                 for st in t.strips if st.name == "Line B")
    strip.frame_start_ui = 220  # the animator slid the line in the NLA
    with pytest.raises(RuntimeError, match="NLA strip 'Line B' of take 'other take 2' was moved or scaled: put it "
                                           "back at frame 200"):
        bpy.ops.diffsheg.generate()


def test_a_line_that_fails_keying_leaves_the_track_as_it_was(speech, monkeypatch):
    talk, other = speech
    scene, ob, face = _scene([("Line A", talk, 1), ("Line B", other, 200)])
    targets = [ob, face.data.shape_keys]
    assert bpy.ops.diffsheg.generate_strips() == {"FINISHED"}
    lines, actions = _sequence(ob), sorted(bpy.data.actions.keys())

    def full_disk(*args):
        raise OSError("No space left on device")
    monkeypatch.setattr(takes, "store_source", full_disk)  # after the keys and the NLA strip
    with pytest.raises(RuntimeError, match="0 of 2 sound strips keyed; 2 failed: 'Line A' \\(could not write"):
        bpy.ops.diffsheg.generate_strips()
    assert sorted(bpy.data.actions.keys()) == actions
    for target in targets:
        assert target.animation_data.action is None
        assert len([t for t in target.animation_data.nla_tracks if t.name.startswith(takes.SEQUENCE_TRACK)]) == 1
    assert _sequence(ob) == lines and _sequence(face.data.shape_keys) == {
        "Line A": (1, "talk take 1"), "Line B": (200, "other take 1")}


def test_selected_only_keys_only_the_selected_strips(speech):
    talk, other = speech
    scene, ob, face = _scene([("Line A", talk, 1), ("Line B", other, 200), ("Line C", talk, 500)])
    scene.diffsheg.set_frame_range = False
    scene.frame_start, scene.frame_end = 1, 250
    for strip in sound_strips(scene):
        strip.select = strip.name == "Line B"
    assert bpy.ops.diffsheg.generate_strips(selected_only=True) == {"FINISHED"}
    assert takes.takes_of([ob, face.data.shape_keys]) == ["other take 1"]
    assert _first_keys("other take 1", ob, face) == {200.0}
    assert (scene.frame_start, scene.frame_end) == (1, 250)  # 'Set frame range' off: kept
    assert scene.diffsheg.last_report.startswith("1 of 1 sound strips keyed (other take 1)")
    for strip in sound_strips(scene):
        strip.select = False
    with pytest.raises(RuntimeError, match="no selected sound strips"):
        bpy.ops.diffsheg.generate_strips(selected_only=True)
    assert takes.takes_of([ob, face.data.shape_keys]) == ["other take 1"]


def test_a_strip_whose_file_is_gone_or_packed_fails_by_name_and_the_others_are_keyed(speech, tmp_path):
    talk, other = speech
    gone = cut_speech(tmp_path, SECONDS, SPEECH_2, name="gone.wav")
    packed = cut_speech(tmp_path, SECONDS, SPEECH, name="packed.wav")
    scene, ob, face = _scene([("Line A", talk, 1), ("Lost line", gone, 200), ("Packed line", packed, 300),
                              ("Line C", other, 500)])
    sound_strips(scene)[2].sound.pack()
    gone.unlink()
    before = _strip_state(scene)
    assert bpy.ops.diffsheg.generate_strips() == {"FINISHED"}  # with a warning: two failed
    assert takes.takes_of([ob, face.data.shape_keys]) == ["other take 1", "talk take 1"]
    assert _first_keys("other take 1", ob, face) == {500.0}
    assert _strip_state(scene) == before
    s = scene.diffsheg
    assert s.last_report.startswith("2 of 4 sound strips keyed") and not s.last_failed
    assert s.last_report.endswith("; 2 failed: 'Lost line' (its file gone.wav is missing), 'Packed line' "
                                  "(its sound is packed into the .blend); see DiffSHEG report")
    details = report_text()
    assert (f"strip 'Lost line' at frame 200: FAILED: its file gone.wav is missing: restore it to {tmp_path} "
            "or relink the strip") in details
    assert "strip 'Packed line' at frame 300: FAILED: its sound is packed into the .blend: unpack it" in details


def test_esc_keeps_the_strips_keyed_and_leaves_nothing_of_the_one_under_way(speech, tmp_path):
    """The modal operator's steps (a window's timer cannot run headless): StripsRun keys each
    strip on the main thread as its generation ends; cancel stops the one under way."""
    talk, _ = speech
    long = cut_speech(tmp_path, 20.0, SPEECH_2, name="long.wav")
    scene, ob, face = _scene([("Line A", talk, 1), ("Long line", long, 100)])
    scene.diffsheg.steps = 25
    context = SimpleNamespace(scene=scene)
    run = StripsRun(context)
    assert not run.step(context)  # the first strip generating
    assert run.status().startswith("Strip 1/2: generating")
    run.queue.job.wait()
    assert not run.step(context)  # the first keyed, the second generating
    assert takes.takes_of([ob, face.data.shape_keys]) == ["talk take 1"]
    actions = sorted(bpy.data.actions.keys())
    job = run.queue.job
    while job.fraction == 0.0 and not job.done:
        threading.Event().wait(0.01)
    assert run.status().startswith("Strip 2/2: generating") and 0.5 <= run.queue.fraction < 1.0
    run.queue.cancel.set()
    assert run.status() == "Cancelling..."
    job.wait()
    assert run.step(context)
    line, keyed = run.finish(context)
    assert keyed and line.startswith("cancelled: 1 of 2 sound strips keyed (talk take 1)")
    assert sorted(bpy.data.actions.keys()) == actions  # nothing of the long line
    assert takes.takes_of([ob, face.data.shape_keys]) == ["talk take 1"]
    assert (scene.frame_start, scene.frame_end) == (1, FRAMES)
    assert "strip 'Long line' at frame 100: cancelled while generating: nothing keyed" in report_text()


def test_the_panel_offers_it_where_the_scene_has_sound_strips(speech):
    from test_addon_panel import CHECKBOX, LABEL_COLUMN, draw

    scene, _, _ = _scene([])
    assert not [e for e in draw(DIFFSHEG_PT_generate) if "strips" in str(e)]
    scene.sequence_editor.strips.new_sound("Line A", str(speech[0]), channel=1, frame_start=1)
    drawn = draw(DIFFSHEG_PT_generate)
    names = [e[1] if len(e) > 1 else None for e in drawn]
    button = names.index("diffsheg.generate_strips")
    assert names.index("diffsheg.generate") < button < names.index("strips_selected_only")
    assert len(drawn[button][2]) <= 2 * LABEL_COLUMN  # a whole-width button
    checkbox = drawn[names.index("strips_selected_only")]
    assert len(checkbox[2]) <= CHECKBOX and len(checkbox[4]) <= LABEL_COLUMN
    rna = type(scene.diffsheg).bl_rna.properties["strips_selected_only"]
    assert not rna.default and rna.description[0].isupper()


def test_each_strip_reads_the_style_and_emotion_markers_from_its_own_frame(speech, monkeypatch):
    import diffsheg_core

    talk, other = speech
    scene, ob, face = _scene([("Line A", talk, 1), ("Line B", other, 200)])
    scene.timeline_markers.new("style:calm", frame=1)
    scene.timeline_markers.new("emotion:sad=0.5", frame=150)  # before Line B: how it starts
    scene.timeline_markers.new("emotion:happy", frame=224)     # 1 s into Line B
    made = []
    generate = diffsheg_core.generate
    monkeypatch.setattr(diffsheg_core, "generate", lambda *a, **k: made.append(generate(*a, **k)) or made[-1])
    assert bpy.ops.diffsheg.generate_strips() == {"FINISHED"}
    line_a, line_b = sorted(made, key=lambda m: m.meta["audio_file"] != str(talk))
    assert line_a.meta["style_at"] == [[0.0, {"calm": 1.0}]] and line_a.meta["emotion_at"] == [
        [149 / 24, {"sad": 0.5}], [223 / 24, {"happy": 1.0}]]
    assert line_b.meta["emotion_at"] == [[0.0, {"sad": 0.5}], [1.0, {"happy": 1.0}]]
    assert "style and emotion: the panel's, changed from their frames" in report_text()
    scene.timeline_markers.new("emotion:joyful", frame=300)
    with pytest.raises(RuntimeError, match="timeline marker 'emotion:joyful' at frame 300: unknown emotion"):
        bpy.ops.diffsheg.generate_strips()


def test_use_take_keeps_the_animators_own_action_in_the_file(speech):
    talk, other = speech
    scene, ob, face = _scene([("Line A", talk, 1)])
    assert bpy.ops.diffsheg.generate_strips() == {"FINISHED"}
    mine = bpy.data.actions.new("my blocking")
    ob.animation_data.action = mine  # the animator's own, over the track
    assert bpy.ops.diffsheg.use_take(take="talk take 1") == {"FINISHED"}
    assert ob.animation_data.action is None and mine.use_fake_user  # the track plays; the Action stays
