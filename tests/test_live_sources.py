"""Live audio sources (diffsheg_core.live.sources): a real speech file played at real time,
real TCP sockets on 127.0.0.1 sending real speech, the parsing of source specs, and the
microphone's clear refusal on a machine without PortAudio or without a sound card."""

from __future__ import annotations

import json
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from system_tools import require_library

from diffsheg_core.audio import load_audio
from diffsheg_core.errors import AudioError, DiffshegError
from diffsheg_core.live.feed import AudioFeed, FeedClosed
from diffsheg_core.live.sources import (FileSource, MicSource, TcpSource, microphone_status,
                                        open_source)


@pytest.fixture(scope="module")
def german(data_dir):
    """4.9 s of real read German, 22050 Hz mono 16-bit."""
    return data_dir / "audio" / "lang" / "de_thorsten_1.wav"


@pytest.fixture(scope="module")
def mandarin_pcm(data_dir):
    """4.3 s of real read Mandarin as the int16 samples of the file, 16000 Hz mono."""
    samples, rate = sf.read(data_dir / "audio" / "lang" / "zh_aishell_1.wav", dtype="int16")
    assert rate == 16000 and samples.ndim == 1
    return samples


def drain(feed: AudioFeed, timeout: float = 10.0):
    """Every chunk until the feed closes: (chunks, the feed's error)."""
    chunks, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            chunk = feed.get(0.2)
        except FeedClosed:
            return chunks, feed.error
        if chunk is not None:
            chunks.append(chunk)
    raise AssertionError("the feed did not close in time")


def send(port: int, payload: bytes, piece: int, pace_s: float = 0.0, reset: bool = False) -> None:
    """Connect to the source and write `payload` in pieces of `piece` bytes, `pace_s` apart;
    close normally, or abruptly with a reset (SO_LINGER 0)."""
    with socket.create_connection(("127.0.0.1", port)) as client:
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for start in range(0, len(payload), piece):
            client.sendall(payload[start:start + piece])
            if pace_s:
                time.sleep(pace_s)
        if reset:
            client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))


def wait_until(condition, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


# --- FileSource ------------------------------------------------------------------------


def test_file_source_delivers_the_whole_file_at_the_asked_speed(german):
    expected = load_audio(german)
    source = FileSource(german, speed=4.0)
    assert source.sample_rate == 22050
    assert source.description == "file de_thorsten_1.wav at 4x"
    feed = AudioFeed(source.sample_rate)
    started = time.monotonic()
    source.start(feed)
    chunks, error = drain(feed)
    elapsed = time.monotonic() - started
    source.stop()

    assert error is None
    np.testing.assert_array_equal(np.concatenate([c.samples for c in chunks]), expected.samples)
    assert 0.7 * expected.duration / 4 < elapsed < 2.0 * expected.duration / 4
    stamps = [c.arrived for c in chunks]
    assert all(a <= b for a, b in zip(stamps, stamps[1:]))
    assert max(len(c.samples) for c in chunks) == round(0.02 * 22050)
    # paced, not bursty: the last chunk arrived about duration / 4 after the first
    assert stamps[-1] - stamps[0] > 0.7 * expected.duration / 4
    assert not source.running


@pytest.mark.parametrize("speed", [0, -1.0, float("nan"), float("inf"), "fast", True])
def test_file_source_refuses_a_bad_speed(german, speed):
    with pytest.raises(DiffshegError, match="speed"):
        FileSource(german, speed=speed)


def test_file_source_stop_ends_it_early_and_is_idempotent(german):
    source = FileSource(german, speed=1.0)
    feed = AudioFeed(source.sample_rate)
    source.start(feed)
    time.sleep(0.15)
    source.stop()
    source.stop()
    assert not source.running and feed.closed and feed.error is None
    with pytest.raises(DiffshegError, match="already started"):
        source.start(AudioFeed(source.sample_rate))


def test_a_feed_at_another_rate_is_refused(german):
    with pytest.raises(DiffshegError, match="22050 Hz"):
        FileSource(german).start(AudioFeed(16000))


# --- TcpSource -------------------------------------------------------------------------


def test_tcp_source_passes_a_producer_s_pcm_and_ends_when_it_closes(mandarin_pcm):
    source = TcpSource("127.0.0.1", 0)
    feed = AudioFeed(source.sample_rate)
    source.start(feed)
    assert source.port > 0
    assert source.description == f"tcp://127.0.0.1:{source.port} (16000 Hz int16)"
    payload = mandarin_pcm.astype("<i2").tobytes()
    # 1281 bytes (an odd number: half a sample carried to the next read) every 10 ms: about 4x real time
    producer = threading.Thread(target=send, args=(source.port, payload, 1281, 0.01))
    producer.start()
    chunks, error = drain(feed)
    producer.join()

    assert error is None
    received = np.concatenate([c.samples for c in chunks])
    np.testing.assert_array_equal(received, mandarin_pcm.astype(np.float32) / 32768)
    assert max(len(c.samples) for c in chunks) <= 0.05 * 16000
    assert feed.dropped == 0 and source.connections == 1
    assert wait_until(lambda: not source.running)  # the session ended with the connection
    source.stop()


def test_tcp_source_reports_a_connection_reset_mid_stream(mandarin_pcm):
    source = TcpSource("127.0.0.1", 0)
    feed = AudioFeed(source.sample_rate)
    source.start(feed)
    send(source.port, mandarin_pcm[:8000].astype("<i2").tobytes(), 640, 0.005, reset=True)
    _, error = drain(feed)
    source.stop()
    assert error and "reset" in error and f"tcp://127.0.0.1:{source.port}" in error
    assert "Traceback" not in error


def test_tcp_source_reports_half_a_sample_at_the_end(mandarin_pcm):
    source = TcpSource("127.0.0.1", 0)
    feed = AudioFeed(source.sample_rate)
    source.start(feed)
    send(source.port, mandarin_pcm[:1000].astype("<i2").tobytes() + b"\x01", 2001)
    chunks, error = drain(feed)
    source.stop()
    assert sum(len(c.samples) for c in chunks) == 1000
    assert error and "odd number of bytes" in error


def test_a_too_fast_producer_fills_the_feed_and_the_source_keeps_running(mandarin_pcm):
    source = TcpSource("127.0.0.1", 0)
    feed = AudioFeed(source.sample_rate, capacity_s=1.0)
    source.start(feed)
    ten_seconds = np.concatenate([mandarin_pcm, mandarin_pcm, mandarin_pcm])[:160000]
    with socket.create_connection(("127.0.0.1", source.port)) as client:
        client.sendall(ten_seconds.astype("<i2").tobytes())  # at once, and nobody reads the feed
        deadline = time.monotonic() + 5
        while feed.received < len(ten_seconds) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert feed.received == len(ten_seconds)
        assert feed.dropped == len(ten_seconds) - 16000
        assert source.running and not feed.closed
    assert wait_until(lambda: feed.closed)
    assert feed.error is None  # the producer closed: the session ended cleanly
    source.stop()
    assert not source.running


def test_keep_listening_serves_one_producer_after_another(mandarin_pcm):
    source = TcpSource("127.0.0.1", 0, keep_listening=True)
    feed = AudioFeed(source.sample_rate)
    source.start(feed)
    first, second = mandarin_pcm[:4000], mandarin_pcm[4000:9000]
    send(source.port, first.astype("<i2").tobytes(), 4000)
    send(source.port, second.astype("<i2").tobytes(), 1000, reset=True)
    send(source.port, second.astype("<i2").tobytes(), 1000)
    assert wait_until(lambda: source.connections == 3 and feed.received >= 4000 + 5000)
    time.sleep(0.2)
    assert source.running and not feed.closed
    source.stop()
    chunks, error = drain(feed)
    assert error is None and not source.running
    assert source.connections == 3
    assert len(source.connection_errors) == 1 and "reset" in source.connection_errors[0]
    received = np.concatenate([c.samples for c in chunks])
    np.testing.assert_array_equal(received[:4000], first / np.float32(32768))
    np.testing.assert_array_equal(received[-5000:], second / np.float32(32768))


def test_tcp_source_listens_only_on_loopback_unless_allowed():
    for host in ("0.0.0.0", ""):
        with pytest.raises(DiffshegError, match="allow_remote=True"):
            TcpSource(host, 0)
    source = TcpSource("0.0.0.0", 0, allow_remote=True)
    source.start(AudioFeed(source.sample_rate))
    assert source.port > 0 and source.running
    source.stop()
    for host in ("localhost", "127.0.0.1"):
        TcpSource(host, 0)  # loopback: allowed


def test_tcp_source_says_when_its_port_is_taken():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        source = TcpSource("127.0.0.1", port)
        with pytest.raises(DiffshegError, match=f"cannot listen on tcp://127.0.0.1:{port}.*another port"):
            source.start(AudioFeed(source.sample_rate))
    with pytest.raises(DiffshegError, match="port"):
        TcpSource("127.0.0.1", 70000)
    with pytest.raises(DiffshegError, match="sample rate"):
        TcpSource("127.0.0.1", 0, sample_rate=100)


def test_stop_before_any_producer_closes_the_feed_cleanly():
    source = TcpSource("127.0.0.1", 0)
    feed = AudioFeed(source.sample_rate)
    source.start(feed)
    source.stop()
    source.stop()
    assert feed.closed and feed.error is None and not source.running
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", source.port), timeout=1).close()


# --- open_source -------------------------------------------------------------------------


def test_open_source_reads_files_and_tcp_addresses(german):
    file_source = open_source(str(german), speed=2.0)
    assert isinstance(file_source, FileSource) and file_source.speed == 2.0

    tcp = open_source("tcp://127.0.0.1:5005")
    assert isinstance(tcp, TcpSource) and (tcp.host, tcp.port, tcp.sample_rate) == ("127.0.0.1", 5005, 16000)
    assert not tcp.keep_listening
    tcp = open_source("tcp://localhost:0?rate=22050&keep_listening=1")
    assert (tcp.host, tcp.port, tcp.sample_rate, tcp.keep_listening) == ("localhost", 0, 22050, True)
    assert open_source("tcp://[::1]:5005").description == "tcp://[::1]:5005 (16000 Hz int16)"


@pytest.mark.parametrize("spec, words", [
    ("", "tcp://HOST:PORT"),
    ("   ", "mic:NAME"),
    ("mic:", "names no microphone"),
    ("udp://127.0.0.1:5005", "udp:// is not a live source"),
    ("ws://127.0.0.1:5005", "ws:// is not a live source"),
    ("tcp://127.0.0.1", "tcp://HOST:PORT"),
    ("tcp://:5005", "tcp://HOST:PORT"),
    ("tcp://127.0.0.1:port", "not a valid"),
    ("tcp://127.0.0.1:99999", "not a valid"),
    ("tcp://127.0.0.1:5005/audio", "tcp://HOST:PORT"),
    ("tcp://127.0.0.1:5005?rate=fast", "rate must be a whole number"),
    ("tcp://127.0.0.1:5005?rate=100", "sample rate"),
    ("tcp://127.0.0.1:5005?format=f32", "unknown option format"),
    ("tcp://0.0.0.0:5005", "allow_remote"),
])
def test_open_source_names_the_accepted_forms(spec, words):
    with pytest.raises(DiffshegError, match=words.replace("?", r"\?").replace(".", r"\.")):
        open_source(spec)


def test_open_source_reports_a_missing_file_clearly(tmp_path):
    with pytest.raises(AudioError, match="does not exist: check the path"):
        open_source(str(tmp_path / "talk.wav"))


# --- the microphone on this machine ---------------------------------------------------------


def test_the_microphone_says_why_it_cannot_be_used_here():
    reason = microphone_status()
    if reason is None:
        pytest.skip("this machine has a usable microphone")
    assert any(fix in reason for fix in ("libportaudio2", "pip install sounddevice", "plug one in",
                                         "choose one by name"))
    with pytest.raises(DiffshegError) as raised:
        MicSource()
    assert str(raised.value) == reason or "no default microphone" in str(raised.value)
    with pytest.raises(DiffshegError):
        open_source("mic:USB Mic")


MIC_SCRIPT = r"""
import json, sys, time
import numpy as np
from diffsheg_core.live.sources import MicSource, microphone_status, open_source
from diffsheg_core.errors import DiffshegError
from diffsheg_core.live.feed import AudioFeed, FeedClosed
status = microphone_status()
if status and ("PortAudio" in status or "sounddevice" in status):
    print(json.dumps({"skip": status})); sys.exit()
mic = open_source("mic:speechmic")
feed = AudioFeed(mic.sample_rate, capacity_s=30)
mic.start(feed)
deadline = time.monotonic() + 10
while feed.received < int(sys.argv[1]) and time.monotonic() < deadline:
    time.sleep(0.05)
running, closed = mic.running, feed.closed
mic.stop()
chunks = []
try:
    while True:
        chunks.append(feed.get(0).samples)
except FeedClosed:
    pass
try:
    MicSource("no such microphone")
    wrong = None
except DiffshegError as error:
    wrong = str(error)
np.save(sys.argv[2], np.concatenate(chunks))
print(json.dumps({"status": status, "description": mic.description, "running": running,
                  "closed": closed, "error": feed.error, "stopped": not mic.running,
                  "sizes": sorted({len(c) for c in chunks}), "wrong": wrong}))
"""


@pytest.mark.skipif(sys.platform != "linux", reason="the stand-in microphone is an ALSA device")
def test_a_real_portaudio_stream_from_an_alsa_device_playing_speech(tmp_path, mandarin_pcm):
    """MicSource on a real PortAudio input stream: an ALSA `file` device whose capture side
    reads real speech (float32) stands in for a microphone. ALSA reads ~/.asoundrc, so the
    script runs with HOME in a temporary folder. Needs PortAudio (libportaudio2): fails
    without it. The null device has no clock: it records far faster than real time."""
    require_library("portaudio", "libportaudio2")
    speech = mandarin_pcm.astype(np.float32) / 32768
    (tmp_path / "speech.f32").write_bytes(speech.astype("<f4").tobytes())
    (tmp_path / ".asoundrc").write_text(
        'pcm.speechmic {\n type file\n slave.pcm "null"\n file "/dev/null"\n'
        f' infile "{tmp_path / "speech.f32"}"\n format "raw"\n}}\n')
    env = {**os.environ, "HOME": str(tmp_path), "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    out = subprocess.run([sys.executable, "-c", MIC_SCRIPT, str(len(speech)), str(tmp_path / "got.npy")],
                         env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    if "skip" in result:
        pytest.skip(result["skip"])
    assert result["status"] is None
    assert result["description"].startswith("microphone 'speechmic' at ")  # the device's own rate
    assert result["running"] and not result["closed"]
    assert result["stopped"] and result["error"] is None
    rate = int(result["description"].rsplit(" at ", 1)[1].split()[0])
    assert result["sizes"] == [round(0.02 * rate)]  # 20 ms blocks
    got = np.load(tmp_path / "got.npy")
    np.testing.assert_array_equal(got[:len(speech)], speech)
    assert "no microphone 'no such microphone'" in result["wrong"] and "speechmic" in result["wrong"]


def test_a_tcp_address_may_allow_remote_producers_when_asked():
    from diffsheg_core.live.sources import open_source

    with pytest.raises(DiffshegError, match="allow_remote=1"):
        open_source("tcp://0.0.0.0:0")
    source = open_source("tcp://0.0.0.0:0?allow_remote=1")
    assert source.allow_remote and not source.keep_listening


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.parametrize("query, words", [
    ("?allow_remote=", "allow_remote needs a value: allow_remote=1 to listen beyond loopback, or leave it out"),
    ("?allow_remote", "allow_remote needs a value: allow_remote=1 to listen beyond loopback, or leave it out"),
    ("?rate=16000&allow_remote=", "allow_remote needs a value"),
    ("?allow_remote=maybe", "allow_remote must be 1 or 0, got 'maybe': allow_remote=1 to listen beyond loopback"),
    ("?allow_remote=%20", "allow_remote must be 1 or 0, got ' '"),
    ("?allow_remote=1&allow_remote=", "allow_remote is given twice ('1' and ''): give it once"),
    ("?allow_remote=&allow_remote=1", "allow_remote is given twice"),
    ("?allow_remote=0", "reachable from other computers"),
    ("?allow_remote=false", "reachable from other computers"),
    ("?allow_remote=no", "reachable from other computers"),
    ("?keep_listening=&allow_remote=1", "keep_listening needs a value: keep_listening=1 to wait"),
    ("?keep_listening&allow_remote=1", "keep_listening needs a value"),
    ("?keep_listening=2&allow_remote=1", "keep_listening must be 1 or 0, got '2'"),
    ("?rate=16000&rate=&allow_remote=1", "rate is given twice"),
    ("?rate=&allow_remote=1", "rate must be a whole number of Hz, got '': e.g. rate=16000"),
    ("?=1&allow_remote=1", "unknown option"),
])
@pytest.mark.parametrize("host", ["0.0.0.0", "[::]"])
def test_an_empty_or_malformed_tcp_option_is_refused_and_nothing_listens(host, query, words):
    """A template with an unset variable (`?allow_remote=$ALLOW`) must not open the avatar
    to the network: no value, a bad one or a repeated one is an error naming the fix."""
    port = _free_port()
    spec = f"tcp://{host}:{port}{query}"
    with pytest.raises(DiffshegError, match=words.replace("?", r"\?").replace("(", r"\(").replace(")", r"\)")):
        open_source(spec)
    with pytest.raises(ConnectionRefusedError):  # nothing was bound on the port
        socket.create_connection(("127.0.0.1", port), timeout=1).close()


@pytest.mark.parametrize("spec", ["tcp://0:5005", "tcp://[::]:5005", "tcp://[::ffff:0.0.0.0]:5005",
                                  "tcp://user@0.0.0.0:5005", "tcp://:5005?allow_remote=1"])
def test_no_other_form_of_address_listens_beyond_loopback_unasked(spec):
    with pytest.raises(DiffshegError, match="allow_remote=1|tcp://HOST:PORT"):
        open_source(spec)


def test_tcp_flags_are_explicit_yes_or_no():
    for value, yes in (("1", True), ("true", True), ("YES", True), ("0", False), ("False", False), ("no", False)):
        source = open_source(f"tcp://127.0.0.1:0?keep_listening={value}&allow_remote={value}")
        assert source.keep_listening is yes and source.allow_remote is yes
    for value in ("", "0", "false", 1, None):  # bool("0") would be a yes: only True or False
        with pytest.raises(DiffshegError, match="allow_remote must be True or False"):
            TcpSource("0.0.0.0", 0, allow_remote=value)
    with pytest.raises(DiffshegError, match="keep_listening must be True or False"):
        TcpSource("127.0.0.1", 0, keep_listening="")
    with pytest.raises(DiffshegError, match="host is text"):
        TcpSource(None, 0, allow_remote=True)
