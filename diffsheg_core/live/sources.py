"""Live audio sources: a microphone, a speech file played at real time, a TCP socket.

Each source has `sample_rate` (Hz), `description` (for status lines), `start(feed)`, which
starts its own daemon thread (or audio callback) and returns at once, and `stop()`, which
is idempotent, closes the feed and joins the thread. The source puts mono chunks of about
20-50 ms into an `AudioFeed` made at its rate (`AudioFeed(source.sample_rate)`) and closes
the feed when it ends; when it ended badly, with a reason a user can read (the feed's
`error`), never a traceback. `open_source` turns a user's text ("mic", "mic:USB",
"tcp://127.0.0.1:5005", a file path) into a source.

The TCP protocol (`TcpSource`), for a TTS engine or an LLM agent that speaks through the
avatar:

- the source listens on HOST:PORT (loopback only unless `allow_remote=True`) and serves
  one producer connection at a time; a second one waits in the listen queue until the
  first closes (without `keep_listening` it is then dropped, as the session has ended);
- the producer connects and writes raw PCM: signed 16-bit little-endian integers, one
  channel, at the source's `sample_rate` (16000 Hz unless `?rate=` / `sample_rate` says
  otherwise); no header, no framing, any write sizes (an odd trailing byte of one read is
  kept for the next). Nothing is ever sent back;
- it writes at real time or faster: audio that the generator cannot take in time is
  dropped and counted by the feed (`feed.dropped`), never blocking the producer's writes
  beyond what TCP buffers;
- closing the connection (a normal FIN, e.g. `sock.close()` in Python) ends the session:
  the feed closes cleanly. With `keep_listening=True` the source instead waits for the
  next producer and the session only ends at `stop()`;
- a connection reset, or a close after an odd number of bytes (half a sample), ends the
  session with a reason in `feed.error` (with `keep_listening`, the reason is kept in
  `connection_errors` and the source waits for the next producer).

For example, from Python: `s = socket.create_connection(("127.0.0.1", 5005));
s.sendall(pcm_int16.astype("<i2").tobytes()); s.close()`, or from a shell:
`sox talk.wav -t raw -r 16000 -e signed -b 16 -c 1 - | nc -N 127.0.0.1 5005`.

`sounddevice` (the microphone) is imported only when a microphone is used or its status
asked for: it needs the PortAudio library, which its wheels carry on Windows and macOS and
which Linux provides as a system package (`libportaudio2`).
"""

from __future__ import annotations

import functools
import ipaddress
import math
import os
import platform
import socket
import threading
import time
import urllib.parse
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np

from ..audio import MAX_SAMPLE_RATE, MIN_SAMPLE_RATE, open_audio_file
from ..errors import DiffshegError
from .feed import AudioFeed

CHUNK_S = 0.02  # the length of a chunk a source puts: 20 ms
MAX_TCP_CHUNK_S = 0.05  # a TCP read takes at most this much audio at once
FILE_READ_S = 1.0  # a file is read in pieces of this length, and put in chunks of CHUNK_S
MIC_SILENT_S = 2.0  # a microphone whose callback has not run for this long has stopped
POLL_S = 0.1  # how often a waiting thread looks whether it was stopped
JOIN_S = 5.0  # how long stop() waits for a source's thread
DEFAULT_TCP_RATE = 16000

TCP_FLAGS = {"keep_listening": "wait for the next producer when one hangs up",
             "allow_remote": "listen beyond loopback"}  # a tcp:// address's yes/no options: what yes does
FLAG_WORDS = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}

SPEC_FORMS = ("'mic' (the default microphone), 'mic:NAME' or 'mic:INDEX' (a microphone by "
              "name or number), 'tcp://HOST:PORT' (optionally '?rate=22050', '&keep_listening=1', "
              "'&allow_remote=1'), "
              "or the path of a speech file")


class Source:
    """What every live source has: `sample_rate`, `description`, `start(feed)`, `stop()`,
    and `running` (its thread or stream is live)."""

    sample_rate: int

    def __init__(self) -> None:
        self._feed: Optional[AudioFeed] = None
        self._thread: Optional[threading.Thread] = None
        self._stopping = threading.Event()

    @property
    def description(self) -> str:
        raise NotImplementedError

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, feed: AudioFeed) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        """Stop the source and close the feed (with no error if it had not ended); again: nothing."""
        self._stopping.set()
        self._release()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(JOIN_S)
        if self._feed is not None:
            self._feed.close()

    def _release(self) -> None:
        """Unblock the source's thread (close its sockets, its stream); called by stop()."""

    def _attach(self, feed: AudioFeed) -> None:
        if self._feed is not None:
            raise DiffshegError(f"{self.description} was already started: make a new source to start again")
        if feed.sample_rate != self.sample_rate:
            raise DiffshegError(f"the audio feed runs at {feed.sample_rate} Hz but {self.description} "
                                f"delivers {self.sample_rate} Hz: make the feed with AudioFeed(source.sample_rate)")
        self._feed = feed

    def _run_thread(self, target, name: str) -> None:
        def guarded() -> None:
            try:
                target()
            except Exception as error:  # never a traceback from a source's thread: a reason
                if not self._stopping.is_set():
                    self._feed.close(f"{self.description} failed: {error}")

        self._thread = threading.Thread(target=guarded, name=name, daemon=True)
        self._thread.start()


# --- a file at real time ---------------------------------------------------------


class FileSource(Source):
    """A speech file (any format `audio.open_audio_file` reads, mixed down to mono, at its
    own rate) put in chunks of `chunk_s` seconds as fast as a speaker would say it, times
    `speed`. A chunk is put when its last sample would have been spoken, counted from
    `start` (so the pacing does not drift). The feed closes at the end of the file."""

    def __init__(self, path: Union[str, os.PathLike], speed: float = 1.0, chunk_s: float = CHUNK_S):
        super().__init__()
        for name, value in (("speed", speed), ("chunk_s", chunk_s)):
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) \
                    or not math.isfinite(value) or value <= 0:
                raise DiffshegError(f"a speech file's playback {name} must be a number above 0, got {value!r}"
                                    + (" (1 is real time, 2 twice as fast)" if name == "speed" else ""))
        self.path = str(path)
        self.speed = float(speed)
        self.recording = open_audio_file(path)  # an AudioError if missing or not speech
        self.sample_rate = int(self.recording.sample_rate)
        self.chunk = max(1, int(round(chunk_s * self.sample_rate)))
        self.started_at: Optional[float] = None

    @property
    def description(self) -> str:
        return f"file {Path(self.path).name} at {self.speed:g}x"

    def start(self, feed: AudioFeed) -> None:
        self._attach(feed)
        self._run_thread(self._play, f"diffsheg file {Path(self.path).name}")

    def _play(self) -> None:
        feed, rate, total = self._feed, self.sample_rate, self.recording.n_samples
        piece = max(self.chunk, int(FILE_READ_S * rate) // self.chunk * self.chunk)
        self.started_at = t0 = time.monotonic()
        for begin in range(0, total, piece):
            try:
                samples = self.recording.read(begin, min(begin + piece, total)).samples
            except Exception as error:  # the file vanished or changed while playing
                feed.close(f"{self.description} could not be read any further: {error}")
                return
            for offset in range(0, len(samples), self.chunk):
                chunk = samples[offset:offset + self.chunk]
                due = t0 + (begin + offset + len(chunk)) / (rate * self.speed)
                if self._stopping.wait(max(0.0, due - time.monotonic())):
                    return
                feed.put(chunk)
        feed.close()


# --- a microphone ------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def _import_sounddevice() -> tuple[Any, Optional[str]]:
    """(the sounddevice module, None), or (None, why the microphone cannot be used). Cached:
    finding the library is slow (it runs ldconfig), and installing it needs a restart anyway."""
    try:
        import sounddevice
    except OSError as error:  # the module is there, the PortAudio library is not
        if platform.system() == "Linux":
            fix = ("install it with `sudo apt install libportaudio2` (Debian, Ubuntu; Fedora: "
                   "`sudo dnf install portaudio`, Arch: `sudo pacman -S portaudio`), then restart "
                   "Blender (or the program)")
        else:
            fix = ("the sounddevice package should carry it on Windows and macOS: reinstall it "
                   "(`pip install --force-reinstall sounddevice`, or reinstall the add-on)")
        found = "" if "not found" in str(error) else f" ({error})"
        return None, f"the microphone needs the PortAudio library, which was not found{found}: {fix}"
    except ImportError:
        return None, ("the microphone needs the Python package sounddevice, which is not installed: "
                      "`pip install sounddevice` into the Python that runs this")
    return sounddevice, None


def _sounddevice() -> Any:
    module, reason = _import_sounddevice()
    if module is None:
        raise DiffshegError(reason)
    return module


NO_MICROPHONE = ("no microphone (audio input device) was found: plug one in, or allow this "
                 "program to use it in the system's privacy settings, then restart")


def _input_devices(sd: Any) -> list[dict]:
    try:
        return [dict(d) for d in sd.query_devices() if d["max_input_channels"] > 0]
    except sd.PortAudioError:
        return []


def microphone_status() -> Optional[str]:
    """None when a microphone can be used, else the reason (for the add-on's preferences):
    sounddevice or PortAudio missing, or no input device."""
    module, reason = _import_sounddevice()
    if module is None:
        return reason
    try:
        module.query_devices(kind="input")
    except (module.PortAudioError, ValueError):
        return NO_MICROPHONE if not _input_devices(module) else (
            "no default microphone is set: choose one by name ('mic:NAME') or set a default in "
            "the system's sound settings")
    return None


class MicSource(Source):
    """A microphone (`device`: its name, a part of it, or its number; None: the system's
    default input) recorded mono float32 in blocks of `chunk_s` seconds at `sample_rate`
    (None: the device's default rate). If it stops delivering audio (unplugged, taken away
    by the system), the feed closes with the reason."""

    def __init__(self, device: Union[None, int, str] = None, sample_rate: Optional[int] = None,
                 chunk_s: float = CHUNK_S):
        super().__init__()
        sd = _sounddevice()
        if isinstance(device, str) and device.strip().isdigit():
            device = int(device)
        try:
            info = sd.query_devices(device, kind="input")
        except (sd.PortAudioError, ValueError) as error:
            names = [f"{d['index']}: {d['name']}" for d in _input_devices(sd)]
            if not names:
                raise DiffshegError(NO_MICROPHONE) from None
            if device is None:
                raise DiffshegError("no default microphone is set: choose one of "
                                    f"{'; '.join(names)} (by name or number)") from None
            raise DiffshegError(f"no microphone {device!r} ({error}): the microphones are "
                                f"{'; '.join(names)}") from None
        if info["max_input_channels"] < 1:
            raise DiffshegError(f"'{info['name']}' is not a microphone (it has no input channels): "
                                "choose an input device")
        self.device = int(info["index"])
        self.device_name = str(info["name"])
        rate = info["default_samplerate"] if sample_rate is None else sample_rate
        if isinstance(rate, bool) or not float(rate).is_integer() \
                or not MIN_SAMPLE_RATE <= int(rate) <= MAX_SAMPLE_RATE:
            raise DiffshegError(f"the microphone's sample rate must be a whole number of Hz between "
                                f"{MIN_SAMPLE_RATE} and {MAX_SAMPLE_RATE}, got {rate!r}")
        self.sample_rate = int(rate)
        try:
            sd.check_input_settings(self.device, channels=1, dtype="float32", samplerate=self.sample_rate)
        except (sd.PortAudioError, ValueError) as error:
            raise DiffshegError(f"microphone '{self.device_name}' cannot record mono at {self.sample_rate} Hz "
                                f"({error}): leave the rate empty to use its own") from None
        self.blocksize = max(1, int(round(chunk_s * self.sample_rate)))
        self.status_flags: list[str] = []  # PortAudio's notes (input overflow: a block was lost)
        self._sd = sd
        self._stream = None
        self._lock = threading.Lock()
        self._last_block = 0.0

    @property
    def description(self) -> str:
        return f"microphone '{self.device_name}' at {self.sample_rate} Hz"

    def start(self, feed: AudioFeed) -> None:
        self._attach(feed)
        sd = self._sd
        try:
            self._stream = sd.InputStream(
                device=self.device, samplerate=self.sample_rate, channels=1, dtype="float32",
                blocksize=self.blocksize, callback=self._block, finished_callback=self._finished)
            self._last_block = time.monotonic()
            self._stream.start()
        except (sd.PortAudioError, ValueError) as error:
            self._feed = None
            self._close_stream()
            raise DiffshegError(f"microphone '{self.device_name}' could not be opened ({error}): "
                                "is another program using it, or was it unplugged?") from None
        self._run_thread(self._watch, f"diffsheg microphone {self.device_name}")

    def _block(self, indata, frames, time_info, status) -> None:
        """PortAudio's callback: one block of samples (its own thread; must not block)."""
        self._last_block = time.monotonic()
        if status:
            self.status_flags.append(str(status))  # an overflow loses a block; the stream goes on
        self._feed.put(indata[:, 0].copy())

    def _finished(self) -> None:
        """PortAudio: the stream became inactive; unless stop() asked for it, the device went."""
        if not self._stopping.is_set():
            self._fail("the stream ended by itself (was the microphone unplugged?)")

    def _watch(self) -> None:
        """Close the feed with the reason when the stream stops or falls silent on its own
        (some host APIs just stop calling back when a device vanishes)."""
        while not self._stopping.wait(POLL_S):
            stream = self._stream
            if stream is None:  # stop() closed it
                return
            try:
                active = stream.active
            except self._sd.PortAudioError as error:
                return self._fail(str(error))
            if not active:
                return self._fail("the stream ended by itself (was the microphone unplugged?)")
            if time.monotonic() - self._last_block > MIC_SILENT_S:
                return self._fail(f"no audio came for {MIC_SILENT_S:g} s (was the microphone unplugged, "
                                  "or taken by another program?)")

    def _fail(self, reason: str) -> None:
        if self._feed is not None and not self._stopping.is_set():
            self._feed.close(f"the microphone stopped: {reason}")

    def _release(self) -> None:
        self._close_stream()

    def _close_stream(self) -> None:
        with self._lock:
            stream, self._stream = self._stream, None
        if stream is not None:
            try:
                stream.abort()
                stream.close()
            except Exception:  # the device is gone already: nothing left to close
                pass

    @property
    def running(self) -> bool:
        return super().running and self._stream is not None


# --- a TCP socket ------------------------------------------------------------------


class TcpSource(Source):
    """A server socket on `host`:`port` (0: a free port, `.port` after `start`) that takes
    raw little-endian int16 mono PCM at `sample_rate` from one producer at a time (the
    protocol is in this module's docstring). Only loopback addresses unless `allow_remote`:
    the socket has no authentication, and whoever reaches it speaks through the avatar."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, sample_rate: int = DEFAULT_TCP_RATE,
                 keep_listening: bool = False, allow_remote: bool = False):
        super().__init__()
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise DiffshegError(f"a TCP port is a whole number from 0 to 65535 (0: any free port), got {port!r}")
        if isinstance(sample_rate, bool) or not isinstance(sample_rate, (int, np.integer)) \
                or not MIN_SAMPLE_RATE <= sample_rate <= MAX_SAMPLE_RATE:
            raise DiffshegError(f"the TCP source's sample rate must be a whole number of Hz between "
                                f"{MIN_SAMPLE_RATE} and {MAX_SAMPLE_RATE}, got {sample_rate!r}")
        if not isinstance(host, str):
            raise DiffshegError(f"a TCP host is text, e.g. '127.0.0.1', got {host!r}")
        for name, value in (("keep_listening", keep_listening), ("allow_remote", allow_remote)):
            if not isinstance(value, (bool, np.bool_)):  # bool("0") or bool("false") would be a yes
                raise DiffshegError(f"the TCP source's {name} must be True or False, got {value!r}")
        self.host = host
        self.port = port
        self.sample_rate = int(sample_rate)
        self.keep_listening = bool(keep_listening)
        self.allow_remote = bool(allow_remote)
        self.connections = 0  # producers served so far
        self.connection_errors: list[str] = []  # how connections ended badly (keep_listening)
        self._addresses = self._resolve()
        self._listener: Optional[socket.socket] = None
        self._connection: Optional[socket.socket] = None
        self._lock = threading.Lock()

    def _resolve(self) -> list:
        try:
            addresses = socket.getaddrinfo(self.host or None, self.port, type=socket.SOCK_STREAM,
                                           flags=socket.AI_PASSIVE)
        except socket.gaierror as error:
            raise DiffshegError(f"cannot listen on host {self.host!r} ({error}): use 127.0.0.1") from None
        if not self.allow_remote:
            remote = [a[4][0] for a in addresses
                      if not ipaddress.ip_address(a[4][0].split("%")[0]).is_loopback]
            if remote or not self.host:
                raise DiffshegError(
                    f"host {self.host!r} is reachable from other computers ({', '.join(remote) or 'all addresses'}), "
                    "and anyone who reaches the socket would speak through the avatar: listen on "
                    "127.0.0.1, or on a network you trust add ?allow_remote=1 to the tcp:// address "
                    "(allow_remote=True in Python)")
        return addresses

    @property
    def description(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"tcp://{host}:{self.port} ({self.sample_rate} Hz int16)"

    def start(self, feed: AudioFeed) -> None:
        self._attach(feed)
        family, kind, proto, _, address = self._addresses[0]
        listener = socket.socket(family, kind, proto)
        try:
            if os.name != "nt":  # restart at once after a session (TIME_WAIT); on Windows it would share the port
                listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind(address)
            listener.listen(1)
        except OSError as error:
            listener.close()
            self._feed = None
            raise DiffshegError(f"cannot listen on {self.description} ({error.strerror or error}): "
                                "choose another port, or 0 for any free one") from None
        listener.settimeout(POLL_S)
        self._listener = listener
        self.port = listener.getsockname()[1]
        self._run_thread(self._serve, f"diffsheg tcp {self.port}")

    def _serve(self) -> None:
        try:
            while not self._stopping.is_set():
                try:
                    connection, _ = self._listener.accept()
                except socket.timeout:
                    continue
                except OSError:  # stop() closed the listener
                    return
                self.connections += 1
                error = self._receive(connection)
                if self._stopping.is_set():
                    return
                if not self.keep_listening:
                    self._feed.close(error)
                    return
                if error:
                    self.connection_errors.append(error)
        finally:
            self._close_sockets()

    def _receive(self, connection: socket.socket) -> Optional[str]:
        """Put what one producer sends until it closes; why it ended badly, or None."""
        with self._lock:
            self._connection = connection
        most = max(2, int(MAX_TCP_CHUNK_S * self.sample_rate) * 2)
        carry = b""
        try:
            connection.settimeout(POLL_S)
            while not self._stopping.is_set():
                try:
                    data = connection.recv(most - len(carry))
                except socket.timeout:
                    continue
                if not data:
                    if carry:
                        return ("the producer closed the connection in the middle of a sample (an odd "
                                "number of bytes): it must send whole 16-bit samples")
                    return None
                data = carry + data
                whole = len(data) - len(data) % 2
                carry = data[whole:]
                if whole:
                    self._feed.put(np.frombuffer(data[:whole], dtype="<i2"))
            return None
        except OSError as error:
            if self._stopping.is_set():
                return None
            why = "was reset" if isinstance(error, ConnectionResetError) else f"failed ({error.strerror or error})"
            return f"the producer's connection to {self.description} {why} in the middle of the stream"
        finally:
            with self._lock:
                self._connection = None
            connection.close()

    def _release(self) -> None:
        self._close_sockets()

    def _close_sockets(self) -> None:
        with self._lock:
            sockets, self._listener = [self._listener], None
            sockets.append(self._connection)
        for sock in sockets:
            if sock is not None:
                try:
                    if sock is not sockets[0]:
                        sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                sock.close()


# --- from the user's words ----------------------------------------------------------


def open_source(spec: str, speed: float = 1.0) -> Source:
    """A source from a user's text: 'mic' or 'mic:NAME_OR_INDEX' (a microphone),
    'tcp://HOST:PORT' with optional '?rate=HZ', '&keep_listening=1' and '&allow_remote=1'
    (a TCP producer; each option given at most once, a flag as 1/true/yes or 0/false/no:
    an empty one is an error, never a yes), anything else the path of a speech file played at `speed` times real time."""
    if not isinstance(spec, str) or not spec.strip():
        raise DiffshegError(f"no live audio source given: use {SPEC_FORMS}")
    text = spec.strip()
    if text.lower() == "mic":
        return MicSource()
    if text.lower().startswith("mic:"):
        name = text[4:].strip()
        if not name:
            raise DiffshegError(f"'{spec}' names no microphone: use {SPEC_FORMS}")
        return MicSource(int(name) if name.isdigit() else name)
    if "://" in text:
        return _tcp_source(spec, text)
    return FileSource(text, speed=speed)


def _tcp_source(spec: str, text: str) -> TcpSource:
    scheme = text.split("://", 1)[0].lower()
    if scheme != "tcp":
        raise DiffshegError(f"'{spec}': {scheme}:// is not a live source this reads; use {SPEC_FORMS}")
    try:
        url = urllib.parse.urlsplit(text)
        port = url.port
    except ValueError as error:
        raise DiffshegError(f"'{spec}' is not a valid tcp://HOST:PORT address ({error})") from None
    if not url.hostname or port is None or url.path not in ("", "/") or url.fragment \
            or url.username is not None:
        raise DiffshegError(f"'{spec}' is not of the form tcp://HOST:PORT (e.g. tcp://127.0.0.1:5005, "
                            "optionally ?rate=22050)")
    options = _tcp_options(spec, url.query)
    rate_text = options.get("rate", str(DEFAULT_TCP_RATE))
    if not rate_text.isdecimal():  # not isdigit: int('²') fails
        raise DiffshegError(f"'{spec}': rate must be a whole number of Hz, got {rate_text!r}: e.g. rate=16000, "
                            "or leave it out for 16000")
    flags = {name: _tcp_flag(spec, name, options[name]) for name in TCP_FLAGS if name in options}
    return TcpSource(url.hostname, port, int(rate_text), **flags)


def _tcp_options(spec: str, query: str) -> dict[str, str]:
    """A tcp:// address's options by name; an unknown or repeated one is an error."""
    options: dict[str, str] = {}
    for name, value in urllib.parse.parse_qsl(query, keep_blank_values=True):
        if name not in ("rate", *TCP_FLAGS):
            raise DiffshegError(f"'{spec}': unknown option {name or '(one with no name)'}; tcp:// takes rate=HZ, "
                                "keep_listening=1 and allow_remote=1")
        if name in options:
            raise DiffshegError(f"'{spec}': {name} is given twice ({options[name]!r} and {value!r}): "
                                "give it once")
        options[name] = value
    return options


def _tcp_flag(spec: str, name: str, value: str) -> bool:
    """An option's yes (1, true, yes) or no (0, false, no); anything else, empty included
    (a bare `?allow_remote`, a template's unset variable), is an error: never a yes."""
    meaning = TCP_FLAGS[name]
    if not value:
        raise DiffshegError(f"'{spec}': {name} needs a value: {name}=1 to {meaning}, or leave it out")
    if value.lower() not in FLAG_WORDS:
        raise DiffshegError(f"'{spec}': {name} must be 1 or 0, got {value!r}: {name}=1 to {meaning}, "
                            "or leave it out")
    return FLAG_WORDS[value.lower()]
