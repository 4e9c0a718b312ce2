"""Speech input: read and check audio, resample it, and compute the model's features.

Three separate steps, each usable alone:

- reading: `load_audio` turns a file (WAV, FLAC, OGG, MP3 - recognised by content,
  not by extension) or an array into a checked mono `Audio`;
- resampling: `resample` (soxr "HQ", the resampler `librosa.load` uses by default);
- features: `mel_spectrogram` (a power mel spectrogram at 18 kHz, as librosa 0.11
  computes it by default), `mel_features`, the official DiffSHEG mel front end (one
  frame per motion frame); the optional HuBERT features are `torch_layer.hubert`'s
  `hubert_features` (this module says whether they can run: `hubert_status`).

This module runs inside Blender, where only numpy and the bundled wheels exist: it
imports the standard library, numpy, soundfile and soxr, never librosa, scipy or
numba. The mel filterbanks therefore are not computed here but read from
`assets/mel_filters.npz`, which `tools/make_mel_filters.py` makes with librosa.
The audioread fallback (formats libsndfile cannot read) is used only when installed.
HuBERT needs torch, the `transformers` package and a local copy of
facebook/hubert-large-ls960-ft; none is needed for anything else, and this module
never imports transformers or torch.
"""

from __future__ import annotations

import functools
import importlib.util
import math
import os
import re
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Union

import numpy as np
import soundfile as sf
import soxr

from .errors import AudioError, AudioWarning, DiffshegError
from .files import resolve_path

SAMPLE_SPEECH = Path(__file__).resolve().parent / "samples" / "sample_speech.wav"

MIN_SAMPLE_RATE = 4000
MAX_SAMPLE_RATE = 384000
MIN_DURATION_S = 1.0 / 15.0  # one motion frame of the BEAT model
SILENCE_PEAK = 1e-4
MAX_FLOAT_PEAK = 16.0  # beyond this, float samples are integer PCM that was never scaled
MAX_CHANNELS = 16
SOXR_QUALITY = "HQ"  # the resampler librosa.load uses by default (its "soxr_hq")

# Official DiffSHEG mel front end (DESIGN.md section 5).
LOAD_RATE = 22050
MEL_RATE = 18000
MEL_N_FFT = 2048
MEL_N_MELS = 128

# Mel filterbanks (Slaney mel scale and area normalisation, as librosa.filters.mel
# gives by default), stored once by tools/make_mel_filters.py: one (n_mels, 1 + n_fft // 2)
# float32 array per bank, under the key `mel_filter_key(n_fft, n_mels)`.
MEL_FILTERS = Path(__file__).resolve().parent / "assets" / "mel_filters.npz"
MEL_FILTERS_TOOL = "tools/make_mel_filters.py"
MEL_CHUNK = 1 << 20  # samples framed at once (frames x n_fft): about 8 MB of float64

# HuBERT (facebook/hubert-large-ls960-ft): 16 kHz input, one 1024-d frame per 320
# samples from a 400-sample receptive field; long audio runs in chunks of 1000 frames.
HUBERT_REPO_ID = "facebook/hubert-large-ls960-ft"
HUBERT_RATE = 16000
HUBERT_KERNEL = 400
HUBERT_STRIDE = 320
HUBERT_CHUNK = HUBERT_STRIDE * 1000
HUBERT_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")
HUBERT_HOW_TO = (
    f"HuBERT features need `pip install transformers` and the files of {HUBERT_REPO_ID} "
    "(config.json and model.safetensors or pytorch_model.bin) either in the Hugging Face "
    f"cache (`huggingface-cli download {HUBERT_REPO_ID}`) or in a folder whose path you "
    "pass as model_path; nothing is downloaded automatically"
)

AudioSource = Union[str, os.PathLike, np.ndarray]


@dataclass
class Audio:
    """Mono float32 samples (nominally in [-1, 1]) at `sample_rate` Hz; `path` if read from a file."""

    samples: np.ndarray
    sample_rate: int
    path: str | None = None

    @property
    def duration(self) -> float:
        """Length in seconds."""
        return len(self.samples) / self.sample_rate

    @property
    def n_samples(self) -> int:
        return len(self.samples)

    def read(self, start: int, stop: int) -> "Audio":
        """Samples [start, stop) as an Audio (the interface `AudioFile` shares)."""
        return Audio(self.samples[start:stop], self.sample_rate, self.path)

    @property
    def name(self) -> str:
        """How error messages refer to this audio."""
        return f"'{self.path}'" if self.path is not None else "the audio array"


# --- reading -------------------------------------------------------------------


def load_audio(source: AudioSource, sample_rate: int | None = None) -> Audio:
    """Read and check speech from a file path or an array, mixed down to mono.

    For a file, `sample_rate` (optional) resamples the result to that rate.
    For an array, `sample_rate` is the array's own rate and is required; the array
    may be (N,), (N, C) or (C, N) (the shorter axis is taken as channels), float
    in [-1, 1] or integer PCM.
    Raises AudioError for anything that is not usable speech.
    """
    if isinstance(source, (str, os.PathLike)):
        audio = read_audio_file(source)
        check_audio(audio)
        if sample_rate is not None:
            rate = _check_rate(sample_rate, f"the sample_rate requested for {audio.name}",
                               "request a rate between 16000 and 48000 Hz, or None to keep the file's")
            audio = resample(audio, rate)
        return audio
    if isinstance(source, np.ndarray):
        if sample_rate is None:
            raise AudioError(
                "the audio array has no sample rate: pass sample_rate=<Hz> together with the array")
        rate = _check_rate(sample_rate, "the sample_rate given with the audio array",
                           "pass the rate the samples were recorded at")
        audio = Audio(_array_to_mono(source), rate)
        check_audio(audio)
        return audio
    raise AudioError(
        f"cannot read audio from a {type(source).__name__}: pass a file path or a numpy array "
        "(with sample_rate)")


@dataclass
class AudioFile:
    """A recording read piece by piece, never whole: long files in bounded memory.

    `read(start, stop)` gives samples [start, stop) mixed down to mono, as `Audio`.
    `open_audio_file` checks the file as `load_audio` checks an `Audio`."""

    path: str
    sample_rate: int
    n_samples: int
    notes: list[str] = field(default_factory=list)  # what is odd about the file (AudioWarning texts)

    @property
    def duration(self) -> float:
        return self.n_samples / self.sample_rate

    @property
    def name(self) -> str:
        return f"'{self.path}'"

    def read(self, start: int, stop: int) -> Audio:
        with sf.SoundFile(self.path) as fh:
            fh.seek(max(0, start))
            frames = fh.read(max(0, min(stop, self.n_samples) - max(0, start)), dtype="float32", always_2d=True)
        return Audio(_mixdown(frames), self.sample_rate, self.path)


PIECE_SECONDS = 60  # how much of a long recording is read, checked or featurised at once


def open_audio_file(path: str | os.PathLike) -> AudioFile | Audio:
    """A checked recording: an `AudioFile` read in pieces where libsndfile can seek in it,
    else (formats only audioread decodes) the whole `Audio`."""
    path = check_audio_path(path)
    try:
        info = sf.info(str(path))
    except sf.SoundFileError:
        audio = read_audio_file(path)
        check_audio(audio)
        return audio
    _check_channels(path, info.channels)
    recording = AudioFile(str(path), int(info.samplerate), 0)
    recording.n_samples = _check_pieces(recording)
    note = _warn_if_truncated(path, info, recording.n_samples)
    recording.notes += [note] if note else []
    return recording


def _check_pieces(recording: AudioFile) -> int:
    """Check `recording` piece by piece as `check_audio` checks an array; its true length."""
    step = PIECE_SECONDS * recording.sample_rate
    n, peak, finite = 0, 0.0, True
    with sf.SoundFile(recording.path) as fh:
        while True:
            frames = fh.read(step, dtype="float32", always_2d=True)
            if not len(frames):
                break
            mono = _mixdown(frames)
            n += len(mono)
            finite = finite and bool(np.isfinite(mono).all())
            if finite:
                peak = max(peak, float(np.abs(mono).max()))
    _check_summary(recording.name, recording.sample_rate, n, peak, finite)
    return n


def read_audio_file(path: str | os.PathLike) -> Audio:
    """Decode an audio file to mono float32 at its own rate (no checks on the content)."""
    path = check_audio_path(path)
    try:
        frames, rate = _decode_with_soundfile(path)
    except sf.SoundFileError as sf_error:
        frames, rate = _decode_with_audioread(path, sf_error)
    return Audio(_mixdown(frames), int(rate), str(path))


def check_audio_path(path: str | os.PathLike) -> Path:
    """`path` if it names a readable, non-empty regular file; else an AudioError saying why."""
    path = Path(path)
    resolve_path(path, "audio file", AudioError)  # a symbolic link loop, named as such
    if path.is_symlink() and not path.exists():
        raise AudioError(f"audio file '{path}' is a symbolic link to nothing (its target is missing): "
                         "point it at a real file")
    if not path.exists():
        raise AudioError(f"audio file '{path}' does not exist: check the path")
    if path.is_dir():
        raise AudioError(f"'{path}' is a folder, not an audio file: choose a WAV, FLAC, OGG or MP3 file")
    if not path.is_file():
        raise AudioError(f"'{path}' is not a regular file (a pipe, device or socket): save the audio "
                         "to a file first")
    if not os.access(path, os.R_OK):
        raise AudioError(f"audio file '{path}' cannot be read: check its permissions")
    if path.stat().st_size == 0:
        raise AudioError(f"audio file '{path}' is empty (0 bytes): record or export it again")
    return path


def probe_audio(path: str | os.PathLike) -> None:
    """Check, without decoding it, that `path` is a sound file this installation reads:
    libsndfile reads its header, or (other formats) audioread opens it; else an AudioError
    saying why. What a batch's check pass asks of every line's audio."""
    path = check_audio_path(path)
    try:
        info = sf.info(str(path))
    except sf.SoundFileError as sf_error:
        _read_with_audioread(path, sf_error, samples=False)
        return
    _check_channels(path, info.channels)
    _check_header_rate(path, info.samplerate)


def _not_audio(path: Path, sf_error: Exception) -> AudioError:
    return AudioError(
        f"'{path}' could not be decoded as audio ({sf_error}): it is not a sound file, or in a "
        "format this installation cannot read; convert it to WAV (e.g. `ffmpeg -i IN OUT.wav`)")


def _decode_with_soundfile(path: Path) -> tuple[np.ndarray, int]:
    """(N, C) float32 frames via libsndfile, which recognises WAV/FLAC/OGG/MP3 by content.
    A file shorter than its header says is read as far as it goes, with an AudioWarning."""
    info = sf.info(str(path))
    _check_channels(path, info.channels)
    frames, rate = sf.read(path, dtype="float32", always_2d=True)
    _warn_if_truncated(path, info, len(frames))
    return frames, rate


def _check_channels(path: Path, channels: int) -> None:
    """An AudioError unless the header of `path` declares 1 to MAX_CHANNELS channels (a damaged
    header can declare 0 or 65535: decoded as such, the samples are noise or do not fit)."""
    if not 1 <= channels <= MAX_CHANNELS:
        raise AudioError(f"'{path}' declares {channels} channels in its header (speech has 1 or 2, at most "
                         f"{MAX_CHANNELS} are mixed down): the header is damaged or it is not a speech "
                         "recording; save it as mono or stereo WAV")


def _warn_if_truncated(path: Path, info, n_frames: int) -> Optional[str]:
    """Warn (AudioWarning) of a WAV whose data chunk the file does not hold, which libsndfile
    notes in `info` (its sf.info) as `data : N (should be M)`; the warning's text, or None."""
    rate = info.samplerate
    found = re.search(r"^data\s*:\s*(\d+)\s*\(should be (\d+)\)", info.extra_info, re.M)
    if not (found and int(found.group(2)) < int(found.group(1))):
        return None
    promised = n_frames * int(found.group(1)) / max(int(found.group(2)), 1)
    note = (f"'{path}' is cut short: its header promises {promised / rate:.1f} s of audio, the file "
            f"holds {n_frames / rate:.1f} s; the motion covers what is there. Export the recording "
            "again if it should be longer")
    warnings.warn(AudioWarning(note), stacklevel=4)
    return note


def _decode_with_audioread(path: Path, sf_error: Exception) -> tuple[np.ndarray, int]:
    """(N, C) float32 frames via audioread (ffmpeg, GStreamer, ...) for what libsndfile cannot read."""
    rate, channels, pcm = _read_with_audioread(path, sf_error)
    frame = 2 * channels  # 16-bit samples; a partial last frame is dropped
    samples = np.frombuffer(pcm[: len(pcm) // frame * frame], dtype="<i2").astype(np.float32) / 32768.0
    return samples.reshape(-1, channels), rate


def _read_with_audioread(path: Path, sf_error: Exception, samples: bool = True) -> tuple[int, int, bytes]:
    """(sample rate, channels, 16-bit PCM: every sample, or none with `samples` False) of a
    file libsndfile refused (`sf_error`), through audioread; an AudioError naming a damaged
    WAV header, or saying the file cannot be decoded here."""
    not_audio = _not_audio(path, sf_error)
    _check_wav_header(path)  # what libsndfile refused may be a WAV with a damaged header
    try:
        import audioread
    except ImportError:
        raise not_audio from None
    try:
        with audioread.audio_open(str(path)) as decoder:
            rate, channels = decoder.samplerate, decoder.channels
            _check_channels(path, channels)
            pcm = b"".join(decoder) if samples else b""
    except AudioError:
        raise
    except Exception:  # whatever a decoder raises on a damaged file (DecodeError, audioop.error, EOFError, ...)
        raise not_audio from None
    return rate, channels, pcm


def _check_header_rate(path: Path, rate) -> None:
    _check_rate(rate, f"the sample rate of '{path}'", "its header is wrong or it is not speech; resample it to "
                "16000-48000 Hz")


def _check_wav_header(path: Path) -> None:
    """For a file libsndfile refused: an AudioError naming a header value no recording has
    (channels, sample rate, PCM sample width) if it is a RIFF/WAVE file, before another
    decoder reads its data with that header."""
    header = _wav_format(path)
    if header is None:
        return
    tag, channels, rate, bits = header
    _check_channels(path, channels)
    _check_header_rate(path, rate)
    if tag == 1 and not 1 <= bits <= 32:  # integer PCM (other codecs may declare 0)
        raise AudioError(f"'{path}' declares {bits} bits per sample in its header (PCM has 8, 16, 24 or 32): "
                         "the header is damaged; save it again as 16-bit WAV")


def _wav_format(path: Path) -> Optional[tuple[int, int, int, int]]:
    """(format tag, channels, sample rate, bits per sample) of the 'fmt ' chunk of a RIFF/WAVE
    (or RF64) file; None for other files, or where the header is cut short before them."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(12)
            if len(head) < 12 or head[:4] not in (b"RIFF", b"RF64") or head[8:] != b"WAVE":
                return None
            while len(chunk := fh.read(8)) == 8:
                size = int.from_bytes(chunk[4:], "little")
                if chunk[:4] == b"fmt ":
                    fmt = fh.read(16)
                    if len(fmt) < 16:
                        return None
                    tag, channels, rate, _, _, bits = struct.unpack("<HHIIHH", fmt)
                    return tag, channels, rate, bits
                fh.seek(size + (size & 1), os.SEEK_CUR)  # chunks are padded to an even size
    except OSError:
        return None
    return None


def _mixdown(frames: np.ndarray) -> np.ndarray:
    """(N, C) -> (N,) float32 by averaging the channels, as librosa.load does."""
    return np.ascontiguousarray(frames.mean(axis=1, dtype=np.float32))


def _array_to_mono(array: np.ndarray) -> np.ndarray:
    """(N,), (N, C) or (C, N) numeric array -> (N,) float32 in [-1, 1] for integer PCM."""
    if array.size == 0:  # before any axis is taken for channels or any mean is computed
        raise AudioError(f"the audio array has shape {array.shape}: it contains no audio samples; "
                         "pass the recorded speech")
    if array.ndim not in (1, 2):
        raise AudioError(
            f"the audio array has shape {array.shape}: expected (samples,), (samples, channels) "
            "or (channels, samples)")
    if array.ndim == 2:
        channels_axis = 0 if array.shape[0] < array.shape[1] else 1
        if array.shape[channels_axis] > MAX_CHANNELS:
            raise AudioError(
                f"the audio array has shape {array.shape}: neither axis looks like channels "
                f"(at most {MAX_CHANNELS}); pass (samples,) or (samples, channels)")
        array = array if channels_axis == 1 else array.T
    else:
        array = array[:, None]
    return _mixdown(_to_float(array))


def _to_float(array: np.ndarray) -> np.ndarray:
    """Float32 samples; integer PCM is scaled by its full range."""
    if np.issubdtype(array.dtype, np.floating):
        return array.astype(np.float32, copy=False)
    if np.issubdtype(array.dtype, np.signedinteger):
        return array.astype(np.float32) / float(-np.iinfo(array.dtype).min)
    if np.issubdtype(array.dtype, np.unsignedinteger):
        mid = float(np.iinfo(array.dtype).max // 2 + 1)
        return (array.astype(np.float32) - mid) / mid
    raise AudioError(
        f"the audio array has dtype {array.dtype}: pass float samples in [-1, 1] or integer PCM")


def _check_rate(sample_rate: Any, subject: str, fix: str) -> int:
    """A whole number of Hz within [MIN_SAMPLE_RATE, MAX_SAMPLE_RATE]; `subject` and `fix` word the error."""
    if isinstance(sample_rate, bool) or not isinstance(sample_rate, (int, float, np.number)) \
            or not float(sample_rate).is_integer():
        raise AudioError(f"{subject} ({sample_rate!r}) is not a whole number of Hz: {fix}")
    rate = int(sample_rate)
    if not MIN_SAMPLE_RATE <= rate <= MAX_SAMPLE_RATE:
        raise AudioError(
            f"{subject} ({rate} Hz) is outside {MIN_SAMPLE_RATE}-{MAX_SAMPLE_RATE} Hz: {fix}")
    return rate


def check_audio(audio: Audio) -> None:
    """Raise AudioError unless `audio` is finite, audible mono speech of at least one motion frame."""
    finite = bool(np.isfinite(audio.samples).all())
    peak = float(np.abs(audio.samples).max()) if finite and len(audio.samples) else 0.0
    _check_summary(audio.name, audio.sample_rate, len(audio.samples), peak, finite)


def _check_summary(name: str, sample_rate: int, n: int, peak: float, finite: bool) -> None:
    """The checks of `check_audio`, on what they need: rate, length, finiteness, peak."""
    _check_rate(sample_rate, f"the sample rate of {name}",
                "its header is wrong or it is not speech; resample it to 16000-48000 Hz")
    if n == 0:
        raise AudioError(f"{name} contains no audio samples: record or export it again")
    if n < sample_rate * MIN_DURATION_S:
        raise AudioError(
            f"{name} is only {n / sample_rate * 1000:.1f} ms long: at least "
            f"{MIN_DURATION_S * 1000:.1f} ms (one motion frame) of speech is needed")
    if not finite:
        raise AudioError(
            f"{name} contains NaN or infinite samples: the file or array is corrupt; "
            "export the audio again")
    if peak < SILENCE_PEAK:
        raise AudioError(
            f"{name} is silent (peak level {peak:.1e}, below {SILENCE_PEAK:.0e}): "
            "use a recording with audible speech")
    if peak > MAX_FLOAT_PEAK:
        raise AudioError(
            f"{name} has samples up to {peak:.0f}, but float audio must lie in [-1, 1]: "
            "it looks like unscaled integer PCM; divide 16-bit samples by 32768")


# --- resampling ----------------------------------------------------------------


def resample(audio: Audio, sample_rate: int) -> Audio:
    """`audio` at `sample_rate` Hz with librosa's default resampler (soxr HQ).

    The length is ceil(N * new / old), as `librosa.load(path, sr=...)` gives: soxr's
    output is cut or padded with zeros to it, as librosa.resample does.
    """
    if sample_rate == audio.sample_rate:
        return audio
    samples = np.asarray(audio.samples)
    if samples.dtype != np.float64:  # soxr works in the input's precision, like librosa
        samples = samples.astype(np.float32, copy=False)
    resampled = soxr.resample(np.ascontiguousarray(samples), audio.sample_rate, sample_rate,
                              quality=SOXR_QUALITY)
    n = resampled_length(len(samples), audio.sample_rate, sample_rate)
    if len(resampled) >= n:
        resampled = resampled[:n]
    else:
        resampled = np.concatenate([resampled, np.zeros(n - len(resampled), resampled.dtype)])
    return Audio(resampled.astype(np.float32, copy=False), int(sample_rate), audio.path)


def resampled_length(n: int, orig_sr: int, target_sr: int) -> int:
    """Sample count `resample` produces, computed exactly as librosa does."""
    if orig_sr == target_sr:
        return n
    return int(np.ceil(n * (float(target_sr) / orig_sr)))


# --- mel features --------------------------------------------------------------


def mel_filter_key(n_fft: int, n_mels: int) -> str:
    """Name of the stored filterbank for (n_fft, n_mels) at MEL_RATE in MEL_FILTERS."""
    return f"sr{MEL_RATE}_nfft{n_fft}_mels{n_mels}"


@functools.lru_cache(maxsize=None)
def _stored_mel_filters() -> dict[str, np.ndarray]:
    """All filterbanks in MEL_FILTERS, read once."""
    if not MEL_FILTERS.is_file():
        raise DiffshegError(
            f"the mel filterbank file '{MEL_FILTERS}' is missing: this installation is "
            f"incomplete; reinstall it, or make the file with `python {MEL_FILTERS_TOOL}`")
    with np.load(MEL_FILTERS, allow_pickle=False) as stored:
        return {key: stored[key] for key in stored.files}


@functools.lru_cache(maxsize=None)
def _mel_filters(n_fft: int, n_mels: int) -> np.ndarray:
    """(1 + n_fft // 2, n_mels) float64 filterbank, transposed for `power @ filters`."""
    key = mel_filter_key(n_fft, n_mels)
    banks = _stored_mel_filters()
    if key not in banks:
        stored = ", ".join(sorted(banks)) or "none"
        raise DiffshegError(
            f"no mel filterbank is stored for n_fft={n_fft}, n_mels={n_mels} at {MEL_RATE} Hz "
            f"(stored: {stored}): add ({n_fft}, {n_mels}) to the banks of {MEL_FILTERS_TOOL} "
            f"and run `python {MEL_FILTERS_TOOL}`")
    bank = banks[key]
    if bank.shape != (n_mels, 1 + n_fft // 2):
        raise DiffshegError(
            f"the stored mel filterbank {key} has shape {bank.shape}, not "
            f"{(n_mels, 1 + n_fft // 2)}: make '{MEL_FILTERS}' again with `python {MEL_FILTERS_TOOL}`")
    return np.ascontiguousarray(bank.T, dtype=np.float64)


def _periodic_hann(n: int) -> np.ndarray:
    """Periodic ("DFT-even") Hann window of length n: 0.5 - 0.5 cos(2 pi k / n), k < n."""
    return 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(n) / n)


def mel_spectrogram(samples: np.ndarray, n_fft: int, hop: int, n_mels: int) -> np.ndarray:
    """(n_mels, frames) float32 power mel spectrogram of mono `samples` at MEL_RATE (18 kHz).

    The same as librosa 0.11's `librosa.feature.melspectrogram(y=samples, sr=18000,
    n_fft=n_fft, hop_length=hop, n_mels=n_mels)`: frame j is centred on sample j * hop
    (the signal padded with n_fft // 2 zeros at both ends), periodic Hann window of
    n_fft samples, |rfft|^2, then the stored Slaney mel filterbank (see MEL_FILTERS).
    There are 1 + (N + 2 * (n_fft // 2) - n_fft) // hop frames (1 + N // hop for an even
    n_fft). Computed in float64, in chunks of about MEL_CHUNK framed samples.
    """
    for name, value in (("n_fft", n_fft), ("hop", hop), ("n_mels", n_mels)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise DiffshegError(f"mel_spectrogram: {name} must be a positive whole number, got {value!r}")
    x = np.asarray(samples)
    if x.ndim != 1:
        raise AudioError(f"mel_spectrogram needs mono samples of shape (N,), got shape {x.shape}")
    n_fft, hop = int(n_fft), int(hop)
    pad = n_fft // 2
    n_frames = 1 + (len(x) + 2 * pad - n_fft) // hop if len(x) + 2 * pad >= n_fft else 0
    if n_frames < 1:
        raise AudioError(f"mel_spectrogram: {len(x)} samples are too few for one frame of {n_fft}")
    filters = _mel_filters(n_fft, int(n_mels))
    window = _periodic_hann(n_fft)
    mel = np.empty((int(n_mels), n_frames), dtype=np.float32)
    step = max(1, MEL_CHUNK // n_fft)
    for first in range(0, n_frames, step):
        last = min(first + step, n_frames)
        # The padded signal's samples [first * hop, (last - 1) * hop + n_fft), zeros outside x.
        start, stop = first * hop - pad, (last - 1) * hop + n_fft - pad
        segment = np.zeros(stop - start, dtype=np.float64)
        lo, hi = max(start, 0), min(stop, len(x))
        if hi > lo:
            segment[lo - start:hi - start] = x[lo:hi]
        frames = np.lib.stride_tricks.sliding_window_view(segment, n_fft)[::hop]
        spectrum = np.fft.rfft(frames * window, axis=-1)
        power = spectrum.real ** 2 + spectrum.imag ** 2
        mel[:, first:last] = (power @ filters).T
    return mel


def mel_hop(fps: float) -> int:
    """Mel hop in samples at 18 kHz for `fps` motion frames per second (1200 at 15 fps)."""
    hop = MEL_RATE / fps if fps > 0 else math.nan
    if not (math.isfinite(hop) and hop.is_integer() and hop >= 1):
        raise AudioError(
            f"motion rate {fps!r} fps gives no whole mel hop at {MEL_RATE} Hz: use a frame rate "
            f"that divides {MEL_RATE}, e.g. 15 (the BEAT model), 24, 25, 30 or 60")
    return int(hop)


def mel_features(audio: Audio, fps: float = 15.0) -> np.ndarray:
    """(T, 128) float32 mel power spectrogram, one frame per motion frame (official DiffSHEG).

    The audio goes to 22050 Hz (as librosa.load does), then 18000 Hz; the
    spectrogram uses n_fft 2048, hop 18000 / fps, hann window, centred frames, power
    (no log, no normalisation); the last frame, centred past the end, is dropped.
    """
    return mel_frames(audio, fps)[: n_motion_frames(audio, fps)]


def mel_frames(audio: Audio, fps: float = 15.0) -> np.ndarray:
    """(T + 1, 128): `mel_features` with the last frame kept (frame j centred at j / fps s),
    for computing the features of a long recording piece by piece."""
    speech = resample(resample(audio, LOAD_RATE), MEL_RATE)
    return np.ascontiguousarray(mel_spectrogram(speech.samples, MEL_N_FFT, mel_hop(fps), MEL_N_MELS).T,
                                dtype=np.float32)


def n_motion_frames(audio, fps: float = 15.0) -> int:
    """Number of motion frames for `audio` (an Audio or AudioFile) at `fps`; equals
    len(mel_features(audio, fps))."""
    return _frames_of(audio.n_samples, audio.sample_rate, fps)


def _frames_of(n_samples: int, sample_rate: int, fps: float) -> int:
    return _mel_samples(n_samples, sample_rate) // mel_hop(fps)


def _mel_samples(n_samples: int, sample_rate: int) -> int:
    """Samples at MEL_RATE that `n_samples` at `sample_rate` become (through LOAD_RATE, as `mel_frames`)."""
    return resampled_length(resampled_length(n_samples, sample_rate, LOAD_RATE), LOAD_RATE, MEL_RATE)


def samples_for_mel_frame(frame: int, sample_rate: int, fps: float = 15.0) -> int:
    """The fewest samples at `sample_rate` that reach the end of mel frame `frame`'s window:
    MEL_N_FFT // 2 samples at MEL_RATE past its centre at frame / fps (57 ms; at 15 fps short of
    the next frame's start, 67 ms). The resampler's own reach past that is left out: the frame's
    Hann window is near zero there."""
    need = frame * mel_hop(fps) + MEL_N_FFT // 2
    n = int(need * sample_rate // MEL_RATE)
    while n > 0 and _mel_samples(n - 1, sample_rate) >= need:
        n -= 1
    while _mel_samples(n, sample_rate) < need:
        n += 1
    return n


# --- the second speech input ---------------------------------------------------


@dataclass(frozen=True)
class SpeechEncoding:
    """A model's second speech input beside the mel (HuBERT, or the phonetic encoder):
    `encode(audio, n_frames)` gives (n_frames, dim) float32; `key` names the encoder and
    its settings, so cached features are recomputed when either changes."""

    key: str
    encode: Callable[[Audio, int], np.ndarray]


# --- HuBERT features (optional) ------------------------------------------------


def hubert_status(model_path: str | os.PathLike | None = None) -> str | None:
    """None when HuBERT features can be computed, else a one-line reason why not."""
    if importlib.util.find_spec("transformers") is None:
        return "the Python package 'transformers' is not installed"
    folder = Path(model_path) if model_path is not None else cached_hubert_folder()
    if folder is None:
        return f"{HUBERT_REPO_ID} is not in the Hugging Face cache"
    if not folder.is_dir():
        return f"HuBERT model folder '{folder}' does not exist"
    if not (folder / "config.json").is_file():
        return f"HuBERT model folder '{folder}' has no config.json"
    if not any((folder / name).is_file() for name in HUBERT_WEIGHT_FILES):
        return f"HuBERT model folder '{folder}' has no {' or '.join(HUBERT_WEIGHT_FILES)}"
    return None


def require_hubert(model_path: str | os.PathLike | None = None) -> None:
    """Raise AudioError saying what to install when HuBERT features cannot be computed
    (before `torch_layer.hubert.load_hubert` imports torch)."""
    reason = hubert_status(model_path)
    if reason is not None:
        raise AudioError(f"HuBERT features are unavailable: {reason}. {HUBERT_HOW_TO}")


def cached_hubert_folder() -> Path | None:
    """The cached snapshot folder of HUBERT_REPO_ID, without touching the network."""
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:
        return None
    config = try_to_load_from_cache(HUBERT_REPO_ID, "config.json")
    return Path(config).parent if isinstance(config, str) else None
