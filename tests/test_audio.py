"""Audio front end on real speech: loading, checks, resampling, mel and HuBERT features."""

from __future__ import annotations

import importlib.util
import math
import struct
import subprocess
import sys
import warnings
from pathlib import Path

import librosa
import numpy as np
import pytest
import soundfile as sf

from system_tools import require_program

from diffsheg_core.audio import (
    HUBERT_REPO_ID, MEL_FILTERS, SAMPLE_SPEECH, Audio, resampled_length,
    hubert_status, load_audio, mel_features, mel_filter_key, mel_spectrogram, n_motion_frames,
    open_audio_file, resample,
)
from diffsheg_core.errors import AudioError, DiffshegError
from diffsheg_core.torch_layer.hubert import hubert_features

ROOT = Path(__file__).resolve().parents[1]
AUDIO = ROOT.parent / "shared" / "data" / "audio"
SCOTT_24BIT = AUDIO / "2_scott_0_3_3.wav"  # 68.0 s, 16 kHz, 24-bit PCM
MP3_AS_WAV = AUDIO / "2_scott_0_103_103_28s.wav"  # MP3 data (44.1 kHz stereo) named .wav
ZHAO = AUDIO / "12_zhao_2_3_3.wav"  # 56 s, 16 kHz, 16-bit
BEAT2_FLOAT = ROOT.parent / "shared" / "data" / "beat2" / "2_scott_0_1_1.wav"  # 32-bit float
FORREST = AUDIO / "Forrest_tts.wav"  # 118.6 s synthetic speech, 16 kHz

# The filterbanks stored in assets/mel_filters.npz: (n_fft, n_mels, the hop they are used with).
MEL_BANKS = {"official_2048x128": (2048, 128, 1200), "phonetic_512x64": (512, 64, 300)}

HAS_TRANSFORMERS = importlib.util.find_spec("transformers") is not None


def official_mel(path: Path) -> np.ndarray:
    """The official DiffSHEG front end, written as its inference code calls librosa."""
    y, sr = librosa.load(path, sr=22050)
    y = librosa.resample(y, orig_sr=sr, target_sr=18000)
    return librosa.feature.melspectrogram(y=y, sr=18000, hop_length=1200, n_mels=128)[..., :-1].T


@pytest.fixture(scope="module")
def zhao_clip() -> tuple[np.ndarray, int]:
    """Four seconds of real speech (float32, 16 kHz) for making format variants."""
    samples, rate = sf.read(ZHAO, dtype="float32", frames=4 * 16000, start=8 * 16000)
    return samples, rate


# --- loading ---------------------------------------------------------------------


def test_loads_24bit_mono_wav_at_its_own_rate():
    audio = load_audio(SCOTT_24BIT)
    assert audio.sample_rate == 16000
    assert audio.samples.dtype == np.float32 and audio.samples.ndim == 1
    assert len(audio.samples) == 1088000 and audio.duration == pytest.approx(68.0)
    assert audio.path == str(SCOTT_24BIT)
    assert 0.05 < np.abs(audio.samples).max() <= 1.0


def test_mp3_data_in_a_wav_named_file_decodes_by_content():
    audio = load_audio(MP3_AS_WAV)
    assert audio.sample_rate == 44100
    assert audio.duration == pytest.approx(28.7, abs=0.05)
    assert 0.01 < float(np.sqrt(np.mean(audio.samples ** 2))) < 0.5  # real speech level


@pytest.mark.parametrize("fmt, subtype", [("WAV", "PCM_16"), ("FLAC", "PCM_24"), ("OGG", "VORBIS")])
def test_stereo_files_are_mixed_down_by_averaging(tmp_path, zhao_clip, fmt, subtype):
    mono, rate = zhao_clip
    stereo = np.stack([mono, 0.25 * mono], axis=1)
    path = tmp_path / f"stereo.{fmt.lower()}"
    sf.write(path, stereo, rate, format=fmt, subtype=subtype)
    audio = load_audio(path)
    assert audio.sample_rate == rate
    expected = 0.625 * mono
    if fmt == "OGG":  # lossy: same length (within a frame) and the same waveform shape
        assert abs(len(audio.samples) - len(mono)) <= 2048
        n = min(len(audio.samples), len(mono))
        assert np.corrcoef(audio.samples[:n], expected[:n])[0, 1] > 0.95
    else:
        np.testing.assert_allclose(audio.samples, expected, atol=2e-4)


def test_other_sample_rates_load_and_resample_like_librosa_load(tmp_path, zhao_clip):
    mono, rate = zhao_clip
    path = tmp_path / "speech_44k.wav"
    sf.write(path, librosa.resample(mono, orig_sr=rate, target_sr=44100), 44100, subtype="FLOAT")
    native = load_audio(path)
    assert native.sample_rate == 44100 and native.duration == pytest.approx(4.0, abs=1e-3)
    at_22k = load_audio(path, sample_rate=22050)
    reference, _ = librosa.load(path, sr=22050)
    assert at_22k.sample_rate == 22050
    np.testing.assert_array_equal(at_22k.samples, reference)
    assert resample(native, 22050).samples.shape == reference.shape
    with pytest.raises(AudioError, match="sample_rate requested for '.*speech_44k.wav' .*outside"):
        load_audio(path, sample_rate=1000)


def test_arrays_of_any_layout_and_dtype_give_the_same_mono(zhao_clip):
    mono, rate = zhao_clip
    reference = load_audio(mono, sample_rate=rate).samples
    np.testing.assert_array_equal(reference, mono)
    np.testing.assert_array_equal(load_audio(np.stack([mono, mono], 1), rate).samples, mono)
    np.testing.assert_array_equal(load_audio(np.stack([mono, mono], 0), rate).samples, mono)
    pcm16 = np.round(mono * 32767).astype(np.int16)
    np.testing.assert_allclose(load_audio(pcm16, rate).samples, mono, atol=1e-4)
    audio = load_audio(mono.astype(np.float64), sample_rate=16000.0)
    assert audio.samples.dtype == np.float32 and audio.path is None


def test_formats_libsndfile_cannot_read_fall_back_to_audioread(tmp_path, zhao_clip):
    require_program("ffmpeg", "ffmpeg")
    mono, rate = zhao_clip
    wav, m4a = tmp_path / "speech.wav", tmp_path / "speech.m4a"
    sf.write(wav, mono, rate)
    subprocess.run(["ffmpeg", "-v", "error", "-i", str(wav), "-c:a", "aac", str(m4a)], check=True)
    with pytest.raises(sf.SoundFileError):
        sf.info(m4a)
    audio = load_audio(m4a)
    assert audio.sample_rate == rate and audio.duration == pytest.approx(4.0, abs=0.1)


# --- resampling ------------------------------------------------------------------


@pytest.mark.parametrize("path, rate", [(SCOTT_24BIT, 22050), (SCOTT_24BIT, 18000), (ZHAO, 48000),
                                        (MP3_AS_WAV, 22050), (MP3_AS_WAV, 16000)],
                         ids=["16k_to_22050", "16k_to_18000", "16k_to_48000", "44k1_to_22050", "44k1_to_16000"])
def test_resample_equals_librosa_soxr_hq(path, rate):
    audio = load_audio(path)
    ours = resample(audio, rate)
    reference = librosa.resample(audio.samples, orig_sr=audio.sample_rate, target_sr=rate, res_type="soxr_hq")
    assert ours.sample_rate == rate and ours.path == audio.path and ours.samples.dtype == np.float32
    assert len(ours.samples) == resampled_length(len(audio.samples), audio.sample_rate, rate)
    assert len(ours.samples) == math.ceil(len(audio.samples) * rate / audio.sample_rate)
    np.testing.assert_array_equal(ours.samples, reference)
    at_22k = resample(audio, 22050)  # the official chain 22050 -> 18000, as mel_features runs it
    np.testing.assert_array_equal(
        resample(at_22k, 18000).samples,
        librosa.resample(at_22k.samples, orig_sr=22050, target_sr=18000, res_type="soxr_hq"))


def test_resample_keeps_float64_precision_like_librosa(zhao_clip):
    mono, rate = zhao_clip
    audio = Audio(mono.astype(np.float64), rate)
    reference = librosa.resample(audio.samples, orig_sr=rate, target_sr=22050, res_type="soxr_hq")
    ours = resample(audio, 22050).samples
    assert ours.dtype == np.float32
    np.testing.assert_array_equal(ours, reference.astype(np.float32))
    assert resample(audio, rate) is audio


# --- mel features ----------------------------------------------------------------


@pytest.mark.parametrize("bank", list(MEL_BANKS))
def test_stored_filterbanks_equal_librosa(bank):
    n_fft, n_mels, _ = MEL_BANKS[bank]
    with np.load(MEL_FILTERS, allow_pickle=False) as stored:
        assert set(stored.files) == {mel_filter_key(n, m) for n, m, _ in MEL_BANKS.values()}
        filters = stored[mel_filter_key(n_fft, n_mels)]
    assert mel_filter_key(n_fft, n_mels) == f"sr18000_nfft{n_fft}_mels{n_mels}"
    assert filters.dtype == np.float32 and filters.shape == (n_mels, 1 + n_fft // 2)
    # equal to float32 rounding: librosa 0.11 leaves 3.7e-17 at one triangle's foot where the stored bank has 0
    np.testing.assert_allclose(filters, librosa.filters.mel(sr=18000, n_fft=n_fft, n_mels=n_mels),
                               rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("path", [SCOTT_24BIT, ZHAO, FORREST], ids=lambda p: p.stem)
@pytest.mark.parametrize("bank", list(MEL_BANKS))
def test_mel_spectrogram_equals_librosa_melspectrogram(path, bank):
    n_fft, n_mels, hop = MEL_BANKS[bank]
    speech = resample(load_audio(path), 18000).samples
    for samples, hop in ((speech, hop), (speech[: 18000 * 5 + 777], hop + 7)):  # odd hop and length
        mel = mel_spectrogram(samples, n_fft, hop, n_mels)
        reference = librosa.feature.melspectrogram(
            y=samples, sr=18000, n_fft=n_fft, hop_length=hop, n_mels=n_mels)
        assert mel.dtype == np.float32 and mel.shape == reference.shape == (n_mels, 1 + len(samples) // hop)
        # librosa rounds the spectrum to float32; ours is float64 until the end. Measured: 2e-7.
        assert np.abs(mel - reference).max() <= 1e-6 * reference.max()
        np.testing.assert_allclose(mel, reference, rtol=2e-6, atol=1e-7 * reference.max())


@pytest.mark.filterwarnings("ignore:n_fft=2048 is too large:UserWarning")
def test_mel_spectrogram_of_audio_shorter_than_the_window_is_zero_padded(zhao_clip):
    samples = resample(load_audio(zhao_clip[0], zhao_clip[1]), 18000).samples[:1200]
    mel = mel_spectrogram(samples, 2048, 1200, 128)
    reference = librosa.feature.melspectrogram(y=samples, sr=18000, n_fft=2048, hop_length=1200, n_mels=128)
    assert mel.shape == reference.shape == (128, 2)
    assert np.abs(mel - reference).max() <= 1e-6 * reference.max()


def test_mel_spectrogram_without_a_stored_bank_names_it_and_the_tool():
    samples = resample(load_audio(SAMPLE_SPEECH), 18000).samples
    with pytest.raises(DiffshegError) as error:
        mel_spectrogram(samples, 1024, 300, 80)
    message = str(error.value)
    assert "n_fft=1024, n_mels=80" in message and "tools/make_mel_filters.py" in message
    with pytest.raises(DiffshegError, match="hop must be a positive"):
        mel_spectrogram(samples, 2048, 0, 128)
    with pytest.raises(AudioError, match="mono"):
        mel_spectrogram(np.stack([samples, samples]), 2048, 1200, 128)



@pytest.mark.parametrize("path", [SCOTT_24BIT, MP3_AS_WAV], ids=["16k_24bit", "mp3_44k_stereo"])
def test_mel_equals_the_official_librosa_path(path):
    mel = mel_features(load_audio(path))
    reference = official_mel(path)
    assert mel.dtype == np.float32 and mel.shape == reference.shape
    assert np.abs(mel - reference).max() <= 1e-6 * reference.max()


@pytest.mark.parametrize("path", [SCOTT_24BIT, MP3_AS_WAV, ZHAO, BEAT2_FLOAT, SAMPLE_SPEECH],
                         ids=lambda p: p.name)
def test_one_mel_frame_per_fifteenth_of_a_second(path):
    audio = load_audio(path)
    n = n_motion_frames(audio)
    assert n == math.floor(audio.duration * 15)
    assert len(mel_features(audio)) == n
    assert mel_features(audio).shape == (n, 128)


def test_mel_is_power_not_log():
    audio = load_audio(SAMPLE_SPEECH)
    mel = mel_features(audio)
    assert mel.min() >= 0.0
    assert mel.max() / np.median(mel) > 1e4  # a log spectrogram has a range of a few tens
    half = Audio(audio.samples * 0.5, audio.sample_rate, None)
    np.testing.assert_allclose(mel_features(half), 0.25 * mel, rtol=1e-4, atol=1e-7 * mel.max())


def test_other_motion_rates_use_a_whole_hop():
    audio = load_audio(SAMPLE_SPEECH)
    for fps in (24, 25, 30, 60):
        assert len(mel_features(audio, fps)) == n_motion_frames(audio, fps) == math.floor(audio.duration * fps)
    for fps in (29.97, 0, -15, 7):
        with pytest.raises(AudioError, match="divides 18000"):
            n_motion_frames(audio, fps)


def test_shortest_usable_audio_gives_one_frame(zhao_clip):
    mono, rate = zhao_clip
    shortest = load_audio(mono[: math.ceil(rate / 15)], rate)
    assert n_motion_frames(shortest) == len(mel_features(shortest)) == 1
    with pytest.raises(AudioError, match="ms long"):
        load_audio(mono[: math.ceil(rate / 15) - 1], rate)


# --- bad input -------------------------------------------------------------------


def _write(path: Path, samples, rate: int = 16000, subtype: str = "PCM_16") -> Path:
    sf.write(path, np.asarray(samples, dtype=np.float32), rate, subtype=subtype)
    return path


def _text_as_wav(tmp: Path) -> Path:
    path = tmp / "notes.wav"
    path.write_text("this is a text file, not a recording\n")
    return path


def _empty_file(tmp: Path) -> Path:
    path = tmp / "empty.wav"
    path.touch()
    return path


def _speech(n: int) -> np.ndarray:
    return sf.read(ZHAO, dtype="float32", frames=n, start=8 * 16000)[0]


BAD_FILES = {
    "missing": (lambda tmp: tmp / "nowhere.wav", "does not exist"),
    "directory": (lambda tmp: tmp, "is a folder"),
    "text_renamed_wav": (_text_as_wav, "could not be decoded as audio"),
    "zero_bytes": (_empty_file, "is empty"),
    "zero_samples": (lambda tmp: _write(tmp / "none.wav", np.zeros(0)), "no audio samples"),
    "too_short": (lambda tmp: _write(tmp / "short.wav", _speech(800)), "ms long"),
    "silent": (lambda tmp: _write(tmp / "silence.wav", np.zeros(32000)), "is silent"),
    "nan": (lambda tmp: _write(tmp / "nan.wav", np.where(np.arange(16000) == 5, np.nan, _speech(16000)),
                               subtype="FLOAT"), "NaN or infinite"),
    "rate_too_low": (lambda tmp: _write(tmp / "slow.wav", _speech(16000), rate=2000), "outside 4000-384000"),
    "unscaled_pcm": (lambda tmp: _write(tmp / "loud.wav", _speech(16000) * 32768, subtype="FLOAT"),
                     "unscaled integer PCM"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_files_raise_audio_error_naming_file_and_problem(tmp_path, case):
    make, problem = BAD_FILES[case]
    path = make(tmp_path)
    with pytest.raises(AudioError) as error:
        load_audio(path)
    assert str(path) in str(error.value)
    assert problem in str(error.value)


def _damaged_header(tmp: Path, offset: int, fmt: str, value: int) -> Path:
    """Four seconds of real speech (ZHAO) as 16-bit mono WAV (a 44-byte header), whose 'fmt '
    field at `offset` is overwritten with `value`: 22 channels, 24 sample rate, 32 block
    align, 34 bits per sample."""
    path = _write(tmp / f"damaged_{offset}_{value}.wav", _speech(4 * 16000))
    data = bytearray(path.read_bytes())
    assert data[12:16] == b"fmt " and data[36:40] == b"data"
    struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))
    return path


CHANNELS_FIX, RATE_FIX, BITS_FIX = ("save it as mono or stereo WAV", "resample it to 16000-48000 Hz",
                                   "save it again as 16-bit WAV")
DAMAGED_HEADERS = {  # case: (offset, struct format, value, what the message says, the fix it gives)
    "65535_channels": (22, "<H", 65535, "declares 65535 channels", CHANNELS_FIX),
    "0_channels": (22, "<H", 0, "declares 0 channels", CHANNELS_FIX),
    "17_channels": (22, "<H", 17, "declares 17 channels", CHANNELS_FIX),
    "rate_0": (24, "<I", 0, "(0 Hz) is outside 4000-384000", RATE_FIX),
    "rate_4294967295": (24, "<I", 0xFFFFFFFF, "(4294967295 Hz) is outside 4000-384000", RATE_FIX),
    "0_bits": (34, "<H", 0, "declares 0 bits per sample", BITS_FIX),
    "64_bits": (34, "<H", 64, "declares 64 bits per sample", BITS_FIX),
    "65535_bits": (34, "<H", 65535, "declares 65535 bits per sample", BITS_FIX),
}


@pytest.mark.parametrize("audioread", ["installed", "absent"])
@pytest.mark.parametrize("case", list(DAMAGED_HEADERS))
def test_a_wav_header_no_recording_has_is_named_with_the_fix(tmp_path, monkeypatch, case, audioread):
    """Issue 43 (b): a header declaring 65535 channels reached audioread's fallback, whose
    samples did not fit (`ValueError: cannot reshape`); 0 channels, an absurd rate or sample
    width likewise. Each is an AudioError naming the value and the fix, for a whole file
    (load_audio) and a recording read in pieces (open_audio_file, which live file sources
    use), with or without audioread."""
    offset, fmt, value, problem, fix = DAMAGED_HEADERS[case]
    path = _damaged_header(tmp_path, offset, fmt, value)
    if audioread == "absent":
        monkeypatch.setitem(sys.modules, "audioread", None)  # `import audioread` raises ImportError
    for read in (load_audio, open_audio_file):
        with pytest.raises(AudioError) as error:
            read(path)
        message = str(error.value)
        assert str(path) in message and problem in message and fix in message, message


def test_a_wrong_block_align_or_byte_rate_is_read_as_the_samples_say(tmp_path):
    """The block align and byte rate of a 'fmt ' chunk are redundant: a wrong one does not
    change the samples."""
    speech = load_audio(_write(tmp_path / "speech.wav", _speech(4 * 16000))).samples
    for offset, fmt, value in ((32, "<H", 0), (32, "<H", 7), (32, "<H", 65535), (28, "<I", 0)):
        np.testing.assert_array_equal(load_audio(_damaged_header(tmp_path, offset, fmt, value)).samples, speech)


def test_a_channel_count_only_the_fallback_decoder_reads_is_named_too(tmp_path):
    """A Sun/NeXT .au header declaring 65535 channels: libsndfile refuses it, audioread's own
    reader opens it and reported the 65535 channels that did not fit the samples."""
    audioread = pytest.importorskip("audioread")
    path = tmp_path / "speech.au"
    sf.write(path, _speech(4 * 16000), 16000, format="AU", subtype="PCM_16")
    data = bytearray(path.read_bytes())
    assert data[:4] == b".snd" and struct.unpack_from(">I", data, 20) == (1,)
    struct.pack_into(">I", data, 20, 65535)  # the channel count of the .au header
    path.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # audioread's aifc, audioop, sunau on 3.11
        with audioread.audio_open(str(path)) as decoder:
            assert decoder.channels == 65535
        for read in (load_audio, open_audio_file):
            with pytest.raises(AudioError) as error:
                read(path)
            message = str(error.value)
            assert f"'{path}' declares 65535 channels in its header" in message and CHANNELS_FIX in message, message


BAD_ARRAYS = {
    "no_rate": (lambda: (_speech(16000), None), "no sample rate"),
    "rate_too_high": (lambda: (_speech(16000), 500000), "outside 4000-384000"),
    "fractional_rate": (lambda: (_speech(16000), 16000.5), "not a whole number"),
    "three_dims": (lambda: (_speech(16000).reshape(2, 100, 80), 16000), "expected (samples,)"),
    "no_channel_axis": (lambda: (_speech(40000).reshape(200, 200), 16000), "neither axis"),
    "infinite": (lambda: (np.where(np.arange(16000) == 9, np.inf, _speech(16000)), 16000), "NaN or infinite"),
    "silent": (lambda: (np.full(16000, 1e-6, np.float32), 16000), "is silent"),
    "complex": (lambda: (_speech(16000).astype(np.complex64), 16000), "dtype complex64"),
    "list": (lambda: (_speech(16000).tolist(), 16000), "cannot read audio from a list"),
}


@pytest.mark.parametrize("case", list(BAD_ARRAYS))
def test_bad_arrays_raise_audio_error_naming_the_problem(case):
    make, problem = BAD_ARRAYS[case]
    source, rate = make()
    with pytest.raises(AudioError, match="array|list") as error:
        load_audio(source, rate)
    assert problem in str(error.value)


@pytest.mark.parametrize("shape", [(0,), (0, 2), (2, 0), (0, 0)])
def test_an_empty_array_is_refused_before_anything_is_computed(shape):
    """(0, 2) was taken for 2 samples of no channels: numpy warned of an empty mean, then
    the message spoke of 0.1 ms of audio."""
    import diffsheg_core

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(AudioError, match=rf"shape \({shape[0]},.*contains no audio samples; pass the"):
            diffsheg_core.generate(np.zeros(shape, np.float32), 16000)


# --- HuBERT ----------------------------------------------------------------------


NOT_IN_BLENDER = ("librosa", "scipy", "numba")

# Blocks the packages Blender lacks (or, unblocked, leaves them importable), imports the audio
# module, computes the official mel of a real file and checks that none of them was imported.
# "audio_module" loads diffsheg_core/audio.py with an empty parent package (so only audio.py and
# errors.py run); "package" imports it the ordinary way, running diffsheg_core/__init__.py and
# what it imports.
WITHOUT_LIBROSA = """
import importlib.util, sys, types
BLOCKED = {blocked!r}
for name in BLOCKED if {block!r} else ():
    sys.modules[name] = None  # `import name` (and name.anything) now raises ImportError
if {isolated!r}:
    package = types.ModuleType("diffsheg_core")
    package.__path__ = [{package!r}]
    sys.modules["diffsheg_core"] = package
import diffsheg_core.audio as audio
audio_in = audio.load_audio({path!r})
mel = audio.mel_features(audio_in)
assert mel.shape == (audio.n_motion_frames(audio_in), 128) and mel.dtype.name == "float32", mel.shape
assert audio.mel_spectrogram(audio.resample(audio_in, 18000).samples, 512, 300, 64).shape[0] == 64
loaded = sorted(name for name, module in sys.modules.items()
                if name.split(".")[0] in BLOCKED and module is not None)
assert not loaded, loaded
import numpy as np
np.save({out!r}, mel)
"""


@pytest.mark.parametrize("isolated, block", [
    pytest.param(True, True, id="audio_module"),
    pytest.param(True, False, id="audio_module_with_librosa_installed"),
    pytest.param(False, True, id="package"),
])
def test_audio_runs_without_librosa_scipy_and_numba(tmp_path, isolated, block):
    out = tmp_path / "mel.npy"
    code = WITHOUT_LIBROSA.format(blocked=NOT_IN_BLENDER, block=block, isolated=isolated,
                                  package=str(ROOT / "diffsheg_core"), path=str(MP3_AS_WAV), out=str(out))
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-3000:]
    reference = official_mel(MP3_AS_WAV)
    mel = np.load(out)
    assert mel.shape == reference.shape and np.abs(mel - reference).max() <= 1e-6 * reference.max()


def test_importing_audio_does_not_import_transformers():
    code = "import sys, diffsheg_core.audio; assert 'transformers' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


@pytest.fixture
def without_transformers(monkeypatch):
    """Make this process behave as if transformers were not installed."""
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name.split(".")[0] == "transformers" else real_find_spec(name, *a))
    monkeypatch.setitem(sys.modules, "transformers", None)


def test_hubert_without_transformers_says_what_to_install(tmp_path, without_transformers):
    assert "transformers" in hubert_status()
    audio = load_audio(SAMPLE_SPEECH)
    for model_path in (None, tmp_path):
        with pytest.raises(AudioError) as error:
            hubert_features(audio, n_motion_frames(audio), model_path=model_path)
        message = str(error.value)
        assert "pip install transformers" in message and HUBERT_REPO_ID in message
        assert "config.json" in message


@pytest.mark.skipif(not HAS_TRANSFORMERS, reason="needs transformers")
def test_hubert_missing_model_folder_is_reported(tmp_path):
    assert "does not exist" in hubert_status(tmp_path / "absent")
    (tmp_path / "config.json").write_text("{}")
    assert "model.safetensors" in hubert_status(tmp_path)
    with pytest.raises(AudioError, match="config.json"):
        hubert_features(load_audio(SAMPLE_SPEECH), 10, model_path=tmp_path)


def test_hubert_features_with_a_real_transformers_model(tiny_hubert):
    audio = load_audio(SCOTT_24BIT)  # 68 s: runs in four 20 s chunks
    n = n_motion_frames(audio)
    features = hubert_features(audio, n, model_path=tiny_hubert)
    assert features.shape == (n, 32) and features.dtype == np.float32
    assert np.isfinite(features).all() and features.std(axis=0).min() > 0
    quirk = hubert_features(audio, n, model_path=tiny_hubert, official_quirk=True)
    assert quirk.shape == (n, 32) and not np.allclose(quirk, features)
    with pytest.raises(AudioError, match="unknown device"):
        hubert_features(audio, n, model_path=tiny_hubert, device="gpu0")


@pytest.mark.skipif(hubert_status() is not None, reason=f"{HUBERT_REPO_ID} is not available locally")
def test_hubert_features_with_the_real_model():
    audio = load_audio(SAMPLE_SPEECH)
    n = n_motion_frames(audio)
    features = hubert_features(audio, n)
    assert features.shape == (n, 1024) and np.isfinite(features).all()
