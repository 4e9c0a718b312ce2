"""Live in Blender (issue 27, item 4), headless with real speech and real rigs: the character
posed from the stream as it arrives (the BEAT BVH rig in Euler XYZ, the Ready Player Me
avatar in quaternions, the ARKit face), nothing keyed while live, the pose back on Stop,
Record making a take Generate could have made (GENERATED keys, its source stored, the
recorded audio as a sound strip, a range of it regenerated), VMC out to a real OSC
listener, and sources that fail as reports that change nothing.

A headless Blender has no event loop for the modal operator's timer: the tests call the
tick (`LiveRun.step`) in a loop with sleeps, as the timer would, or run the operator's
blocking `execute`, which does the same. Files play at 2x real time to keep this short.
"""

from __future__ import annotations

import re
import socket
import struct
import threading
import tempfile
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from addon_fixtures import (HAS_AUDIO, REPO, append_face, bpy, cut_speech, import_beat_armature,
                            import_readyplayerme, mocap_motion, reset_scene, scene_state)
from addon_fixtures import exit_before_blender_teardown  # noqa: F401 (fixture)

from blender_addon.environment import microphone_problem
from blender_addon.features import live
from blender_addon.scene import takes
from blender_addon.scene.bake import BakeOptions, bake_motion
from blender_addon.scene.keying import action_fcurves, fcurves_of
from blender_addon.scene.retarget import bone_quaternions
from diffsheg_core.audio import n_motion_frames, read_audio_file
from diffsheg_core.errors import DiffshegError

pytestmark = pytest.mark.blender

SPEED = 2.0


@pytest.fixture(scope="module")
def speech(tmp_path_factory):
    return cut_speech(tmp_path_factory.mktemp("live"), 3.0)


def _beat_scene(speech, record: bool):
    """The BEAT armature and the ARKit face as the panel's character, Live from `speech`."""
    scene = reset_scene()
    ob, face = import_beat_armature(), append_face()
    s = scene.diffsheg
    s.armature, s.preset, s.device = ob, "beat", "CPU"
    s.face_meshes.add().object = face
    s.live_source, s.live_file, s.live_speed, s.live_record = "FILE", str(speech), SPEED, record
    return scene, ob, face


def _keys(targets) -> dict:
    """Every key of the Actions the targets play, and which Actions they are."""
    out = {}
    for t in targets:
        for fc in fcurves_of(t):
            co = np.empty(2 * len(fc.keyframe_points), dtype=np.float32)
            fc.keyframe_points.foreach_get("co", co)
            out[(t.name, fc.data_path, fc.array_index)] = co.tobytes()
    return out


def _pose(ob, face, bones) -> np.ndarray:
    """The bones' rotations (as quaternions, whatever their mode) and the face's shape-key values."""
    quats = [np.array(ob.pose.bones[b].matrix_basis.to_quaternion()) for b in bones]
    quats = [q if q[0] >= 0 else -q for q in quats]
    values = [kb.value for kb in face.data.shape_keys.key_blocks[1:]]
    return np.concatenate([np.ravel(quats), values])


class _OscListener:
    """A real python-osc server on 127.0.0.1 keeping the addresses of the messages it gets."""

    def __init__(self):
        from pythonosc.dispatcher import Dispatcher
        from pythonosc.osc_server import BlockingOSCUDPServer

        self.addresses: list[str] = []
        dispatcher = Dispatcher()
        dispatcher.set_default_handler(lambda address, *values: self.addresses.append(address))
        self.server = BlockingOSCUDPServer(("127.0.0.1", 0), dispatcher)
        self.port = self.server.server_address[1]
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def test_live_poses_the_character_from_the_stream_keys_nothing_and_stop_puts_the_take_back(speech):
    """A take playing (real mocap keyed); Live without Record poses bones and face from the
    stream at every tick, each pose the frame shown through keying's own mapping (also when
    the timeline moves), sends each frame over VMC, writes no key and changes no Action; Stop
    puts the take's pose back."""
    scene, ob, face = _beat_scene(speech, record=False)
    options = BakeOptions(armature=ob, face_meshes=[face], preset=None, add_sound=False)
    bake_motion(scene, mocap_motion(60), None, options)
    scene.frame_set(20)
    listener = _OscListener()
    scene.diffsheg.live_vmc, scene.diffsheg.live_vmc_address = True, f"127.0.0.1:{listener.port}"
    bones = ["Spine", "Neck", "RightArm", "LeftForeArm", "RightHandIndex1"]
    before_state, before_keys = scene_state(scene), _keys([ob, face.data.shape_keys])
    before_pose = _pose(ob, face, bones)

    run = live.LiveRun(bpy.context).start()
    assert live.current() is run and not bpy.ops.diffsheg.live_start.poll()
    shown = []
    frames_due = run.session.frames_due
    run.session.frames_due = lambda now=None: shown.append(frames_due(now)) or shown[-1]
    poses, checked, hips = [], 0, []
    hips_before = np.array(ob.pose.bones["Hips"].location)
    try:
        deadline = time.monotonic() + 20
        while len(poses) < 12 and not run.step():  # Stop before the file ends
            assert time.monotonic() < deadline, "no frames came"
            if shown[-1]:
                poses.append(_pose(ob, face, bones))
                hips.append(np.array(ob.pose.bones["Hips"].location))
                frame = shown[-1][-1]
                if checked < 3:  # the pose is the newest frame, retargeted as keying would
                    motion = replace(run.poser.template, rotations=frame.rotations[None], face=frame.face[None])
                    expected = bone_quaternions(motion, run.poser.targets.armature)
                    for bone in bones:
                        q = np.array(ob.pose.bones[bone].matrix_basis.to_quaternion())
                        assert abs(abs(float(q @ expected[bone][0])) - 1.0) < 1e-4, bone
                    checked += 1
                assert _keys([ob, face.data.shape_keys]) == before_keys
            time.sleep(1 / 60)
        assert run.status().startswith(f"Live, file {speech.name} at 2x: ") and run.last is not None
        live_pose = _pose(ob, face, bones)
        scene.frame_set(40)  # the timeline moves: the take is evaluated, then the live frame posed over it
        np.testing.assert_allclose(_pose(ob, face, bones), live_pose, atol=1e-6)
        scene.frame_set(20)
        run.request_stop()
        while not run.step():
            time.sleep(0.01)
        outcome = run.end(bpy.context)
        sent = sum(len(f) for f in shown)
        deadline = time.monotonic() + 2.0  # the listener's thread reads the last datagrams
        while listener.addresses.count("/VMC/Ext/Blend/Apply") < sent and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        listener.close()
    assert live.current() is None
    assert checked == 3 and len(poses) == 12
    poses = np.array(poses)
    steps = np.abs(np.diff(poses, axis=0)).max(axis=1)
    assert np.mean(steps > 1e-4) > 0.8  # a new pose at (nearly) every frame shown
    face_values = poses[:, 4 * len(bones):]
    assert (face_values.max(axis=0) - face_values.min(axis=0)).max() > 0.1  # the face moves too
    assert np.abs(poses - before_pose).max() > 0.1  # not the take's pose

    assert outcome.take is None and outcome.level == "INFO" and "not recorded (Record is off)" in outcome.line
    assert scene_state(scene) == before_state and _keys([ob, face.data.shape_keys]) == before_keys
    np.testing.assert_allclose(_pose(ob, face, bones), before_pose, atol=1e-6)  # the take's pose again
    # the whole body: the hips shift their weight live (the stream's lower body), and are put back
    assert np.ptp(np.array(hips), axis=0).max() > 1e-3
    np.testing.assert_allclose(np.array(ob.pose.bones["Hips"].location), hips_before, atol=1e-6)
    assert listener.addresses.count("/VMC/Ext/Blend/Apply") == sent > 0  # every frame shown, over VMC
    assert listener.addresses.count("/VMC/Ext/Bone/Pos") > 40 * sent


@pytest.mark.parametrize("catch_up", [1, 4], ids=["as-made", "catching-up"])
def test_live_plants_the_feet_on_the_ready_player_me_avatar(speech, catch_up):
    """Whole body live on a rig with other proportions than the canonical body: the hips
    move, and a foot the stream says is down stays where it landed on the rig's own legs
    (feet.LiveFeet) over every run of frames made with it down: within 2 mm (the issue asks
    for 1 cm; unpinned on the rig, the same frames drift 0.82 cm). A tick that catches up (a
    loaded machine, here `catch_up` frames at a time) poses only the newest frame due; a foot
    that stepped in the frames it passed over lands anew, not pulled back to where it stood."""
    scene = reset_scene()
    rig, faces = import_readyplayerme()
    s = scene.diffsheg
    s.armature, s.device = rig, "CPU"
    s.live_source, s.live_file, s.live_speed, s.live_record = "FILE", str(speech), SPEED, False
    run = live.LiveRun(bpy.context).start()
    shown, waiting = [], []
    frames_due = run.session.frames_due

    def due(now=None):
        waiting.extend(frames_due(now))
        batch = waiting[:] if len(waiting) >= catch_up or run.session.done else []
        del waiting[:len(batch)]
        shown.append(batch)
        return batch

    run.session.frames_due = due
    ankles, downs, hips = [], [], []
    try:
        deadline = time.monotonic() + 30
        while not run.step():
            assert time.monotonic() < deadline, "the session did not end"
            if run.finishing is None and shown and shown[-1]:
                bpy.context.view_layer.update()
                ankles.append({side: np.array(rig.matrix_world @ rig.pose.bones[f"{side.capitalize()}Foot"].head)
                               for side in ("right", "left")})
                # per side: down in every frame made since the last tick, in the one posed, and how many
                downs.append({side: (all(f.feet_down[side] for f in shown[-1]), shown[-1][-1].feet_down[side],
                                     len(shown[-1])) for side in ("right", "left")})
                hips.append(np.array(rig.pose.bones["Hips"].location))
            time.sleep(1 / 60)
        run.end(bpy.context)
    finally:
        if live.current() is run:
            run.end(bpy.context)
    assert sum(down["right"][2] for down in downs) > 10 and np.ptp(np.array(hips), axis=0).max() > 1e-3
    worst, held = 0.0, 0
    for side in ("right", "left"):
        landed = None
        for ankle, down in zip(ankles, downs):
            stayed, posed, frames = down[side]
            if stayed and landed is not None:
                worst, held = max(worst, float(np.linalg.norm(ankle[side] - landed))), held + frames
            else:  # landed in the frames of this tick, or up
                landed = ankle[side] if posed else None
    print(f"live, Ready Player Me: a planted foot moves at most {100 * worst:.2f} cm from where it landed")
    assert held > 10 and worst < 0.002


@pytest.mark.skipif(not HAS_AUDIO, reason="this Blender has no audio support: no sound strips")
def test_record_makes_a_take_as_generate_would_that_can_be_regenerated_in_ranges(speech, tmp_path):
    """The Ready Player Me avatar, Live from a file through the operator (its blocking run),
    the .blend saved: the take is keyed from the frame Live started on with GENERATED keys,
    keeps its source (the motion, the recorded audio beside the .blend), plays the audio as a
    sound strip, and a range of it is generated anew."""
    scene = reset_scene()
    rig, faces = import_readyplayerme()
    s = scene.diffsheg
    s.armature, s.device = rig, "CPU"
    for mesh in faces:
        s.face_meshes.add().object = mesh
    s.live_source, s.live_file, s.live_speed, s.live_hop = "FILE", str(speech), SPEED, 4
    assert s.live_record  # on by default
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    scene.frame_set(50)

    assert bpy.ops.diffsheg.live_start("EXEC_DEFAULT") == {"FINISHED"}
    assert s.last_report.startswith("live_001 take 1: recorded live, 3.0 s, 72 frames") and not s.last_failed
    targets = [rig] + [m.data.shape_keys for m in faces]
    assert takes.takes_of(targets) == ["live_001 take 1"]
    actions = [a for a in bpy.data.actions if takes.is_take(a)]
    assert {a[takes.TARGET] for a in actions} == set(targets)
    for action in actions:
        for fc in action_fcurves(action, action.slots[0] if len(getattr(action, "slots", ())) else None):
            types = {k.type for k in fc.keyframe_points}
            assert types == {"GENERATED"} and fc.keyframe_points[0].co[0] == 50.0, fc.data_path
    assert {fc.data_path.split('"')[1] for fc in fcurves_of(rig)} >= {"Spine", "Neck", "RightArm", "LeftHand",
                                                                      "Hips", "LeftUpLeg", "RightLeg", "LeftFoot"}
    assert 'pose.bones["Hips"].location' in {fc.data_path for fc in fcurves_of(rig)}  # legs live, recorded

    source = takes.source_of("live_001 take 1")
    wav = tmp_path / "live" / "live_001.wav"
    assert source.audio_path == str(wav) and source.start_frame == 50
    recorded = read_audio_file(wav)
    assert abs(recorded.duration - 3.0) < 0.1
    assert source.motion.fps == 15 and n_motion_frames(recorded, 15) == source.motion.n_frames == 45
    assert source.motion.meta["live"]["hop"] == 4 and source.motion.meta["audio_file"] == str(wav)
    (strip,) = [st for st in scene.sequence_editor.strips if st.type == "SOUND"]
    assert strip.frame_start == 50 and bpy.path.abspath(strip.sound.filepath) == str(wav)

    s.range_mode, s.range_start, s.range_end = "FRAMES", 70, 100
    s.set_steps, s.steps = True, 5
    assert bpy.ops.diffsheg.generate() == {"FINISHED"}, s.last_report
    assert takes.takes_of(targets) == ["live_001 take 1", "live_001 take 2"]


def test_a_source_that_fails_is_a_report_and_changes_nothing(speech, tmp_path):
    """A missing file, a file that is not audio, no character, a busy port, an unusable
    microphone: each refused before anything changes, with the reason in the status bar."""
    scene, ob, face = _beat_scene(speech, record=True)
    state, pose = scene_state(scene), _pose(ob, face, ["Spine", "RightArm"])
    s = scene.diffsheg

    def refused(reason: str) -> None:
        """The operator reports `reason` as an error (bpy.ops raises it), in the panel too."""
        with pytest.raises(RuntimeError, match=re.escape(reason)) as err:
            bpy.ops.diffsheg.live_start()
        assert "Traceback" not in str(err.value) and reason in s.last_report and s.last_failed

    for path, reason in ((tmp_path / "gone.wav", "does not exist"),
                         (REPO / "README.md", "could not be decoded as audio")):
        s.live_file = str(path)
        refused(reason)
    s.live_file = str(speech)
    s.armature = None
    s.face_meshes.clear()
    refused("no target: choose an armature and/or a face mesh in the panel")
    s.armature = ob
    s.face_meshes.add().object = face

    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    s.live_source, s.live_port = "SOCKET", busy.getsockname()[1]
    try:
        with pytest.raises(DiffshegError, match=f"cannot listen on tcp://127.0.0.1:{s.live_port}"):
            live.LiveRun(bpy.context).start()
    finally:
        busy.close()
    assert live.current() is None

    s.live_source = "MIC"
    problem = microphone_problem()
    if problem is not None:  # this machine has no usable microphone: Start says why
        with pytest.raises(DiffshegError, match=re.escape(problem.split(":")[0])):
            live.LiveRun(bpy.context)
    refused("from a file only")  # a script (no modal timer) runs a file to its end
    assert scene_state(scene) == state and live.current() is None
    np.testing.assert_allclose(_pose(ob, face, ["Spine", "RightArm"]), pose)


def test_a_socket_producer_that_breaks_off_keeps_what_was_performed(speech, tmp_path, monkeypatch):
    """A producer sends real speech over the socket at real time, then its connection is reset:
    the session ends by itself, the report says why, and Record keeps what was performed (in
    the temporary folder, the .blend being unsaved, which the report says too). The session ran
    the panel's Hop with live's other defaults (its recording says so)."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    scene, ob, face = _beat_scene(speech, record=True)
    s = scene.diffsheg
    s.live_source, s.live_hop = "SOCKET", 3
    with socket.socket() as probe:  # a free port
        probe.bind(("127.0.0.1", 0))
        s.live_port = probe.getsockname()[1]
    audio = read_audio_file(speech)
    assert audio.sample_rate == live.SOCKET_RATE
    pcm = (np.clip(audio.samples[: int(1.5 * audio.sample_rate)], -1, 1) * 32767).astype("<i2")
    run = live.LiveRun(bpy.context).start()

    def produce():
        conn = socket.create_connection(("127.0.0.1", s.live_port))
        chunk = audio.sample_rate // 50
        for i in range(0, len(pcm), chunk):
            conn.sendall(pcm[i:i + chunk].tobytes())
            time.sleep(0.02)
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        conn.close()  # a reset, not a clean end

    producer = threading.Thread(target=produce, daemon=True)
    producer.start()
    deadline = time.monotonic() + 20
    while not run.step():
        assert time.monotonic() < deadline
        time.sleep(1 / 60)
    producer.join()
    outcome = run.end(bpy.context)
    assert outcome.take == "live_001 take 1" and outcome.level == "WARNING"
    assert "see DiffSHEG report" in outcome.line
    report = bpy.data.texts["DiffSHEG report"].as_string()
    assert report.splitlines()[0] == outcome.line  # the report opens with the status line
    counted = int(re.search(r"(\d+) warnings?, see DiffSHEG report", outcome.line).group(1))
    assert counted == len(report.split("\nwarnings:\n")[1].strip().splitlines())  # and lists as many warnings
    assert "was reset in the middle of the stream" in report
    wav = tmp_path / "diffsheg_live" / "live_001.wav"
    assert f"its audio is in the temporary folder ({wav})" in report
    assert takes.source_of(outcome.take).audio_path == str(wav)
    assert 1.3 < read_audio_file(wav).duration <= 1.55
    from diffsheg_core.live.engine import LiveConfig

    default = LiveConfig()
    recorded = takes.source_of(outcome.take).motion.meta["live"]
    assert (recorded["hop"], recorded["lookahead"], recorded["through_lookahead"], recorded["match_velocity"]) \
        == (3, default.lookahead, True, True)
    assert takes.source_of(outcome.take).motion.meta["candidates"] == 1  # the panel's: live takes the settings'


def test_quitting_right_after_a_session_is_discarded_does_not_abort(speech, tmp_path):
    """Blender ends a running session (a file opened, the window closed) and quits at once:
    the process exits cleanly (the runtime was torn down under the session's threads: abort)."""
    import subprocess
    import sys

    script = tmp_path / "discard.py"
    script.write_text(f"""
import sys, time
sys.path.insert(0, {str(REPO / "tests")!r})
from addon_fixtures import bpy, import_readyplayerme, reset_scene
from blender_addon.features import live
s = reset_scene().diffsheg
s.armature, s.device = import_readyplayerme()[0], "CPU"
s.live_source, s.live_file, s.live_speed, s.live_record = "FILE", {str(speech)!r}, 2.0, False
run = live.LiveRun(bpy.context).start()
for _ in range(30):
    run.step()
    time.sleep(1 / 60)
run.discard(restore=True)
""")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_one_session_at_a_time_and_undo_ends_it(speech):
    scene, ob, face = _beat_scene(speech, record=True)
    state = scene_state(scene)
    run = live.LiveRun(bpy.context).start()
    try:
        with pytest.raises(DiffshegError, match="a live session is running already"):
            live.LiveRun(bpy.context)
        assert bpy.ops.diffsheg.live_stop.poll() and not bpy.ops.diffsheg.live_start.poll()
        live._data_replaced()  # what undo, redo and opening a file call
        assert run.discarded and live.current() is None
    finally:
        if live.current() is not None:
            run.discard(restore=True)
    while not run.step():
        time.sleep(0.01)
    assert scene_state(scene) == state


def test_the_live_panel_and_the_preferences():
    from test_addon_panel import CHECKBOX, LABEL_COLUMN, Layout, draw

    from blender_addon.ui import preferences
    from blender_addon.ui.panel import DIFFSHEG_PT_live
    from blender_addon.ui.properties import DIFFSHEG_PG_settings, LIVE_HOP, LIVE_HOPS
    from diffsheg_core.live.engine import HOPS, LiveConfig

    s = reset_scene().diffsheg
    assert DIFFSHEG_PT_live.bl_parent_id == "DIFFSHEG_PT_generate" and "DEFAULT_CLOSED" in DIFFSHEG_PT_live.bl_options
    assert (LIVE_HOP, LIVE_HOPS) == (LiveConfig.hop, HOPS)
    assert (s.live_source, s.live_port, s.live_speed, s.live_record, s.live_vmc) == ("MIC", 5005, 1.0, True, False)
    rna = DIFFSHEG_PG_settings.bl_rna.properties
    shown = {}
    for source in ("MIC", "FILE", "SOCKET"):
        s.live_source = source
        drawn = draw(DIFFSHEG_PT_live)
        shown[source] = [e[1] for e in drawn if e[0] == "prop"]
        assert [e[1:] for e in drawn if e[0] == "operator"] == [("diffsheg.live_start", "Start Live")]
        for kind, *rest in drawn:
            if kind != "prop":
                continue
            name, text, split, heading = rest
            label = rna[name].name if text is None else text
            assert len(heading) <= LABEL_COLUMN and len(label) <= (CHECKBOX if rna[name].type == "BOOLEAN"
                                                                    else LABEL_COLUMN), (name, label)
            description = rna[name].description
            assert description[0].isupper() and not description.endswith("."), name
    assert shown["FILE"][:3] == ["live_source", "live_file", "live_speed"]
    assert shown["SOCKET"][:2] == ["live_source", "live_port"] and "live_mic" in shown["MIC"]
    assert {"live_hop", "live_record", "live_vmc"} <= set(shown["MIC"]) and "live_vmc_address" not in shown["MIC"]
    s.live_vmc = True  # the address, on a row of its own, the whole width: it is read whole
    assert [e[1:4] for e in draw(DIFFSHEG_PT_live) if e[1] == "live_vmc_address"] == [("live_vmc_address", "To", False)]

    problem = microphone_problem()
    s.live_source = "MIC"
    labels = " ".join(e[1] for e in draw(DIFFSHEG_PT_live) if e[0] == "label")
    log = []
    preferences.draw_microphone(Layout(log), SimpleNamespace(region=None))
    in_preferences = " ".join(e[1] for e in log)
    if problem is None:
        assert in_preferences == "Live: a microphone can be used"
    else:
        assert labels == problem[0].upper() + problem[1:]
        assert in_preferences == f"Live cannot use a microphone: {problem}"


def test_live_feet_lower_the_hips_for_a_straight_leg_and_land_anew_after_a_passed_step():
    """feet.LiveFeet on a straight leg (thigh and shin 0.45 each, the ankle right under the hip):
    the hips rising 1 cm under a planted foot come down again as far as the leg needs, with the
    ankle kept where it landed; a foot up in a frame a catching-up tick passed over lands anew
    where the stream put it, not where it stood before the step."""
    from blender_addon.scene.feet import REACH, LiveFeet, _pose
    from blender_addon.scene.retarget import LegRig

    eye = np.eye(3)
    leg = LegRig(side="left", bones=("thigh", "shin", "foot"), rest=(eye, eye, eye, eye),
                 heads=np.array([[0.0, 0, 1.0], [0.1, 0, 0.95], [0.1, 0, 0.5], [0.1, 0, 0.05]]),
                 left=np.array([1.0, 0, 0]))
    still = {name: np.array([[1.0, 0, 0, 0]]) for name in ("hips", "thigh", "shin", "foot")}

    def ankle(displacement, legs):
        return _pose(leg, displacement, {**still, **legs})[1][3][0]

    feet = LiveFeet(15.0)
    legs, lowered = feet.solve([leg], np.zeros((1, 3)), still, "hips", {"left": True}, 0)
    landed = ankle(np.zeros((1, 3)), {})
    assert np.allclose(ankle(lowered, legs), landed, atol=1e-6)
    risen = np.array([[0.0, 0.0, 0.01]])
    legs, lowered = feet.solve([leg], risen, still, "hips", {"left": True}, 1)
    assert np.linalg.norm(ankle(lowered, legs) - landed) < 1e-4  # without the drop: 1 cm short
    assert 0.0105 < risen[0, 2] - lowered[0, 2] < 0.0115 and np.allclose(lowered[0, :2], 0)
    assert np.linalg.norm(ankle(lowered, legs) - (lowered[0] + leg.heads[1])) <= REACH * 0.9 + 1e-6

    feet.passed({"left": False})  # frame 2 was made with the foot up, and not shown
    moved = np.array([[0.2, 0.0, 0.0]])
    legs, lowered = feet.solve([leg], moved, still, "hips", {"left": True}, 3)
    assert np.linalg.norm(ankle(lowered, legs) - (landed + moved[0])) < 1e-3
