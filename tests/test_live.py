"""Live generation end to end on real speech: the `live` CLI at real time with a recording,
a latency log and VMC out to a real OSC listener; a socket producer that stalls, that
closes, that breaks and that sends faster than real time. Speed goals live in
bench/bench_live.py, not here."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from conftest import blas_threads

from diffsheg_core.audio import (MEL_N_FFT, MEL_RATE, Audio, mel_frames, n_motion_frames, read_audio_file,
                                  samples_for_mel_frame)
from diffsheg_core.errors import DiffshegError
from diffsheg_core.checkpoints import load_model
from diffsheg_core.live.engine import LiveConfig, LiveEngine
from diffsheg_core.live.session import LiveSession
from diffsheg_core.live.sources import FileSource, TcpSource
from diffsheg_core.lower_body import JOINTS as LEG_JOINTS, foot_positions, lower_rotations
from diffsheg_core.motion import Motion
from diffsheg_core.pipeline import generate
from diffsheg_core.runtime.backends import open_network
from diffsheg_core.settings import GenerateSettings
from diffsheg_core.training.metrics.channels import face_channel, mouth_opening
from diffsheg_core.training.metrics.lipsync import envelope_correlation

ROOT = Path(__file__).resolve().parents[1]
SPEECH = ROOT.parent / "shared" / "data" / "beat2" / "2_scott_0_1_1.wav"
FIXED_HOP = LiveConfig(max_hop=LiveConfig().hop)
"""Live with its hop held whatever the machine's speed: frame for frame the same motion
from the same speech and seed (a session that widens its hop to keep up samples other
windows on a busier machine), for tests that compare two sessions."""


@pytest.fixture(scope="module")
def model():
    bundle = load_model()
    return bundle, open_network(bundle, "auto", "auto", "fp32", 1)


@pytest.fixture(scope="module")
def speech() -> Audio:
    """The first 8 s of a real take (16 kHz)."""
    full = read_audio_file(SPEECH)
    return Audio(full.samples[: 8 * full.sample_rate], full.sample_rate)


def _mouth_voice(motion: Motion, audio: Audio) -> float:
    return envelope_correlation(mouth_opening(motion), motion.fps, audio.samples, audio.sample_rate)[0]


class _OscListener:
    """A real python-osc server on 127.0.0.1 that keeps every message with its arrival time."""

    def __init__(self):
        from pythonosc.dispatcher import Dispatcher
        from pythonosc.osc_server import BlockingOSCUDPServer

        self.messages: list[tuple[float, str, tuple]] = []
        dispatcher = Dispatcher()
        dispatcher.set_default_handler(lambda address, *values: self.messages.append(
            (time.monotonic(), address, values)))
        self.server = BlockingOSCUDPServer(("127.0.0.1", 0), dispatcher)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def test_live_cli_on_a_real_file_at_real_time_records_logs_and_streams_vmc(tmp_path, speech, model):
    clip = tmp_path / "speech.wav"
    sf.write(clip, speech.samples, speech.sample_rate)
    listener = _OscListener()
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "diffsheg_core", "live", "--source", str(clip), "--record",
             str(tmp_path / "take.npz"), "--latency-log", str(tmp_path / "latency.json"),
             "--osc", f"127.0.0.1:{listener.port}"],
            capture_output=True, text=True, timeout=120, env={**os.environ, "DIFFSHEG_THREADS": "1"})
    finally:
        listener.close()
    assert proc.returncode == 0, proc.stderr
    assert "latency p50" in proc.stdout and "wrote" in proc.stdout

    # the recording covers the audio, is finite, and keeps most of offline generation's lip-sync
    take = Motion.load_npz(tmp_path / "take.npz")
    heard = read_audio_file(tmp_path / "take.wav")
    assert np.array_equal(heard.samples, read_audio_file(clip).samples)  # every sample played, none lost
    assert abs(take.n_frames - n_motion_frames(speech, take.fps)) <= 1
    assert np.isfinite(take.rotations).all() and np.isfinite(take.face).all()
    assert take.meta["live"]["hop"] == LiveConfig().hop
    offline = generate(speech, settings=GenerateSettings(model=model[0], seed=0))
    assert _mouth_voice(take, speech) >= 0.8 * _mouth_voice(offline, speech)

    # the latency log holds every frame, in order, each shown after its audio arrived
    log = json.loads((tmp_path / "latency.json").read_text())["frames"]
    times = np.array([f["t"] for f in log])
    assert len(log) == take.n_frames
    assert np.allclose(times, np.arange(take.n_frames) / take.fps, atol=1e-5)
    assert all(0 < f["latency"] < 10 for f in log)

    # VMC: one frame of valid messages per shown frame, at the stream's frame rate
    addresses = [address for _, address, _ in listener.messages]
    assert set(addresses) <= {"/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Root/Pos", "/VMC/Ext/Bone/Pos",
                              "/VMC/Ext/Blend/Val", "/VMC/Ext/Blend/Apply"}
    applies = np.array([t for t, address, _ in listener.messages if address == "/VMC/Ext/Blend/Apply"])
    assert len(applies) == take.n_frames
    assert 0.7 / take.fps < np.median(np.diff(applies)) < 1.3 / take.fps
    bones = {values[0] for _, address, values in listener.messages if address == "/VMC/Ext/Bone/Pos"}
    assert {"Spine", "Neck", "Head", "LeftUpperArm", "RightHand", "LeftIndexProximal"} <= bones
    # the whole body, live: hips and legs recorded with their contacts, sent as VMC bones
    assert take.joint_names[-len(LEG_JOINTS):] == list(LEG_JOINTS) and take.root_translation.shape == (take.n_frames, 3)
    assert take.meta["hips_height"] > 0 and sum(len(v) for v in take.meta["contacts"].values()) > 0
    assert take.meta["lower_body"] == "model"  # the bundled model's own, planted as they come
    assert take.meta["live"]["legs_eta"] == 1.0  # the model's eta (LiveConfig.legs_eta)
    soles = foot_positions(lower_rotations(take), take.root_translation.astype(np.float64))
    for side, spans in take.meta["contacts"].items():  # a contact foot does not slide
        for a, b in spans:
            assert np.linalg.norm(np.diff(soles[side][1][a:b + 1], axis=0), axis=-1).max(initial=0.0) < 0.01
    assert {"LeftUpperLeg", "RightLowerLeg", "LeftFoot", "RightToes"} <= bones
    hips = np.array([values[1:4] for _, address, values in listener.messages
                     if address == "/VMC/Ext/Bone/Pos" and values[0] == "Hips"])
    assert len(hips) == take.n_frames and np.ptp(hips[:, [0, 2]], axis=0).max() > 0.005  # the weight shifts
    shapes = {values[0] for _, address, values in listener.messages if address == "/VMC/Ext/Blend/Val"}
    assert {"JawOpen", "EyeBlinkLeft", "MouthClose", "A", "Blink_L"} <= shapes


def _serve(session: LiveSession) -> tuple[threading.Thread, dict]:
    """Run the session in a thread; returns the thread and where its result will be."""
    out: dict = {}
    thread = threading.Thread(target=lambda: out.setdefault("result", session.run_to_end()), daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not session.source.port and time.monotonic() < deadline:
        time.sleep(0.01)
    return thread, out


def _pcm(audio: Audio) -> bytes:
    return (np.clip(audio.samples, -1, 1) * 32767).astype("<i2").tobytes()


def _send_at_real_time(sock: socket.socket, pcm: bytes, rate: int, chunk_s: float = 0.04) -> None:
    step, start = int(rate * chunk_s) * 2, time.monotonic()
    for k, i in enumerate(range(0, len(pcm), step)):
        sock.sendall(pcm[i: i + step])
        time.sleep(max(0.0, start + (k + 1) * chunk_s - time.monotonic()))


def test_a_stalling_producer_eases_the_avatar_to_rest_and_it_resumes(speech, model):
    """The stall shows only on a machine that keeps up with the speech (one that falls
    behind is still working through what came before it): 10 steps, a third of the compute."""
    rate = speech.sample_rate
    session = LiveSession(TcpSource(sample_rate=rate), GenerateSettings(seed=0, steps=10), bundle=model[0],
                          network=model[1])
    thread, out = _serve(session)
    first, second = Audio(speech.samples[: 3 * rate], rate), Audio(speech.samples[3 * rate: 6 * rate], rate)
    with socket.create_connection(("127.0.0.1", session.source.port)) as sock:
        _send_at_real_time(sock, _pcm(first), rate)
        time.sleep(2.0)  # the producer stalls
        _send_at_real_time(sock, _pcm(second), rate)
    thread.join(60)
    result = out["result"]
    assert result.error is None and session.load() < 1.0, "the machine falls behind live speech even at 10 steps"
    assert 1.2 < result.underrun_seconds < 2.5
    fps = result.motion.fps
    assert result.motion.n_frames >= int((6 + result.underrun_seconds - 0.1) * fps)
    jaw = face_channel(result.motion, "jawOpen")
    gap = jaw[int(3.8 * fps): int((3 + result.underrun_seconds) * fps)]  # the stall, once eased in
    spoken = jaw[int(0.5 * fps): int(3 * fps)]
    after = jaw[int((3.5 + result.underrun_seconds) * fps):]  # speech again
    assert gap.mean() < 0.5 * spoken.mean()  # the mouth rests while no audio comes
    assert after.std() > 2 * gap.std() and after.mean() > 2 * gap.mean()  # and talks again after
    silence = result.audio.samples[3 * rate + rate // 2: 3 * rate + int(rate * (result.underrun_seconds - 0.2))]
    assert not silence.any()  # the recording holds the filled silence, and says so
    assert any("filled with silence" in w for w in result.motion.meta["warnings"])


def test_a_closed_socket_ends_the_session_and_a_reset_one_says_why(speech, model):
    rate = speech.sample_rate
    session = LiveSession(TcpSource(sample_rate=rate), GenerateSettings(seed=1), bundle=model[0], network=model[1])
    thread, out = _serve(session)
    sock = socket.create_connection(("127.0.0.1", session.source.port))
    _send_at_real_time(sock, _pcm(Audio(speech.samples[: 2 * rate], rate)), rate)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
    sock.close()  # an abrupt reset mid-stream
    thread.join(60)
    result = out["result"]
    assert result.error and "reset" in result.error.lower()
    assert result.motion.n_frames >= int(1.9 * result.motion.fps)  # what was heard is kept
    assert np.isfinite(result.motion.rotations).all()


def test_a_producer_faster_than_real_time_is_bounded_and_reported(speech, model):
    rate = speech.sample_rate
    session = LiveSession(TcpSource(sample_rate=rate), GenerateSettings(seed=0), bundle=model[0], network=model[1])
    session.feed.capacity = 2 * rate  # a 2 s buffer, so the test is short
    thread, out = _serve(session)
    with socket.create_connection(("127.0.0.1", session.source.port)) as sock:
        sock.sendall(_pcm(speech))  # 8 s at once
    thread.join(60)
    result = out["result"]
    assert result.error is None
    assert 5.0 < result.dropped_seconds < 6.1
    assert result.audio.duration + result.dropped_seconds == pytest.approx(speech.duration, abs=0.01)
    assert "dropped" in session.status()
    assert any("dropped: it came faster than real time" in w for w in result.motion.meta["warnings"])  # the take says so
    assert abs(result.motion.n_frames - n_motion_frames(result.audio, result.motion.fps)) <= 1


def test_a_machine_that_falls_behind_says_so(tmp_path, speech, model):
    """Speech played at 16x real time: no CPU makes a second of motion in 1/16 s, so the
    status line and the recording say that the machine falls behind, with its compute per
    second of speech at the source's pace; before 2 s of speech nothing is judged."""
    clip = tmp_path / "speech.wav"
    sf.write(clip, speech.samples[: 3 * speech.sample_rate], speech.sample_rate)
    session = LiveSession(FileSource(clip, speed=16.0), GenerateSettings(seed=0), bundle=model[0], network=model[1])
    assert session.load() is None and "falling behind" not in session.status()
    result = session.run_to_end()
    assert result.dropped_seconds == 0 and session.load() > 1.0
    assert session.load() == pytest.approx(16 * result.compute / (result.motion.n_frames / result.motion.fps), rel=0.05)
    assert result.load == session.load()  # the recording carries the figure the CLI reports
    assert "falling behind: " in session.status() and "s of compute a second" in session.status()
    assert any(w.startswith("the machine was falling behind") for w in result.motion.meta["warnings"])


def test_a_machine_too_slow_for_the_hop_widens_it_and_never_drifts(tmp_path, speech, model):
    """Issue 39, item 4: 8 s of real speech with the 25-step sampling, played faster than this
    machine makes it at hops of 3 frames: at 1.75x the pace it keeps at hop 3, measured first
    (at least 1.5x real time; the 2-core CI box needs 1.1-1.2 s of compute a second at 1x, and
    the fast default keeps up there). The session takes the frames that wait in wider windows (up
    to max_hop), says so once in its status line and the recording, keeps its latency
    bounded (the last second's no worse than the first's plus a hop), drops no audio, and
    records every frame heard. With the hop held at 3 (max_hop 3) the same session falls
    seconds behind."""
    clip = tmp_path / "speech.wav"
    sf.write(clip, speech.samples, speech.sample_rate)
    bundle, network = model
    settings = GenerateSettings(seed=0, sampling="quality")
    widening, held_at_3 = LiveConfig(hop=3), LiveConfig(hop=3, max_hop=3)
    first = tmp_path / "first.wav"  # this machine's pace at hop 3: boxes differ about 2x in speed
    sf.write(first, speech.samples[: 3 * speech.sample_rate], speech.sample_rate)
    measured = LiveSession(FileSource(first, speed=16.0), settings, live=held_at_3, bundle=bundle,
                           network=network).run_to_end()
    pace = max(1.5, 1.75 * 3.0 / measured.compute)

    def run(live: LiveConfig):
        session = LiveSession(FileSource(clip, speed=pace), settings, live=live, bundle=bundle, network=network)
        result = session.run_to_end()
        return session, result, [lat for _, lat in result.latencies]

    session, result, latencies = run(widening)
    assert result.dropped_seconds == 0 and result.error is None
    assert result.audio.duration == pytest.approx(speech.duration, abs=0.05)  # every sample heard ...
    assert result.motion.n_frames == n_motion_frames(result.audio, result.motion.fps)  # ... and every frame
    widest = result.motion.meta["live"]["widest_hop"]
    assert 3 < widest <= LiveConfig().max_hop
    assert f"hops up to {widest} frames to keep up (too slow for 3)" in session.status()
    assert any(w.startswith("the session sampled hops up to") for w in result.motion.meta["warnings"])
    def growth(values):  # the last second's latency over that of the middle second (once the hop has widened)
        middle = len(values) // 2
        return np.percentile(values[-15:], 95) - np.percentile(values[middle - 15:middle], 95)

    held_session, held, held_latencies = run(held_at_3)
    print(f"at {pace:.2f}x: latency p95 {np.percentile(latencies, 95):.2f} s, grew {growth(latencies):+.2f} s from "
          f"the middle second to the last, widest hop {widest}; hop held at 3: p95 {np.percentile(held_latencies, 95):.2f} s, "
          f"grew {growth(held_latencies):+.2f} s")
    assert held.motion.meta["live"]["widest_hop"] == 3 and "falling behind" in held_session.status()
    # widened, it keeps up: no drift over the speech beyond the widest hop it may take (max_hop's
    # frames, shown at the pace: 0.53 s at 1.5x) and 0.1 s of compute jitter (with the 25 steps on
    # the 2-core CI box at 1.5x, 2026-12-05: +0.22, +0.34, +0.44 and, once in about ten runs,
    # +0.57 s; held at 3: +1.50 to +1.83 s; on a box twice as fast at 3.3x: +0.12, held +1.33 s)
    assert growth(latencies) < LiveConfig().max_hop / (result.motion.fps * pace) + 0.1
    # held, it drifts: a hop-3 session needs 1.75x the time it has, so while the speech's second
    # half plays (its seconds over the pace) it falls 0.75 of that time behind
    drift = 0.75 * (speech.duration / 2) / pace
    assert growth(held_latencies) > growth(latencies) + min(0.5, 0.5 * drift)


def test_live_fast_sampling_scales_the_settings_skip_guidance(model):
    bundle, network = model
    engine = LiveEngine(bundle, network, GenerateSettings(skip_guidance=0.2), 16000,
                        LiveConfig(skip_scale=2.5, legs_skip_scale=4.5))
    assert engine.plan.guidance.skip == pytest.approx(0.5)
    assert engine.meta()["skip_guidance"] == pytest.approx(0.5) and engine.meta()["live"]["skip_scale"] == 2.5
    # the whole-body model's hips and legs (its lower branch's 30 channels) with their own
    assert engine.plan.guidance.legs_skip == pytest.approx(0.9) and engine.plan.guidance.lower == 30
    assert engine.meta()["live"]["legs_skip_scale"] == 4.5
    default = LiveEngine(bundle, network, GenerateSettings(), 16000)
    assert default.plan.guidance.skip == pytest.approx(bundle.skip_guidance * LiveConfig().skip_scale)
    assert LiveEngine(bundle, network, GenerateSettings(skip_guidance=0), 16000).plan.guidance.skip is None  # off stays off
    quality = LiveEngine(bundle, network, GenerateSettings(sampling="quality"), 16000)
    assert quality.plan.guidance.skip == pytest.approx(bundle.skip_guidance)  # the 25 steps keep the settings'


def test_live_runs_the_models_int8_live_graphs_on_onnxruntime(speech, model):
    """On onnxruntime a session runs the model file's live graphs (its products by weights in
    int8, about 0.8x the compute a window); a file without them runs the model's own graphs and
    torch its float weights. The int8 session's frames stay far nearer the float one's than
    another seed's are (8 s of the real take, seeds 0 and 1, the hop held)."""
    from dataclasses import replace

    from diffsheg_core.runtime.backends import live_network

    bundle, network = model
    float_bundle = replace(bundle, live_graphs={})
    float_network = open_network(float_bundle, "onnx", "auto", "fp32", 1)
    torch_network = open_network(bundle, "torch", "cpu", "fp32", 1)

    def session(bundle, network, seed):
        engine = LiveEngine(bundle, network, GenerateSettings(seed=seed, threads=1), speech.sample_rate, FIXED_HOP)
        engine.push(speech.samples)
        while engine.ready():
            engine.step()
        engine.finish()
        motion = engine.motion()
        return engine, np.concatenate([motion.rotations.reshape(motion.n_frames, -1), motion.face], axis=1)

    engine, int8 = session(bundle, network, 0)
    assert network.name == "onnx" and engine.network is live_network(bundle, network) is not network
    assert engine.meta()["live"]["int8_graphs"] is True
    assert LiveEngine(bundle, torch_network, GenerateSettings(), 16000).network is torch_network
    float_engine, floats = session(float_bundle, float_network, 0)
    assert float_engine.network is float_network and float_engine.meta()["live"]["int8_graphs"] is False
    _, other_seed = session(float_bundle, float_network, 1)
    ratio = np.abs(int8 - floats).mean() / np.abs(other_seed - floats).mean()
    assert 0 < ratio < 0.2, ratio  # measured 0.06


def test_windows_run_through_their_lookahead_and_keep_only_the_new_frames(speech, model):
    """With `through_lookahead` a window ends at its lookahead's last frame, not its new frames'
    (the clip's length, holding the emitted frames before the new ones), the new frames are
    sampled against the lookahead's speech features and sent out, the lookahead's frames are not."""
    bundle, network = model
    clip, hop, lookahead = bundle.config.clip_len, 2, 1
    engine = LiveEngine(bundle, network, GenerateSettings(), speech.sample_rate,
                        LiveConfig(hop=hop, max_hop=hop, lookahead=lookahead, through_lookahead=True,
                                   match_velocity=False))  # the frames exactly as sampled (the seam: below)
    windows, sample_window = [], engine.sampler.sample_window

    def recorded(eps_fn, length, known, noise, **kw):
        window = sample_window(eps_fn, length, known, noise, **kw)
        windows.append((length, 0 if known is None else known.shape[1], window))
        return window

    engine.sampler.sample_window = recorded
    engine.push(speech.samples[: 4 * speech.sample_rate])
    sent = []
    while engine.ready():
        before = engine.emitted
        sent.append(engine.step())
        assert engine.emitted == before + hop
    assert windows[0][:2] == (hop + lookahead, 0)  # the first window: its new frames and the lookahead's
    later = windows[-1]
    assert later[:2] == (clip, clip - hop - lookahead)
    np.testing.assert_array_equal(sent[-1], later[2][0, clip - hop - lookahead: clip - lookahead])
    assert engine.emitted + lookahead <= engine.heard_frames
    with pytest.raises(DiffshegError, match="a window takes 1 to 32 new frames"):  # 34, less one shown and L
        engine.step(33)


def test_a_window_waits_only_for_the_audio_its_lookahead_frames_mel_reads(speech, model):
    """A window is sampled once the audio that its last lookahead frame's mel frame reads has
    arrived (57 ms past the frame's centre), 10 ms before that frame is heard (the next frame's
    start). Its features stop there, so the frames are those of a session that had all the
    audio in, and that mel frame is the one the whole recording gives."""
    bundle, network = model
    fps, rate = bundle.config.fps, speech.sample_rate
    needed = samples_for_mel_frame(2, rate, fps)  # hop 2 and lookahead 1: the first window's lookahead is frame 2
    assert needed / rate == pytest.approx(2 / fps + MEL_N_FFT / 2 / MEL_RATE, abs=2 / rate)
    assert n_motion_frames(Audio(speech.samples[:needed], rate), fps) == 2  # frame 2 is not heard yet ...
    assert n_motion_frames(Audio(speech.samples[:needed + int(0.010 * rate)], rate), fps) == 3  # ... for 10 ms
    read = mel_frames(Audio(speech.samples[:needed], rate), fps)
    np.testing.assert_allclose(read[2], mel_frames(speech, fps)[2], rtol=1e-3, atol=1e-6)
    live = LiveConfig(max_hop=2)
    early = LiveEngine(bundle, network, GenerateSettings(), rate, live)
    early.push(speech.samples[: needed - 1])
    assert not early.ready() and early.readable_frames == 2
    early.push(speech.samples[needed - 1: needed])
    assert early.ready() and early.heard_frames == 2 and early.readable_frames == 3
    made = [early.step()]
    for i in range(needed, 3 * rate, 320):  # on in 20 ms chunks, each window as soon as it can be
        early.push(speech.samples[i: i + 320])
        while early.ready():
            made.append(early.step())
    late = LiveEngine(bundle, network, GenerateSettings(), rate, live)
    late.push(speech.samples[: 4 * rate])
    while late.emitted < early.emitted:
        late.step()
    np.testing.assert_array_equal(np.concatenate(made), np.concatenate(late._frames))


def test_a_frame_not_heard_yet_is_never_emitted_nor_a_mel_frame_read_past_the_audio(speech, model):
    """Without a lookahead, the frame whose mel frame has arrived but which is not heard yet is
    not one of the recording's: a session emits the frames heard, as many as its audio makes.
    Above 17.6 fps a mel frame reaches past the next frame's start, and a window waits for it."""
    bundle, network = model
    rate, fps = speech.sample_rate, bundle.config.fps
    n = samples_for_mel_frame(37, rate, fps)  # 57-67 ms past frame 37's centre: it is readable, not heard
    audio = Audio(speech.samples[:n], rate)
    engine = LiveEngine(bundle, network, GenerateSettings(), rate, LiveConfig(hop=2, lookahead=0))
    engine.push(audio.samples)
    assert engine.heard_frames == 37 and engine.readable_frames == 38
    while engine.ready():
        engine.step()
    assert engine.emitted == 36
    engine.finish()
    assert engine.emitted == engine.heard_frames == n_motion_frames(audio, fps) == engine.motion().n_frames
    fast = LiveEngine(bundle, network, GenerateSettings(), rate)
    fast.fps = 30  # as a 30 fps model counts: each mel frame reads past the next frame's start
    fast.push(speech.samples[: rate])
    assert fast.readable_frames < fast.heard_frames
    assert samples_for_mel_frame(fast.readable_frames - 1, rate, 30) <= rate < samples_for_mel_frame(
        fast.readable_frames, rate, 30)
    assert fast.waiting == fast.readable_frames - fast.live.lookahead  # what the window would read has arrived


def test_live_windows_take_off_the_level_of_the_session_heard_so_far(speech, model):
    """The phonetic encoder's input is the log-mel less each band's mean level. Offline that is
    the whole recording's; live it is the mean over every whole recogniser frame heard up to
    the window (`speech_features.RunningLevel`), each counted once, not the window's own few
    seconds (whose mean moved with the frame at the edge of the audio it read)."""
    from diffsheg_core.phonetic import raw_log_mel
    from diffsheg_core.speech_features import LEVEL_EDGE_S, RunningLevel

    bundle, network = model
    audio = Audio(speech.samples[: 6 * speech.sample_rate], speech.sample_rate)
    engine = LiveEngine(bundle, network, GenerateSettings(), audio.sample_rate)
    engine.push(audio.samples)
    stops = []
    read = engine._features
    engine._features = lambda first, last, end: stops.append(samples_for_mel_frame(
        end - 1 + engine.live.lookahead, audio.sample_rate, bundle.config.fps)) or read(first, last, end)
    while engine.ready():
        engine.step()
    per_second = bundle.phonetic.fps * bundle.phonetic.subframes
    counted = engine._level.count
    assert counted == engine._level.next == int((stops[-1] / audio.sample_rate - LEVEL_EDGE_S) * per_second) + 1
    whole = raw_log_mel(audio, bundle.phonetic)[:, :counted].mean(axis=1)
    np.testing.assert_allclose(engine._level.total / counted, whole, atol=1e-3)
    level = RunningLevel(2)  # frames read twice (overlapping windows) are counted once, skipped ones not at all
    frames = np.arange(40.0).reshape(2, 20)
    level.add(frames[:, :6], 0, 4)
    np.testing.assert_allclose(level.add(frames[:, 2:], 2, 8)[:, 0], frames[:, :8].mean(axis=1))
    np.testing.assert_allclose(level.add(frames[:, 12:], 12, 30)[:, 0],
                               np.concatenate([frames[:, :8], frames[:, 12:]], axis=1).mean(axis=1))


def test_live_fast_sampling_scales_the_face_guidance_and_takes_its_candidates(model):
    bundle, network = model
    engine = LiveEngine(bundle, network, GenerateSettings(guidance=2.0), 16000,
                        LiveConfig(face_scale=1.5, candidates=2))
    assert engine.plan.guidance.scale == pytest.approx(3.0) and engine.config.candidates == 2
    meta = engine.meta()["live"]
    assert meta["face_scale"] == 1.5 and engine.meta()["candidates"] == 2 and meta["through_lookahead"] is True
    # the settings' candidates, when given, are the job's; the 25 steps keep the settings' face guidance
    assert LiveEngine(bundle, network, GenerateSettings(candidates=3), 16000,
                      LiveConfig(candidates=2)).config.candidates == 3
    quality = LiveEngine(bundle, network, GenerateSettings(sampling="quality", guidance=2.0), 16000,
                         LiveConfig(face_scale=1.5))
    assert quality.plan.guidance.scale == pytest.approx(2.0)


def test_what_a_user_chose_of_the_latency_settings():
    """--hop and --lookahead, when given, replace the defaults' (a hop wider than the default's
    widest is its own widest: hop 14 was refused)."""
    import argparse

    from diffsheg_core.live.cli import add_parser

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())

    def resolve(*argv):
        args = parser.parse_args(["live", *argv])
        return LiveConfig.chosen(args.hop, args.lookahead)

    assert resolve() == LiveConfig() == LiveConfig(hop=2, lookahead=1, face_scale=1.5, through_lookahead=True,
                                                   match_velocity=True)
    assert resolve("--lookahead", "2") == LiveConfig(lookahead=2)
    assert resolve("--hop", "4") == LiveConfig(hop=4)
    assert resolve("--hop", "14") == LiveConfig(hop=14, max_hop=14)
    LiveConfig.chosen(hop=16).check(clip_len=34)


def test_each_window_shares_the_change_of_velocity_at_its_seam(speech, model):
    """`match_velocity` moves a window's new gestures by one offset so that the step from the
    last frame shown to the first new one is the mean of the step that frame arrived with and
    the new frames' own next step; the face, the legs and the new frames' shape stay as sampled.
    Off, the seams keep their kinks."""
    from diffsheg_core.live.engine import continue_velocity

    bundle, network = model
    audio = Audio(speech.samples[: 4 * speech.sample_rate], speech.sample_rate)
    kinks = {}
    for match in (True, False):
        engine = LiveEngine(bundle, network, GenerateSettings(), audio.sample_rate,
                            LiveConfig(max_hop=2, match_velocity=match))
        g = engine.sampler.upper  # the gestures; a lower branch's legs and the face after them
        engine.push(audio.samples)
        sampled, sample_window = [], engine.sampler.sample_window
        engine.sampler.sample_window = lambda *a, **kw: sampled.append(sample_window(*a, **kw)) or sampled[-1]
        kinks[match], hop, lookahead = [], engine.live.hop, engine.live.lookahead  # windows run through it
        while engine.ready():
            shown = np.concatenate(engine._frames)[-2:] if engine.emitted else None
            n_known = engine.emitted - max(0, engine.emitted + hop + lookahead - bundle.config.clip_len)
            new = engine.step()
            if shown is None or len(shown) < 2:
                continue
            raw = sampled[-1][0, n_known: n_known + hop]
            seam = new[0, :g] - shown[1, :g]
            kinks[match].append(np.abs(seam - (shown[1, :g] - shown[0, :g] + new[1, :g] - new[0, :g]) / 2).max())
            np.testing.assert_array_equal(new[:, g:], raw[:, g:])  # the legs and face as sampled
            np.testing.assert_allclose(np.diff(new[:, :g], axis=0), np.diff(raw[:, :g], axis=0), atol=1e-5)
            if match:
                np.testing.assert_allclose(new, continue_velocity(raw, shown, g), atol=1e-6)
        assert engine.meta()["live"]["match_velocity"] is match
    assert max(kinks[True]) < 1e-4 and np.median(kinks[False]) > 0.05, kinks


@pytest.fixture(scope="module")
def default_takes(model):
    """The real take made live at the defaults (`training.calibrate.live_take`: the engine fed it
    all at once, its hop held) and offline, seeds 0 and 1: (audio, {"live": [...], "offline": [...]})."""
    from diffsheg_core.training.calibrate import live_take

    bundle, _ = model
    audio = read_audio_file(SPEECH)
    return audio, {"live": [live_take(bundle, audio, seed) for seed in (0, 1)],
                   "offline": [generate(audio, settings=GenerateSettings(model=bundle, seed=seed, threads=1))
                               for seed in (0, 1)]}


def test_live_gestures_move_and_speak_like_offline_ones(default_takes):
    """Issue 39's bar for live quality, on the real take and two seeds: the default live
    session's wrists move at least 0.9x as fast as offline generation's of the same speech
    (the distilled student), jitter at most 1.2x as much, and its mouth follows the voice as
    well (within 5 %). The seeds spread widely (at hop 3, a seed's wrists 0.74-1.30x offline's
    across seeds 0-7 on the held-out 20 s), so two seeds are held to 0.85x and 1.2x (seeds 0-7,
    live's int8 graphs, the prior's draws 1.2x as wide: 0.94x, 1.12x, and the mouth 0.98x;
    docs/live.md has other speech)."""
    from diffsheg_core.training.metrics.posture import naturalness

    audio, takes = default_takes

    def measured(motion):
        nat = naturalness(motion)
        return nat["wrist speed (arm lengths/s)"], nat["wrist jitter (arm lengths/s^2)"], _mouth_voice(motion, audio)

    figures = {name: [measured(motion) for motion in motions] for name, motions in takes.items()}
    live, offline = (np.mean(figures[name], axis=0) for name in ("live", "offline"))
    speed, jitter, mouth = live / offline
    assert speed >= 0.85, (live, offline)
    assert jitter <= 1.2, (live, offline)
    assert mouth >= 0.95, (live, offline)


def test_live_keeps_the_mouth_in_sync(default_takes):
    """Live waits for one frame of audio past a hop of two: at that lookahead the jaw barely
    closed for bilabials (open vowels over bilabials 0.87x offline's on these two seeds); windows
    run through their lookahead with the face's guidance at 1.5x (the defaults), it opens and
    closes as offline's and follows the voice as well (the real take, seeds 0-1; bars 0.95x)."""
    from diffsheg_core.training.metrics.channels import face_channel
    from diffsheg_core.training.metrics.lipsync import phoneme_contrast
    from diffsheg_core.training.metrics.textgrid import phone_tier, read_textgrid

    audio, takes = default_takes
    phones = phone_tier(read_textgrid(SPEECH.with_suffix(".TextGrid")))
    figures = {name: [(phoneme_contrast(face_channel(motion, "jawOpen"), motion.fps, phones)["ratio"],
                       _mouth_voice(motion, audio)) for motion in motions] for name, motions in takes.items()}
    live, offline = (np.mean(figures[name], axis=0) for name in ("live", "offline"))
    assert (live / offline >= 0.95).all(), (live, offline)


def test_a_live_take_holds_the_posture_of_the_25_steps(tmp_path, model):
    """Live windows start from the gesture prior's draws, as the offline fast sampling's do, and
    held the wrists about 0.1 arm lengths higher than the 25 steps'; the model file's live
    posture (training.calibrate, measured on other takes) is a constant added to the frames
    live sends out after its first 34 (left as they are), eased in over the next 34. On 30 s of
    unheard speech, seeds 0-3 (a seed's live wrists sit up to 0.24 arm lengths from the 25
    steps': two seeds are too few): the wrists' mean height within 0.05 arm lengths of the 25
    steps' offline (0.02; uncalibrated 0.14), the frames the uncalibrated engine's moved by
    exactly that constant so weighted, the same streamed a hop at a time through a session as
    in its recording, and the recording says so. Other steps or guidance scales than the
    model's are not calibrated."""
    from dataclasses import replace

    from diffsheg_core.lower_body import upper_body
    from diffsheg_core.pipeline import calibrated_posture, posture_weights
    from diffsheg_core.training.calibrate import live_take
    from diffsheg_core.training.metrics.posture import wrist_positions

    bundle, _ = model
    raw = replace(bundle, info={k: v for k, v in bundle.info.items() if k != "live_posture"})
    full = read_audio_file(ROOT.parent / "shared" / "data" / "audio" / "2_scott_0_3_3.wav")
    audio = Audio(full.samples[: 30 * full.sample_rate], full.sample_rate)
    seeds = (0, 1, 2, 3)
    takes = {"quality": [upper_body(generate(audio, model=bundle, seed=seed, sampling="quality")) for seed in seeds],
             "live": [upper_body(live_take(bundle, audio, seed)) for seed in seeds]}
    calibrated, made = takes["live"][0], upper_body(live_take(raw, audio, 0))
    assert calibrated.meta["live"]["posture_calibrated"] is True and made.meta["live"]["posture_calibrated"] is False
    n = 3 * len(calibrated.joint_names)
    posture = calibrated_posture(bundle, live=True)
    assert not posture.first.any()  # a session's first window is left as sampled
    shift = (posture.later * bundle.std)[:n]
    weights = posture_weights(0, calibrated.n_frames, bundle.config.clip_len)
    assert shift.any() and weights[: bundle.config.clip_len].max() == 0 and weights[-1] == 1
    moved = (weights[:, None] * shift).reshape(calibrated.rotations.shape)
    np.testing.assert_allclose(calibrated.rotations - made.rotations, moved, atol=1e-5)
    # so the uncalibrated engine's other seeds are their calibrated takes less that constant
    takes["raw"] = [made] + [replace(t, rotations=t.rotations - moved) for t in takes["live"][1:]]
    height = {name: np.mean([wrist_positions(t)[..., 1].mean() for t in found]) for name, found in takes.items()}
    assert abs(height["live"] - height["quality"]) <= 0.05 <= height["raw"] - height["quality"], height
    clip = tmp_path / "speech.wav"
    sf.write(clip, audio.samples[: 6 * audio.sample_rate], audio.sample_rate)
    shown = []
    session = LiveSession(FileSource(clip, speed=2.0), GenerateSettings(seed=0), live=FIXED_HOP, bundle=bundle,
                          network=model[1])
    recorded = session.run_to_end(shown.append).motion
    assert recorded.meta["live"]["posture_calibrated"] is True and recorded.n_frames > 2 * bundle.config.clip_len
    np.testing.assert_allclose(np.stack([f.rotations[:len(calibrated.joint_names)] for f in shown]),
                               recorded.rotations[: len(shown), : len(calibrated.joint_names)], atol=1e-6)
    np.testing.assert_allclose(recorded.rotations[:, :len(calibrated.joint_names)],
                               live_take(bundle, Audio(audio.samples[: 6 * audio.sample_rate], audio.sample_rate),
                                         0).rotations[:, :len(calibrated.joint_names)], atol=1e-5)
    for settings in (GenerateSettings(steps=10), GenerateSettings(skip_guidance=0.2), GenerateSettings(sampling="quality")):
        assert LiveEngine(bundle, model[1], settings, 16000).meta()["live"]["posture_calibrated"] is False


def test_the_engine_refuses_what_live_cannot_do(model):
    bundle, network = model
    with pytest.raises(DiffshegError, match="style over time"):
        LiveEngine(bundle, network, GenerateSettings(style_at=((0, 0),)), 16000)
    with pytest.raises(DiffshegError, match="hop"):
        LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(hop=0))
    with pytest.raises(DiffshegError, match="lookahead"):
        LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(lookahead=-1))
    with pytest.raises(DiffshegError, match="later_start"):
        LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(later_start=25))
    with pytest.raises(DiffshegError, match="legs_eta"):
        LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(legs_eta=-0.5))
    for skip_scale in (-1.0, 11, True):
        with pytest.raises(DiffshegError, match="live skip_scale must be a number from 0 to 10"):
            LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(skip_scale=skip_scale))
        with pytest.raises(DiffshegError, match="live legs_skip_scale must be a number from 0 to 10"):
            LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(legs_skip_scale=skip_scale))
    for face_scale in (-1.0, 0, 11, True):
        with pytest.raises(DiffshegError, match="live face_scale must be a number from 0 to 10"):
            LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(face_scale=face_scale))
    for candidates in (0, 2.5, True):
        with pytest.raises(DiffshegError,
                           match=r"live candidates \(None: the settings'\) must be a whole number from 1 to 16"):
            LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(candidates=candidates))
    with pytest.raises(DiffshegError, match="choose a smaller hop or lookahead"):  # a model of 20-frame windows
        LiveConfig(max_hop=12, lookahead=8, through_lookahead=True).check(clip_len=20)
    for name in ("through_lookahead", "match_velocity"):
        with pytest.raises(DiffshegError, match=f"{name} must be True or False"):
            LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(**{name: "yes"}))
    for max_hop in (1, 17, 3.5):
        with pytest.raises(DiffshegError, match="max_hop must be a whole number of frames from the hop"):
            LiveEngine(bundle, network, GenerateSettings(), 16000, LiveConfig(max_hop=max_hop))
    with pytest.raises(DiffshegError, match="4000 Hz or more"):
        LiveEngine(bundle, network, GenerateSettings(), 100)


def test_upper_body_only_streams_no_legs(tmp_path, speech, model):
    """A session without legs streams the upper body alone, numpy on the session's threads."""
    clip = tmp_path / "speech.wav"
    sf.write(clip, speech.samples[: 2 * speech.sample_rate], speech.sample_rate)
    shown = []
    session = LiveSession(FileSource(clip, speed=4.0), GenerateSettings(upper_body_only=True),
                          bundle=model[0], network=model[1])
    before = blas_threads()  # OpenBLAS's own: a thread per core
    result = session.run_to_end(lambda frame: shown.append((frame, blas_threads())))
    # numpy's BLAS on the session's threads (the default, 1) while it samples (the first half of
    # the frames: the last may be shown after it ended), as generate holds it; given back after
    assert {threads for _, threads in shown[: len(shown) // 2]} <= {frozenset({1})}
    assert blas_threads() == before
    shown = [frame for frame, _ in shown]
    assert session.legs is None and session.joint_names == list(model[0].rig_layout.joint_names)  # 47, no legs
    assert shown and all(f.root_translation is None and f.rotations.shape == (len(session.joint_names), 3)
                         for f in shown)
    assert result.motion.root_translation is None and result.motion.joint_names == session.joint_names


def test_live_lays_the_emotion_over_each_hop(tmp_path, speech, model):
    """Sad, live, against neutral live from the same speech and seed: the face is exactly
    the emotion layer over the neutral frames (it is frame by frame), the brows go up and the
    mouth down, the head is lower and the gestures slower, as offline; the recording says so."""
    from diffsheg_core.emotion import NAMES, _face
    from diffsheg_core.kinematics import wrist_positions
    from diffsheg_core.training.metrics.channels import face_channel

    clip = tmp_path / "speech.wav"
    sf.write(clip, speech.samples[: 5 * speech.sample_rate], speech.sample_rate)
    runs = {}
    for emotion in (None, "sad"):
        session = LiveSession(FileSource(clip, speed=4.0), GenerateSettings(seed=0, emotion=emotion),
                              live=FIXED_HOP, bundle=model[0], network=model[1])
        runs[emotion] = session.run_to_end().motion
    neutral, sad = runs[None], runs["sad"]
    assert sad.meta["emotion"] == {"sad": 1.0} and sad.n_frames == neutral.n_frames
    track = np.zeros((sad.n_frames, len(NAMES)))
    track[:, NAMES.index("sad")] = 1.0
    np.testing.assert_allclose(sad.face, _face(neutral, track), atol=1e-6)
    assert face_channel(sad, "browInnerUp").mean() > face_channel(neutral, "browInnerUp").mean() + 0.3
    assert face_channel(sad, "mouthFrownLeft").mean() > face_channel(neutral, "mouthFrownLeft").mean() + 0.2

    def head_pitch(m):  # degrees, down positive, over the neck's two joints
        return np.degrees(sum(m.rotations[:, m.joint_names.index(j), 0] for j in ("Neck", "Neck1"))).mean()

    def wrist_speed(m):
        return np.linalg.norm(np.diff(wrist_positions(m), axis=0), axis=-1).mean()

    assert head_pitch(sad) > head_pitch(neutral) + 8
    assert wrist_speed(sad) < 0.9 * wrist_speed(neutral)
    assert sad.joint_names[-len(LEG_JOINTS):] == list(LEG_JOINTS)  # the legs under the emotional arms


def test_the_emotion_changed_while_live_eases_in_and_is_recorded(tmp_path, speech, model):
    """Neutral, then happy asked for while the frames are shown (the panel's menu does so):
    until the change the frames are neutral's exactly, then the smile eases in over
    emotion.SWITCH_S and holds; the recording notes the change, so regenerating a range of it
    knows the emotion there. A bad emotion is refused and changes nothing."""
    from diffsheg_core.emotion import EASE_S, SWITCH_S, take_emotion
    from diffsheg_core.training.metrics.channels import face_channel

    clip = tmp_path / "speech.wav"
    sf.write(clip, speech.samples[: 6 * speech.sample_rate], speech.sample_rate)
    # at 2x real time: faster, a 2-core machine falls so far behind that the feed drops audio,
    # and the two sessions would hear different speech
    first = LiveSession(FileSource(clip, speed=2.0), GenerateSettings(seed=0), live=FIXED_HOP, bundle=model[0],
                        network=model[1]).run_to_end()
    assert first.dropped_seconds == 0, "the machine fell behind: audio was dropped"
    neutral = first.motion
    session = LiveSession(FileSource(clip, speed=2.0), GenerateSettings(seed=0), live=FIXED_HOP, bundle=model[0], network=model[1])
    with pytest.raises(DiffshegError, match="unknown emotion 'joyful'"):
        session.set_emotion("joyful")

    def show(frame):
        if frame.index == 20:
            session.set_emotion({"happy": 0.8})

    changed = session.run_to_end(show).motion
    (t, spec), = changed.meta["emotion_at"]  # noted at the middle of its ease
    fps = changed.fps
    at = int(round(t * fps - SWITCH_S * fps / 2))
    assert spec == {"happy": 0.8} and 20 <= at < changed.n_frames - 2 * fps
    np.testing.assert_array_equal(changed.face[:at], neutral.face[:at])
    smile = face_channel(changed, "mouthSmileLeft") - face_channel(neutral, "mouthSmileLeft")
    held = at + int(np.ceil(SWITCH_S * fps))
    # eased in, then held (0.48 at most: happy's 0.6 at 0.8), giving way where the lips close on p, b, m as
    # offline (live's face guidance at 1.5x closes them firmly: the median is 0.30 here)
    assert abs(smile[at]) < 0.05 and np.median(smile[held:]) > 0.25 and smile[at:held].mean() < np.median(smile[held:])
    track = take_emotion(changed)
    assert track is not None and track[held + 6:, 1].min() == pytest.approx(0.8, abs=0.01)
    # the track is the change's step at the noted frame (the middle of live's ease) through
    # emotion_track's Gaussian: it crosses half the intensity there and reaches ceil(3 sigma)
    # frames before it (a frame more than `at - 4` when t's fraction rounds so). Against live's
    # own smoothstep a frame apart, the difference depends on that fraction (0.08-0.09).
    middle = round(t * fps)
    before = middle - int(np.ceil(3 * EASE_S * fps))
    assert before >= at - 5 and not track[:before].any()
    assert track[middle - 1, 1] < 0.4 < track[middle + 1, 1]


@pytest.mark.parametrize("lookahead,through", [(0, False), (2, False), (5, False), (1, True), (5, True)])
def test_every_frame_heard_is_emitted_whatever_the_lookahead(speech, model, lookahead, through):
    bundle, network = model
    audio = Audio(speech.samples[: int(2.5 * speech.sample_rate)], speech.sample_rate)
    engine = LiveEngine(bundle, network, GenerateSettings(), audio.sample_rate,
                        LiveConfig(lookahead=lookahead, through_lookahead=through))
    for i in range(0, audio.n_samples, 320):
        engine.push(audio.samples[i: i + 320])
        while engine.ready():
            engine.step()
    engine.finish()
    assert engine.emitted == engine.heard_frames == n_motion_frames(audio, bundle.config.fps)
    assert engine.motion().n_frames == engine.emitted


def _live_cli_showing(tmp_path, speech: Audio, *options: str):
    """The live CLI on `speech` (recording to take.npz, standard input a pipe), once it shows
    frames: (the process, the thread reading its stderr, the stderr read so far)."""
    clip = tmp_path / "speech.wav"
    sf.write(clip, speech.samples, speech.sample_rate)
    proc = subprocess.Popen([sys.executable, "-m", "diffsheg_core", "live", "--source", str(clip), *options,
                             "--record", str(tmp_path / "take.npz")], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "DIFFSHEG_THREADS": "1"})
    err_parts: list[str] = []
    reader = threading.Thread(target=lambda: err_parts.extend(iter(lambda: proc.stderr.read(1), "")), daemon=True)
    reader.start()
    deadline = time.monotonic() + 60
    while "latency" not in "".join(err_parts) and time.monotonic() < deadline:  # frames are being shown
        time.sleep(0.05)
    return proc, reader, err_parts


def test_ctrl_c_ends_the_live_cli_cleanly_and_writes_the_recording(tmp_path, speech):
    import signal

    proc, reader, err_parts = _live_cli_showing(tmp_path, speech)
    time.sleep(1.5)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    reader.join(10)
    err = "".join(err_parts)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    take = Motion.load_npz(tmp_path / "take.npz")
    heard = read_audio_file(tmp_path / "take.wav")
    assert 1.0 < heard.duration < speech.duration - 1.0  # stopped part-way: what was heard is kept
    assert take.n_frames == n_motion_frames(heard, take.fps)


def test_a_line_on_standard_input_changes_the_emotion_of_the_live_cli(tmp_path, speech):
    """A performer types (or an agent pipes) an emotion while the CLI runs: a bad one is
    said and changes nothing, a good one is laid from then on and the recording notes it."""
    proc, reader, err_parts = _live_cli_showing(tmp_path, speech, "--speed", "2")
    proc.stdin.write("joyful\nsad=0.7\n")
    proc.stdin.close()
    proc.wait(timeout=60)
    reader.join(10)
    err = "".join(err_parts)
    assert proc.returncode == 0, err
    assert "ignored 'joyful', the emotion stays as it was: unknown emotion 'joyful'" in err and "emotion: sad=0.7" in err
    take = Motion.load_npz(tmp_path / "take.npz")
    (t, spec), = take.meta["emotion_at"]
    assert spec == {"sad": 0.7} and 0 < t < take.n_frames / take.fps


def test_a_session_that_hears_nothing_ends_cleanly(tmp_path, model):
    """A producer that connects and hangs up before a frame's worth of audio: no frame, no
    error, legs and emotion included; the CLI says nothing was recorded."""
    session = LiveSession(TcpSource(sample_rate=16000), GenerateSettings(emotion="sad"), bundle=model[0],
                          network=model[1])
    thread, out = _serve(session)
    with socket.create_connection(("127.0.0.1", session.source.port)) as sock:
        sock.sendall(np.zeros(400, "<i2").tobytes())  # 25 ms: less than a frame
    thread.join(60)
    result = out["result"]
    assert result.error is None and result.motion.n_frames == 0
    assert result.load is None and session.load() is None  # nothing heard: no compute per second to report
    assert result.motion.joint_names[-len(LEG_JOINTS):] == list(LEG_JOINTS)
    proc = subprocess.run([sys.executable, "-m", "diffsheg_core", "live", "--source", "tcp://127.0.0.1:5093",
                           "--speed", "2"], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "--speed plays a speech file faster" in proc.stderr, proc.stderr


def test_the_live_cli_on_port_0_says_its_port_and_no_compute_figure_for_a_short_take(tmp_path, speech, model):
    """`--source tcp://127.0.0.1:0` listens on a free port and says which, so a producer can
    connect; a take too short to judge (1 s) reports no compute per second of speech (not
    the compute over almost no audio)."""
    import re

    clip = Audio(speech.samples[: speech.sample_rate], speech.sample_rate)
    with open(tmp_path / "stderr.txt", "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "diffsheg_core", "live", "--source", "tcp://127.0.0.1:0"],
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=err, text=True,
                                env={**os.environ, "DIFFSHEG_THREADS": "1"})
    try:
        deadline, found = time.monotonic() + 60, None
        while found is None and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
            found = re.search(r"listening on tcp://127\.0\.0\.1:(\d+) \(16000 Hz int16\)",
                              (tmp_path / "stderr.txt").read_text())
        assert found is not None and int(found.group(1)) > 0, (tmp_path / "stderr.txt").read_text()
        with socket.create_connection(("127.0.0.1", int(found.group(1))), timeout=10) as sock:
            sock.sendall(_pcm(clip))
        out, _ = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, (tmp_path / "stderr.txt").read_text()
    frames = n_motion_frames(clip, model[0].config.fps)
    assert out.startswith(f"{frames} frames (1.0 s of audio); latency p50") and "compute" not in out, out
