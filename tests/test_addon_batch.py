"""batch_render.py end to end, as a user runs it: a folder of two real speech clips,
keyed into a saved scene without rendering, then with a tiny Workbench render."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from addon_fixtures import (HAS_AUDIO, REPO, SPEECH, SPEECH_2, append_face, bpy, cut_speech,
                            import_beat_armature, reset_scene)
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)
from system_tools import require_program

from blender_addon.scene.keying import fcurves_of
from blender_addon.scene.sound import sound_strips


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    folder = tmp_path_factory.mktemp("talks")
    cut_speech(folder, seconds=2.0, source=SPEECH, name="scott.wav")
    cut_speech(folder, seconds=1.5, source=SPEECH_2, name="zhao.wav")
    return folder


@pytest.fixture(scope="module")
def scene_blend(tmp_path_factory):
    scene = reset_scene(fps=12)
    import_beat_armature()
    append_face()
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x, scene.render.resolution_y = 48, 32
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    camera.location, camera.rotation_euler = (0.0, -4.0, 1.2), (1.57, 0.0, 0.0)
    scene.camera = camera
    path = tmp_path_factory.mktemp("scene") / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def _batch(*args, cwd):
    return subprocess.run([sys.executable, str(REPO / "batch_render.py"), *args], cwd=cwd,
                          capture_output=True, text=True, timeout=600)


def test_folder_without_render_saves_keyed_scenes(clips, scene_blend, tmp_path):
    proc = _batch("--blend", str(scene_blend), "--audio", str(clips), "--preset", "beat",
                  "--steps", "5", "--device", "cpu", "--no-render", "--save", str(tmp_path / "saved"),
                  cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "[1/2] scott.wav: generating" in proc.stdout and "[2/2] zhao.wav" in proc.stdout
    for stem, seconds in (("scott", 2.0), ("zhao", 1.5)):
        bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "saved" / f"{stem}.blend"))
        scene = bpy.context.scene
        ob = scene.objects["2_scott_0_1_1"]
        assert ob.animation_data.action.name == f"{stem} take 1"
        curves = fcurves_of(ob)
        assert len(curves) == 3 * (47 + 9) + 3  # Euler bones (the BVH importer's), hips and legs, hips' location
        assert curves[0].keyframe_points[-1].co[0] == round(seconds * 12)
        assert len(fcurves_of(scene.objects["Neutral"].data.shape_keys)) == 51
        # each file from the same start scene; no strip on a Blender without audio support
        assert [s.name for s in sound_strips(scene)] == ([stem] if HAS_AUDIO else [])
    assert not list(tmp_path.glob("*.mp4"))


def test_folder_with_tiny_workbench_render_writes_videos_with_audio(clips, scene_blend, tmp_path):
    ffprobe = require_program("ffprobe", "ffmpeg")
    out = tmp_path / "renders"
    proc = _batch("--blend", str(scene_blend), "--audio", str(clips), "--steps", "5",
                  "--device", "cpu", "--output", str(out), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for stem in ("scott", "zhao"):
        video = out / f"{stem}.mp4"
        assert video.is_file() and video.stat().st_size > 1000
        streams = subprocess.run([ffprobe, "-v", "error", "-show_entries", "stream=codec_type",
                                  "-of", "csv=p=0", str(video)], capture_output=True, text=True).stdout
        assert sorted(streams.split()) == (["audio", "video"] if HAS_AUDIO else ["video"])


def test_failure_is_one_line_and_a_nonzero_exit(scene_blend, tmp_path):
    proc = _batch("--blend", str(scene_blend), "--audio", str(tmp_path / "missing.wav"), cwd=tmp_path)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1].startswith("batch_render: error: ")
    assert "missing.wav" in proc.stderr and "Traceback" not in proc.stderr


def test_inputs_with_the_same_stem_get_outputs_of_their_own(scene_blend, tmp_path):
    import soundfile as sf

    folder = tmp_path / "talks"
    folder.mkdir()
    samples, rate = sf.read(str(cut_speech(tmp_path, seconds=1.0)), dtype="float32")
    sf.write(folder / "talk.wav", samples, rate)
    sf.write(folder / "talk.flac", samples, rate)
    sf.write(folder / "other.wav", samples, rate)
    proc = _batch("--blend", str(scene_blend), "--audio", str(folder), "--preset", "beat", "--steps", "2",
                  "--no-render", "--save", str(tmp_path / "saved"), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "saved").iterdir()) == ["other.blend", "talk_flac.blend",
                                                                       "talk_wav.blend"]


def test_every_generation_option_of_the_panel_is_a_batch_option(scene_blend, tmp_path):
    speech = cut_speech(tmp_path, seconds=1.5)
    proc = _batch("--blend", str(scene_blend), "--audio", str(speech), "--preset", "beat", "--steps", "3",
                  "--overlap", "6", "--style", "0", "--guidance", "1.5", "--gesture-energy", "0.2",
                  "--smoothing", "1", "--candidates", "2", "--face-seed", "3", "--start-frame", "10",
                  "--max-error", "0.5", "--max-face-error", "0.01", "--no-render", "--save", str(tmp_path / "all.blend"), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "all.blend").is_file()
    bad = _batch("--blend", str(scene_blend), "--audio", str(speech), "--gesture-energy", "3", "--no-render",
                 cwd=tmp_path)
    assert bad.returncode == 1 and "gesture energy) must be a number from 0 to 1" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_the_25_step_sampling_stays_selectable_as_sampling_quality(scene_blend, tmp_path):
    """Issue 39, item 5: --sampling quality reaches generation (the model's own 25 steps), the
    default is fast (by the bundled model's distilled student); the report (the saved .blend's
    Text, --report) says which."""
    speech = cut_speech(tmp_path, seconds=1.0)
    for option, said in (([], "sampling: fast, 5 steps, by the distilled student"),
                         (["--sampling", "quality"], "sampling: quality, 25 steps")):
        report = tmp_path / f"{said[10:14]}.txt"
        proc = _batch("--blend", str(scene_blend), "--audio", str(speech), "--preset", "beat", "--device", "cpu",
                      *option, "--no-render", "--report", str(report), cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert said in report.read_text(encoding="utf-8").splitlines(), report.read_text(encoding="utf-8")
    bad = _batch("--blend", str(scene_blend), "--audio", str(speech), "--sampling", "slow", "--no-render",
                 cwd=tmp_path)
    assert bad.returncode == 2 and "--sampling: invalid choice: 'slow'" in bad.stderr and "quality" in bad.stderr


def test_the_bundled_model_is_an_input_of_a_batch(scene_blend, tmp_path):
    import hashlib

    from diffsheg_core.checkpoints import DEFAULT_WEIGHTS

    before = hashlib.sha256(DEFAULT_WEIGHTS.read_bytes()).hexdigest()
    backup = shutil.copy(DEFAULT_WEIGHTS, tmp_path / "backup.safetensors")  # restored if the refusal fails
    try:
        proc = _batch("--blend", str(scene_blend), "--audio", str(cut_speech(tmp_path, seconds=1.0)),
                      "--no-render", "--save", str(DEFAULT_WEIGHTS), cwd=tmp_path)
    finally:
        if hashlib.sha256(DEFAULT_WEIGHTS.read_bytes()).hexdigest() != before:
            shutil.copy(backup, DEFAULT_WEIGHTS)
            pytest.fail("--save overwrote the bundled model (restored from a copy)")
    assert proc.returncode == 1 and "is an input of this run" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_regenerate_a_range_of_a_saved_take_keeping_the_face(scene_blend, tmp_path):
    """A take saved by one batch, then --regenerate 20-60 --hold-face on that file: a new
    take plays, the frames outside the range and the whole face evaluate as before."""
    talk = cut_speech(tmp_path, seconds=8.0, name="talk.wav")
    first = tmp_path / "first.blend"
    assert _batch("--blend", str(scene_blend), "--audio", str(talk), "--preset", "beat", "--device", "cpu",
                  "--no-render", "--save", str(first), cwd=tmp_path).returncode == 0
    for bad, match in ((["--regenerate", "60-20"], "START <= END"), (["--hold-face"], "goes with --regenerate"),
                       (["--regenerate", "20-60", "--audio", str(talk)], "leave out --audio"),
                       (["--regenerate", "90-200"], "within the take's frames 1-96")):
        proc = _batch("--blend", str(first), "--preset", "beat", "--no-render", *bad, cwd=tmp_path)
        assert proc.returncode != 0 and match in proc.stderr, (bad, proc.stderr[-500:])
    second = tmp_path / "second.blend"
    proc = _batch("--blend", str(first), "--regenerate", "20-60", "--hold-face", "--seed", "4", "--preset", "beat",
                  "--device", "cpu", "--no-render", "--save", str(second), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "talk take 1 frames 20-60: talk take 2:" in proc.stdout

    def curves(path):
        bpy.ops.wm.open_mainfile(filepath=str(path))
        objects = bpy.context.scene.objects
        body, face = objects["2_scott_0_1_1"], objects["Neutral"].data.shape_keys
        return body.animation_data.action.name, *[
            {(fc.data_path, fc.array_index): [fc.evaluate(f) for f in range(1, 97)] for fc in fcurves_of(t)}
            for t in (body, face)]

    (take1, body1, face1), (take2, body2, face2) = curves(first), curves(second)
    assert (take1, take2) == ("talk take 1", "talk take 2")
    for path, values in face1.items():
        assert max(abs(a - b) for a, b in zip(values, face2[path])) < 1e-5, path
    outside = [i for i in range(96) if not 19 <= i <= 59]
    moved = 0.0
    for path, values in body1.items():
        assert max(abs(values[i] - body2[path][i]) for i in outside) < 1e-5, path
        moved = max(moved, max(abs(a - b) for a, b in zip(values, body2[path])))
    assert moved > 0.05


def test_the_saved_scene_holds_the_report_and_the_console_gets_one_short_line(scene_blend, tmp_path):
    """Issue 41, item 6: the saved .blend has the Text 'DiffSHEG report' (model, style,
    Actions, warnings), --report FILE holds it too, each take prints one line of at most 120
    characters; a negative start frame with the scene's range is refused by name, and keys
    before frame 0 with --keep-frame-range."""
    speech = cut_speech(tmp_path, seconds=1.0)
    proc = _batch("--blend", str(scene_blend), "--audio", str(speech), "--preset", "beat", "--steps", "2",
                  "--no-render", "--save", str(tmp_path / "take.blend"), "--report", str(tmp_path / "take.txt"),
                  cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    done = [l for l in proc.stdout.splitlines() if " frames, " in l and " keys, " in l]
    assert len(done) == 1 and len(done[0]) <= 120, proc.stdout
    assert all(len(l) <= 120 for l in proc.stdout.splitlines()), proc.stdout
    details = (tmp_path / "take.txt").read_text(encoding="utf-8")
    assert "model: diffsheg-default" in details and "actions: " in details
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "take.blend"))
    assert bpy.data.texts["DiffSHEG report"].as_string() == details

    refused = _batch("--blend", str(scene_blend), "--audio", str(speech), "--preset", "beat", "--steps", "2",
                     "--no-render", "--start-frame", "-100", "--save", str(tmp_path / "neg.blend"), cwd=tmp_path)
    assert refused.returncode == 1 and "Traceback" not in refused.stderr
    assert "start frame -100 is before frame 0" in refused.stderr and "--keep-frame-range" in refused.stderr
    assert not (tmp_path / "neg.blend").exists()
    kept = _batch("--blend", str(scene_blend), "--audio", str(speech), "--preset", "beat", "--steps", "2",
                  "--no-render", "--start-frame", "-100", "--keep-frame-range", "--save", str(tmp_path / "neg.blend"),
                  cwd=tmp_path)
    assert kept.returncode == 0, kept.stderr[-2000:]
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "neg.blend"))
    curves = fcurves_of(bpy.context.scene.objects["2_scott_0_1_1"])
    assert curves[0].keyframe_points[0].co[0] == -100
