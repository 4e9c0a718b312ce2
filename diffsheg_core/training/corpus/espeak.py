"""espeak-ng through its C library (ctypes), for exact phone timings.

The command line prints timed phonemes only for MBROLA voices (`--pho`). The library
reports a phoneme event carrying the exact output sample at which each phoneme starts,
for every voice (for stops, the burst: the closure before it is given back to the stop
from the audio's silence); lexical stress comes from `espeak_TextToPhonemes` and is matched to the
spoken vowels by sequence alignment.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import pickle

import numpy as np

from ...errors import DiffshegError
from .phones import SILENCE, Phone, VOWELS, from_espeak, merge_silences
from .synthesis import Synthesis, VoiceSpec

_AUDIO_OUTPUT_SYNCHRONOUS = 2
_INITIALIZE_PHONEME_EVENTS = 0x0001
_EVENT_LIST_TERMINATED, _EVENT_PHONEME = 0, 7
_RATE, _VOLUME, _PITCH, _RANGE, _WORDGAP = 1, 2, 3, 4, 7
_POS_CHARACTER = 1


class _EventId(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    _fields_ = [
        ("type", ctypes.c_int), ("unique_identifier", ctypes.c_uint),
        ("text_position", ctypes.c_int), ("length", ctypes.c_int),
        ("audio_position", ctypes.c_int), ("sample", ctypes.c_int),
        ("user_data", ctypes.c_void_p), ("id", _EventId),
    ]


_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int,
                             ctypes.POINTER(_Event))


class _Engine:
    """One espeak-ng instance per process (the library keeps global state)."""

    def __init__(self) -> None:
        name = ctypes.util.find_library("espeak-ng") or "libespeak-ng.so.1"
        try:
            lib = ctypes.CDLL(name)
        except OSError as exc:
            raise DiffshegError(
                "espeak-ng's library is not installed: run `apt-get install espeak-ng` "
                f"(Debian/Ubuntu) and retry ({exc})") from exc
        lib.espeak_Synth.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_uint, ctypes.c_int,
                                     ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p]
        lib.espeak_SetVoiceByName.argtypes = [ctypes.c_char_p]
        lib.espeak_TextToPhonemes.restype = ctypes.c_char_p
        lib.espeak_TextToPhonemes.argtypes = [ctypes.POINTER(ctypes.c_void_p), ctypes.c_int, ctypes.c_int]
        self.sample_rate = lib.espeak_Initialize(_AUDIO_OUTPUT_SYNCHRONOUS, 0, None,
                                                 _INITIALIZE_PHONEME_EVENTS)
        if self.sample_rate <= 0:
            raise DiffshegError("espeak-ng failed to start: is espeak-ng-data installed?")
        self.lib = lib
        self._chunks: list[np.ndarray] = []
        self._events: list[tuple[int, str]] = []
        self._callback = _CALLBACK(self._collect)
        lib.espeak_SetSynthCallback(self._callback)

    def _collect(self, wav, n, events) -> int:
        if n > 0:
            self._chunks.append(np.ctypeslib.as_array(wav, shape=(n,)).copy())
        i = 0
        while events[i].type != _EVENT_LIST_TERMINATED:
            if events[i].type == _EVENT_PHONEME:
                self._events.append((events[i].sample, events[i].id.string.decode("ascii", "replace")))
            i += 1
        return 0

    def set_voice(self, voice: VoiceSpec) -> None:
        if self.lib.espeak_SetVoiceByName(voice.name.encode()) != 0:
            raise DiffshegError(f"espeak-ng has no voice {voice.name!r}: see `espeak-ng --voices`")
        for param, value in ((_RATE, voice.rate), (_PITCH, voice.pitch), (_RANGE, voice.pitch_range),
                             (_WORDGAP, voice.word_gap), (_VOLUME, 100)):
            self.lib.espeak_SetParameter(param, int(value), 0)

    def speak(self, text: str) -> tuple[np.ndarray, list[tuple[int, str]]]:
        self._chunks, self._events = [], []
        data = text.encode("utf-8")
        if self.lib.espeak_Synth(data, len(data) + 1, 0, _POS_CHARACTER, 0, 0, None, None) != 0:
            raise DiffshegError(f"espeak-ng could not synthesise {text[:40]!r}")
        self.lib.espeak_Synchronize()
        samples = np.concatenate(self._chunks) if self._chunks else np.zeros(0, np.int16)
        return samples.astype(np.float32) / 32768.0, self._events

    def stressed_vowels(self, text: str, language: str) -> list[tuple[str, int]]:
        """(ARPAbet vowel, stress) in spoken order, from espeak's phoneme transcription."""
        buf = ctypes.create_string_buffer(text.encode("utf-8"))
        ptr = ctypes.c_void_p(ctypes.addressof(buf))
        out: list[tuple[str, int]] = []
        while ptr.value:
            chunk = self.lib.espeak_TextToPhonemes(ctypes.byref(ptr), 0, ord("|") << 8) or b""
            for word in chunk.decode("utf-8", "replace").split():
                for token in word.split("|"):
                    stress = 1 if "'" in token else 2 if "," in token else 0
                    label = from_espeak(token.replace("'", "").replace(",", ""), language)
                    if label in VOWELS:
                        out.append((label, stress))
        return out


    def run(self, voice: VoiceSpec, text: str) -> tuple[np.ndarray, list[tuple[int, str]], list[tuple[str, int]]]:
        """Samples, phoneme events and stressed vowels of `text` spoken by `voice`."""
        self.set_voice(voice)
        samples, events = self.speak(text)
        return samples, events, self.stressed_vowels(text, voice.language)


_engine: _Engine | None = None


def _get_engine() -> _Engine:
    global _engine
    if _engine is None:
        _engine = _Engine()
    return _engine


def _run_isolated(voice: VoiceSpec, text: str) -> tuple[np.ndarray, list[tuple[int, str]], list[tuple[str, int]]]:
    """`_Engine.run` in a forked child of the freshly started engine. espeak-ng carries
    state from one utterance to the next (the same text comes out a few samples longer
    or shorter, with other noise), so an utterance would depend on what was spoken before
    it in the process; from a pristine copy it is reproducible. Without fork, in-process."""
    engine = _get_engine()
    if not hasattr(os, "fork"):
        return engine.run(voice, text)
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: speak, send the result (or the error) back, exit at once
        code = 1
        try:
            os.close(read_fd)
            ctypes.CDLL(None).srand(1)
            try:
                payload = pickle.dumps(engine.run(voice, text))
            except DiffshegError as exc:
                payload = pickle.dumps(exc)
            with os.fdopen(write_fd, "wb") as fh:
                fh.write(payload)
            code = 0
        finally:
            os._exit(code)
    os.close(write_fd)
    with os.fdopen(read_fd, "rb") as fh:
        data = fh.read()
    _, status = os.waitpid(pid, 0)
    if status != 0 or not data:
        raise DiffshegError(f"espeak-ng crashed on {text[:40]!r} (status {status})")
    result = pickle.loads(data)
    if isinstance(result, DiffshegError):
        raise result
    return result


def _align_stress(spoken: list[str], lexical: list[tuple[str, int]]) -> list[int]:
    """Stress per spoken vowel: edit-distance alignment of the spoken vowel labels with the
    transcription's (they differ where synthesis reduces or merges vowels)."""
    n, m = len(spoken), len(lexical)
    cost = np.zeros((n + 1, m + 1))
    cost[:, 0], cost[0, :] = np.arange(n + 1), np.arange(m + 1)
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            sub = cost[i - 1, j - 1] + (spoken[i - 1] != lexical[j - 1][0])
            cost[i, j] = min(sub, cost[i - 1, j] + 1, cost[i, j - 1] + 1)
    stress, i, j = [0] * n, n, m
    while i > 0 and j > 0:
        if cost[i, j] == cost[i - 1, j - 1] + (spoken[i - 1] != lexical[j - 1][0]):
            stress[i - 1] = lexical[j - 1][1]
            i, j = i - 1, j - 1
        elif cost[i, j] == cost[i - 1, j] + 1:
            i -= 1
        else:
            j -= 1
    return stress


_STOPS = frozenset({"P", "B", "T", "D", "K", "G", "CH", "JH"})
_CLOSURE_DB = -35.0
"""A 5 ms block this far below the utterance's loud blocks is stop closure (silence)."""
_MAX_CLOSURE = 0.12
_MIN_PAUSE = 0.025
"""Shorter pauses between words (s) are joined to the phone before."""


def _attach_closures(samples: np.ndarray, sr: int, phones: list[Phone]) -> list[Phone]:
    """espeak-ng reports a stop when its burst starts; the closure before it is silence it
    counts to the phone before. Give the closure to the stop (where aligners and the lips
    put it): move each stop's start back over the silent blocks just before it."""
    block = max(sr // 200, 1)
    n = len(samples) // block
    if n == 0:
        return phones
    level = 10 * np.log10(np.mean(samples[: n * block].reshape(n, block).astype(np.float64) ** 2, axis=1) + 1e-12)
    quiet = level < np.percentile(level, 95) + _CLOSURE_DB
    out = list(phones)
    for i in range(1, len(out)):
        stop, prev = out[i], out[i - 1]
        if stop.label not in _STOPS or prev.label == SILENCE:
            continue
        b = int(stop.start * sr) // block
        earliest = max(prev.start + 0.4 * (prev.end - prev.start), stop.start - _MAX_CLOSURE)
        while b > 0 and quiet[b - 1] and (b - 1) * block / sr >= earliest:
            b -= 1
        start = b * block / sr
        if start < stop.start:
            out[i - 1] = Phone(prev.label, prev.start, start, prev.stress)
            out[i] = Phone(stop.label, start, stop.end, stop.stress)
    return out


def _is_modifier(symbol: str) -> bool:
    """A bare modifier of the phone before (palatalisation: `;`, Japanese `_j`) or a switch
    of language (`(en)`), not a phone."""
    return (not symbol.strip(";") or (symbol.startswith("_") and symbol[1:].isalpha())
            or symbol.startswith("("))


def synthesize(text: str, voice: VoiceSpec) -> Synthesis:
    """Speak `text` with an espeak-ng voice; phones timed to the exact output sample."""
    samples, events, lexical = _run_isolated(voice, text)
    if not events or len(samples) == 0:
        raise DiffshegError(f"espeak-ng produced no speech for {text[:40]!r}")
    sr = _get_engine().sample_rate
    # a bare modifier (';', palatalisation) and a pause too short to see belong to the
    # phone before them: dropping their events extends that phone over them
    language = voice.language
    events = [(s, sym) for i, (s, sym) in enumerate(events) if not _is_modifier(sym) and not (
        from_espeak(sym, language) == SILENCE and i + 1 < len(events) and events[i + 1][0] - s < _MIN_PAUSE * sr)]
    bounds = [s for s, _ in events] + [len(samples)]
    phones = [] if bounds[0] == 0 else [Phone(SILENCE, 0.0, bounds[0] / sr, 0)]
    for (start, symbol), end in zip(events, bounds[1:]):
        if end > start:
            label = from_espeak(symbol, language)
            phones.append(Phone(label, start / sr, end / sr, -1 if label in VOWELS else 0))
    vowel_idx = [i for i, p in enumerate(phones) if p.is_vowel]
    stress = _align_stress([phones[i].label for i in vowel_idx], lexical)
    for i, s in zip(vowel_idx, stress):
        phones[i] = Phone(phones[i].label, phones[i].start, phones[i].end, s)
    return Synthesis(samples, sr, _attach_closures(samples, sr, merge_silences(phones)), voice)
