"""Flite through its C library (ctypes): CMU's clustergen voices (rms, slt, awb), whose
statistical parametric speech sounds nearer a human voice than espeak-ng's formants.

Each segment of the synthesised utterance carries its end time, the time the wave was
built with, and its syllable's lexical stress (`R:SylStructure.parent.stress`).
"""

from __future__ import annotations

import ctypes
import ctypes.util

import numpy as np

from ...errors import DiffshegError
from .phones import extend_to, from_festival_segments, merge_silences
from .synthesis import FLITE_VOICES, Synthesis, VoiceSpec

_INSTALL = "run `apt-get install flite` (Debian/Ubuntu) and retry"


class _Wave(ctypes.Structure):
    _fields_ = [("type", ctypes.c_char_p), ("sample_rate", ctypes.c_int), ("num_samples", ctypes.c_int),
                ("num_channels", ctypes.c_int), ("samples", ctypes.POINTER(ctypes.c_short))]


class _Voice(ctypes.Structure):
    _fields_ = [("name", ctypes.c_char_p), ("features", ctypes.c_void_p)]


def _load(name: str) -> ctypes.CDLL:
    path = ctypes.util.find_library(name) or f"lib{name}.so.1"
    try:
        return ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
    except OSError as exc:
        raise DiffshegError(f"flite's library {name!r} is not installed: {_INSTALL} ({exc})") from exc


class _Engine:
    """The flite library and the voices registered so far in this process."""

    def __init__(self) -> None:
        lib = _load("flite")
        for fn, res, args in (
            ("flite_synth_text", ctypes.c_void_p, [ctypes.c_char_p, ctypes.c_void_p]),
            ("utt_wave", ctypes.POINTER(_Wave), [ctypes.c_void_p]),
            ("utt_relation", ctypes.c_void_p, [ctypes.c_void_p, ctypes.c_char_p]),
            ("relation_head", ctypes.c_void_p, [ctypes.c_void_p]),
            ("item_next", ctypes.c_void_p, [ctypes.c_void_p]),
            ("item_feat_string", ctypes.c_char_p, [ctypes.c_void_p, ctypes.c_char_p]),
            ("item_feat_float", ctypes.c_float, [ctypes.c_void_p, ctypes.c_char_p]),
            ("ffeature_string", ctypes.c_char_p, [ctypes.c_void_p, ctypes.c_char_p]),
            ("delete_utterance", None, [ctypes.c_void_p]),
            ("flite_feat_set_float", None, [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_float]),
        ):
            getattr(lib, fn).restype, getattr(lib, fn).argtypes = res, args
        lib.flite_init()
        self.lib = lib
        self.voices: dict[str, int] = {}

    def voice(self, name: str) -> int:
        if name not in self.voices:
            try:
                vox_lib = ctypes.CDLL(ctypes.util.find_library(f"flite_{name}") or f"libflite_{name}.so.1")
            except OSError as exc:
                raise DiffshegError(f"flite has no voice {name!r} (known: {', '.join(FLITE_VOICES)}): "
                                    f"{_INSTALL}") from exc
            register = getattr(vox_lib, f"register_{name}")
            register.restype, register.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
            voice = register(None)
            if not voice:
                raise DiffshegError(f"flite could not load its voice {name!r}: {_INSTALL}")
            self.voices[name] = voice
        return self.voices[name]

    def run(self, voice: VoiceSpec, text: str) -> tuple[np.ndarray, int, list[tuple[str, float, bool]]]:
        """Samples, sample rate and (segment, end time, in a stressed syllable) of `text`."""
        vox = self.voice(voice.name)
        features = ctypes.cast(vox, ctypes.POINTER(_Voice)).contents.features
        self.lib.flite_feat_set_float(features, b"duration_stretch", voice.stretch)
        self.lib.flite_feat_set_float(features, b"f0_shift", voice.f0_shift)
        utt = self.lib.flite_synth_text(text.encode("utf-8"), vox)
        if not utt:
            raise DiffshegError(f"flite could not synthesise {text[:40]!r}")
        try:
            wave = self.lib.utt_wave(utt).contents
            samples = np.ctypeslib.as_array(wave.samples, shape=(wave.num_samples * wave.num_channels,))
            samples = samples.reshape(-1, wave.num_channels)[:, 0].astype(np.float32) / 32768.0
            segments, item = [], self.lib.relation_head(self.lib.utt_relation(utt, b"Segment"))
            while item:
                stress = self.lib.ffeature_string(item, b"R:SylStructure.parent.stress") or b"0"
                segments.append((self.lib.item_feat_string(item, b"name").decode(),
                                 float(self.lib.item_feat_float(item, b"end")), stress == b"1"))
                item = self.lib.item_next(item)
            return samples, int(wave.sample_rate), segments
        finally:
            self.lib.delete_utterance(utt)


_engine: _Engine | None = None


def synthesize(text: str, voice: VoiceSpec) -> Synthesis:
    """Speak `text` with a flite voice (`voice.name`, e.g. 'cmu_us_rms')."""
    global _engine
    if _engine is None:
        _engine = _Engine()
    samples, sr, segments = _engine.run(voice, text)
    phones = from_festival_segments(segments)
    if not phones or len(samples) == 0:
        raise DiffshegError(f"flite produced no speech for {text[:40]!r}")
    return Synthesis(samples, sr, extend_to(merge_silences(phones), len(samples) / sr), voice)
