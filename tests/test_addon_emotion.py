"""Emotion in the add-on (issue 29, item 2): the panel's Emotion menu and Intensity slider
reach generation, timeline markers 'emotion:sad' change it from their frame as style
markers do (a bad one refused, named, before anything runs), a range with Neutral keeps
its take's emotion, Live lays the panel's emotion, the report names the emotion, and a Happy take
keyed onto the ARKit face smiles more than a Neutral one. Real speech, the bundled model
at 5 steps."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

from addon_fixtures import append_face, bpy, cut_speech, import_beat_armature, report_text, reset_scene
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)
from test_addon_panel import Layout

import diffsheg_core
from blender_addon.features import live
from blender_addon.scene.keying import fcurves_of
from blender_addon.ui import panel
from blender_addon.ui.properties import DIFFSHEG_PG_settings
from diffsheg_core import emotion

SMILE = 'key_blocks["mouthSmileLeft"].value'


@pytest.fixture(scope="module")
def speech(tmp_path_factory):
    return cut_speech(tmp_path_factory.mktemp("emotion"), seconds=4.0, name="talk.wav")


def _panel(speech):
    """The BEAT rig and the ARKit face as the panel's character, 5 steps on the CPU."""
    scene = reset_scene(fps=24)
    armature, face = import_beat_armature(), append_face()
    s = scene.diffsheg
    s.audio_path, s.armature, s.preset, s.device = str(speech), armature, "beat", "CPU"
    s.face_meshes.add().object = face
    s.set_steps, s.steps, s.add_sound = True, 5, False
    return scene, s, face


class _Layout(Layout):
    """test_addon_panel's recording layout; each property with whether its row is active."""

    def _child(self, heading=""):
        child = _Layout(self.log, self.use_property_split, heading or self.heading)
        child.active = self.active
        return child

    def prop(self, data, name, text=None, expand=False, **kw):
        self.log.append(("prop", name, self.active))


def _draw(cls) -> list:
    log = []
    cls.draw(SimpleNamespace(layout=_Layout(log)), bpy.context)
    return log


def _record(monkeypatch, name: str) -> list:
    """The settings and results of diffsheg_core's `name` (generate or regenerate), which still runs."""
    made = []
    real = getattr(diffsheg_core, name)

    def wrapped(*args, **kwargs):
        made.append((kwargs["settings"], real(*args, **kwargs)))
        return made[-1][1]

    monkeypatch.setattr(diffsheg_core, name, wrapped)
    return made


def test_the_emotion_menu_is_the_cores_emotions():
    s = reset_scene().diffsheg
    rna = DIFFSHEG_PG_settings.bl_rna.properties
    assert tuple(item.identifier for item in rna["emotion"].enum_items) == emotion.NAMES
    assert [item.name for item in rna["emotion"].enum_items][:2] == ["Neutral", "Happy"]
    assert (s.emotion, s.emotion_intensity) == ("neutral", 1.0)
    intensity = rna["emotion_intensity"]
    assert (intensity.subtype, intensity.hard_min, intensity.hard_max) == ("FACTOR", 0.0, 1.0)
    for name in ("emotion", "emotion_intensity"):
        description = rna[name].description
        assert description[0].isupper() and not description.endswith("."), name


def test_the_panel_draws_emotion_beside_style():
    s = reset_scene().diffsheg
    props = [e[1:] for e in _draw(panel.DIFFSHEG_PT_generate) if e[0] == "prop"]
    at = props.index(("style_mix", False))
    assert props[at + 1: at + 3] == [("emotion", True), ("emotion_intensity", False)]  # greyed out: Neutral
    assert not any(e[0] == "label" and "without emotion" in e[1] for e in _draw(panel.DIFFSHEG_PT_live))
    s.emotion = "sad"
    assert ("prop", "emotion_intensity", True) in _draw(panel.DIFFSHEG_PT_generate)
    assert not any(e[0] == "label" and "without emotion" in e[1] for e in _draw(panel.DIFFSHEG_PT_live))


def test_the_panels_emotion_and_markers_reach_generate_from_their_frame(speech, monkeypatch):
    scene, s, _ = _panel(speech)
    s.emotion, s.emotion_intensity = "sad", 0.6
    s.start_at_scene_start, s.start_frame = False, 11
    scene.timeline_markers.new("emotion:happy=0.5,surprised=0.3", frame=59)  # 2 s after the start frame
    scene.timeline_markers.new("emotion:neutral", frame=83)
    scene.timeline_markers.new("style:calm", frame=1)  # before the start: from the start
    made = _record(monkeypatch, "generate")
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    settings, motion = made[0]
    assert settings.emotion == {"sad": 0.6}
    assert settings.emotion_at == ((2.0, {"happy": 0.5, "surprised": 0.3}), (3.0, {}))
    assert motion.meta["emotion"] == {"sad": 0.6}
    assert "emotion: sad 0.6; from 2 s: happy 0.5, surprised 0.3; from 3 s: neutral" in report_text()
    assert "; from 0 s: calm\n" in report_text()


@pytest.mark.parametrize("name, reason", [
    ("emotion:joyful", "unknown emotion 'joyful': choose one of neutral, happy"),
    ("emotion:sad=2", "the intensity of emotion 'sad' must be a number from 0 to 1"),
    ("emotion:happy=0.8,sad=0.5", "add up to 1.3"),
    ("emotion: ", "names no emotion: rename it like emotion:sad"),
])
def test_a_bad_emotion_marker_is_refused_naming_it_before_anything_runs(speech, monkeypatch, name, reason):
    scene, s, _ = _panel(speech)
    scene.timeline_markers.new(name, frame=30)
    monkeypatch.setattr(diffsheg_core, "generate", lambda *a, **k: pytest.fail("generated"))
    with pytest.raises(RuntimeError, match=re.escape(f"timeline marker '{name}' at frame 30") + ".*" + reason):
        bpy.ops.diffsheg.generate()


def test_a_range_with_neutral_keeps_the_takes_emotion_and_markers_change_it(speech, monkeypatch):
    scene, s, _ = _panel(speech)
    s.emotion, s.emotion_intensity = "angry", 0.8
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    s.emotion, s.range_mode, s.range_start, s.range_end = "neutral", "FRAMES", 30, 70
    made = _record(monkeypatch, "regenerate")
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    settings, motion = made[-1]
    assert (settings.emotion, settings.emotion_at) == (None, None)  # the core keeps the take's
    assert motion.meta["regenerated"][-1]["emotion"] == {"angry": 0.8}
    assert "emotion: angry 0.8" in report_text()
    scene.timeline_markers.new("emotion:sad", frame=49)
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    settings, motion = made[-1]
    assert (settings.emotion, settings.emotion_at) == ({"angry": 0.8}, ((2.0, {"sad": 1.0}),))
    s.emotion = "happy"
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    assert made[-1][0].emotion == {"happy": 0.8}


def test_live_carries_the_panels_emotion_and_follows_it_while_running(speech):
    """Live starts with the panel's emotion; the performer turns the menu to Sad while it
    runs, and the live face shows it from then on (noted in the recording's meta)."""
    import time

    scene, s, face = _panel(speech)
    s.emotion, s.emotion_intensity, s.live_source, s.live_file = "happy", 0.5, "FILE", str(speech)
    s.live_speed, s.live_record = 2.0, False
    run = live.LiveRun(bpy.context).start()
    assert run.session.engine.settings.emotion == {"happy": 0.5}
    brows, deadline = [], time.monotonic() + 30
    key = face.data.shape_keys.key_blocks["browInnerUp"]
    while not run.step():
        assert time.monotonic() < deadline, "the session did not end"
        if run.shown >= 8 and s.emotion == "happy":
            s.emotion, s.emotion_intensity = "sad", 1.0  # while live
        if run.last is not None:
            brows.append((s.emotion, key.value))
        time.sleep(1 / 60)
    run.end(bpy.context)
    (t, spec), = run.session.emotion.changes
    assert spec == {"sad": 1.0} and t > 0
    happy = [v for e, v in brows if e == "happy"]
    sad = [v for e, v in brows if e == "sad"][-5:]  # once eased in
    assert happy and sad and np.mean(sad) > np.mean(happy) + 0.25, (happy, sad)


def test_a_happy_take_smiles_more_than_a_neutral_one(speech):
    scene, s, face = _panel(speech)
    means = {}
    for name in ("neutral", "happy"):
        s.emotion = name
        assert bpy.ops.diffsheg.generate() == {"FINISHED"}
        curve = next(fc for fc in fcurves_of(face.data.shape_keys) if fc.data_path == SMILE)
        means[name] = np.mean([curve.evaluate(f) for f in range(scene.frame_start, scene.frame_end + 1)])
    assert means["happy"] > means["neutral"] + 0.2, means
