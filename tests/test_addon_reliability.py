"""The add-on and batch_render.py refuse what cannot work before generating, with messages
that name the file or field and the fix, and leave the scene as it was."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest

from addon_fixtures import (HAS_AUDIO, REPO, append_face, bpy, cut_speech, import_beat_armature, mocap_motion,
                            report_text, reset_scene, scene_state)
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)

import diffsheg_core
from blender_addon.features.generate import CUSTOM_PRESET
from blender_addon.scene.bake import MAX_FRAME, MIN_FRAME, BakeOptions, bake_motion, check_frames
from blender_addon.scene.preset import load_preset
from diffsheg_core.errors import DiffshegError


@pytest.fixture(scope="module")
def speech(tmp_path_factory):
    return cut_speech(tmp_path_factory.mktemp("speech"), seconds=3.0)


def _configure(scene, audio, armature, face, preset="beat", start=1):
    s = scene.diffsheg
    s.audio_path = str(audio)
    s.armature = armature
    s.preset = preset
    s.set_steps, s.steps = True, 3
    s.device = "CPU"
    s.start_at_scene_start = False
    s.start_frame = start
    s.face_meshes.add().object = face
    return s


def _refused(scene, match: str, monkeypatch) -> None:
    """The operator refuses with `match` before generating, and the scene is unchanged."""
    def never(*args, **kwargs):
        raise AssertionError("generated although the settings could be refused up front")

    monkeypatch.setattr(diffsheg_core, "generate", never)
    before = scene_state(scene)
    with pytest.raises(RuntimeError, match=match) as err:
        bpy.ops.diffsheg.generate()
    assert "Traceback" not in str(err.value)
    assert scene_state(scene) == before


def test_a_folder_as_audio_is_named_a_folder(tmp_path, monkeypatch):
    scene = reset_scene()
    _configure(scene, tmp_path, import_beat_armature(), append_face())
    _refused(scene, "is a folder, not an audio file", monkeypatch)


def test_a_start_frame_beyond_blenders_range_is_refused(speech, monkeypatch):
    scene = reset_scene()
    settings = _configure(scene, speech, import_beat_armature(), append_face(), start=MAX_FRAME)
    settings.start_frame = MAX_FRAME
    if settings.start_frame != MAX_FRAME:
        pytest.skip("this Blender's start frame property stops short of its frame range")
    with pytest.raises(RuntimeError, match="outside Blender's frames"):
        bpy.ops.diffsheg.generate()


@pytest.mark.parametrize("start,frames,allowed", [(MIN_FRAME - 1, 1, f"{MIN_FRAME} to {MAX_FRAME}"),
                                                   (MAX_FRAME - 10, 100, f"{MIN_FRAME} to {MAX_FRAME - 99}")])
def test_a_start_frame_outside_blenders_range_is_told_the_range_it_may_take(start, frames, allowed):
    with pytest.raises(DiffshegError, match=f"outside Blender's frames .*: choose a start frame from {allowed}$"):
        check_frames(start, frames)


def test_a_failed_generate_replaces_the_report_of_the_last_run(tmp_path, monkeypatch):
    scene = reset_scene()
    settings = _configure(scene, tmp_path, None, None)  # a folder as the audio
    settings.last_report, settings.last_failed = "keyed 72 frames (13392 keys) into speech", False
    _refused(scene, "is a folder, not an audio file", monkeypatch)
    assert settings.last_failed and "is a folder, not an audio file" in settings.last_report


def test_style_names_that_are_not_text_get_a_menu_and_generate_says_why(speech, tmp_path):
    """The style menu (asked on every redraw) never raises: it offers the style indices;
    Generate names the problem, in the status bar and in the panel."""
    from blender_addon.ui.properties import _style_items
    from diffsheg_core.checkpoints import DEFAULT_WEIGHTS, read_safetensors, write_safetensors

    meta, tensors = read_safetensors(DEFAULT_WEIGHTS, "")
    info = {**json.loads(meta["info"]), "style_names": [1, 2, 3]}
    model = write_safetensors(tensors, {**meta, "info": json.dumps(info)}, tmp_path / "numbered.safetensors")
    scene = reset_scene()
    settings = _configure(scene, speech, import_beat_armature(), append_face())
    settings.model_path = str(model)
    assert [label for _, label, _ in _style_items(settings, bpy.context)] == [
        "Default", "Style 0", "Style 1", "Style 2"]
    before = scene_state(scene)
    with pytest.raises(RuntimeError, match=r"numbered.safetensors: its style names \[1, 2, 3\] are not 3 different "
                                           "names") as err:
        bpy.ops.diffsheg.generate()
    assert "Traceback" not in str(err.value) and scene_state(scene) == before
    assert settings.last_failed and "its style names [1, 2, 3]" in settings.last_report


def test_with_every_sequencer_channel_taken_the_sound_strip_says_how_to_free_one(speech):
    if not HAS_AUDIO:
        pytest.skip("this Blender build has no audio support: no sound strips")
    from blender_addon.scene.sound import CHANNELS, _strips

    scene = reset_scene()
    strips = _strips(scene.sequence_editor_create())
    for channel in range(1, CHANNELS + 1):
        strips.new_sound(f"busy {channel}", str(speech), channel=channel, frame_start=1)
    armature = import_beat_armature()
    before = scene_state(scene)
    with pytest.raises(DiffshegError, match="all 128 channels of the sequencer are in use at frame 1 or later. "
                                            "Free one by deleting or moving a strip in the Video Sequencer"):
        bake_motion(scene, mocap_motion(frames=30), str(speech), BakeOptions(armature=armature))
    assert scene_state(scene) == before


def test_a_preset_without_the_models_layout_is_refused_before_generating(speech, tmp_path, monkeypatch):
    preset = tmp_path / "show_only.json"
    preset.write_text(json.dumps({"name": "show only", "bones": {"smplx": {"neck": "neck"}}}))
    scene = reset_scene()
    settings = _configure(scene, speech, import_beat_armature(), append_face(), preset=CUSTOM_PRESET)
    settings.preset_file = str(preset)
    _refused(scene, "no bone map for the 'beat' layout", monkeypatch)


@pytest.mark.parametrize("jaw,match", [
    ({"bone": "jaw", "degrees": float("nan")}, '"jaw"."degrees" must be a number of degrees'),
    ({"bone": "jaw", "degrees": 1e9}, '"jaw"."degrees" must be a number of degrees between 0 and 90'),
    ({"bone": "jaw", "degrees": "25"}, '"jaw"."degrees"'),
    ({"bone": "jaw", "axis": [0, 0, 0]}, '"jaw"."axis" is zero'),
    ({"bone": "jaw", "axis": "x"}, '"jaw"."axis" must be three numbers'),
    ({"bone": 3}, '"jaw"."bone" must be a name'),
    ({"bone": "jaw", "strength": 2}, "strength"),
])
def test_bad_preset_numbers_name_the_preset_and_the_field(tmp_path, jaw, match):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"name": "mine", "bones": {"beat": {"Neck": "neck"}}, "jaw": jaw}))
    with pytest.raises(DiffshegError, match=match) as err:
        load_preset(str(path))
    assert str(path) in str(err.value) and "compare it with presets/beat.json" in str(err.value)


def test_bad_bone_tables_name_the_joint(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"bones": {"beat": {"Neck": 7}}}))
    with pytest.raises(DiffshegError, match="joint 'Neck' must map to a bone name"):
        load_preset(str(path))


def test_ctrl_c_in_batch_render_is_one_line(speech, tmp_path):
    proc = subprocess.Popen([sys.executable, str(REPO / "batch_render.py"), "--audio", str(speech),
                             "--no-render", "--save", str(tmp_path / "out.blend"), "--steps", "25"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if "generating" in line:
            proc.send_signal(signal.SIGINT)
            break
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    assert "batch_render: cancelled" in err and "Traceback" not in err
    assert not (tmp_path / "out.blend").exists()


def test_a_model_with_a_nan_weight_is_reported_by_name_and_the_scene_kept(speech, tmp_path):
    import numpy as np

    from diffsheg_core.checkpoints import DEFAULT_WEIGHTS, load_model, read_safetensors, write_safetensors

    meta, tensors = read_safetensors(DEFAULT_WEIGHTS, "")
    weight = load_model().weights["encoder_ges.out.weight"].copy()  # stored beside the graphs, as older files do
    weight.flat[0] = np.nan
    damaged = write_safetensors({**tensors, "model.encoder_ges.out.weight": weight}, meta,
                                tmp_path / "damaged.safetensors")
    scene = reset_scene()
    settings = _configure(scene, speech, import_beat_armature(), append_face())
    settings.model_path = str(damaged)
    before = scene_state(scene)
    with pytest.raises(RuntimeError, match="damaged weights in model.encoder_ges.out.weight") as err:
        bpy.ops.diffsheg.generate()
    assert "damaged.safetensors" in str(err.value) and "Traceback" not in str(err.value)
    assert scene_state(scene) == before


def test_a_wav_cut_short_is_keyed_and_the_report_says_so(speech, tmp_path):
    data = speech.read_bytes()
    cut = tmp_path / "cut.wav"
    cut.write_bytes(data[: len(data) // 2])
    scene = reset_scene()
    settings = _configure(scene, cut, import_beat_armature(), append_face())
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}
    assert "1 warning, see DiffSHEG report" in settings.last_report
    assert "warning: " in report_text() and "is cut short" in report_text()
