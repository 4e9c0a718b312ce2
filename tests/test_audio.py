"""Audio front end on real speech: loading, checks, resampling, mel and HuBERT features."""

from __future__ import annotations

import importlib.util
import math
import shutil
import subprocess
import sys
from pathlib import Path

import librosa
import numpy as np
import pytest
import soundfile as sf

from diffsheg_core.audio import (
    HUBERT_REPO_ID, SAMPLE_SPEECH, Audio, hubert_features, hubert_status, load_audio,
    mel_features, n_motion_frames, resample,
)
from diffsheg_core.errors import AudioError

ROOT = Path(__file__).resolve().parents[1]
AUDIO = ROOT.parent / "shared" / "data" / "audio"
SCOTT_24BIT = AUDIO / "2_scott_0_3_3.wav"  # 68.0 s, 16 kHz, 24-bit PCM
MP3_AS_WAV = AUDIO / "2_scott_0_103_103_28s.wav"  # MP3 data (44.1 kHz stereo) named .wav
ZHAO = AUDIO / "12_zhao_2_3_3.wav"  # 56 s, 16 kHz, 16-bit
BEAT2_FLOAT = ROOT.parent / "shared" / "data" / "beat2" / "2_scott_0_1_1.wav"  # 32-bit float

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


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg is not installed")
def test_formats_libsndfile_cannot_read_fall_back_to_audioread(tmp_path, zhao_clip):
    mono, rate = zhao_clip
    wav, m4a = tmp_path / "speech.wav", tmp_path / "speech.m4a"
    sf.write(wav, mono, rate)
    subprocess.run(["ffmpeg", "-v", "error", "-i", str(wav), "-c:a", "aac", str(m4a)], check=True)
    with pytest.raises(sf.SoundFileError):
        sf.info(m4a)
    audio = load_audio(m4a)
    assert audio.sample_rate == rate and audio.duration == pytest.approx(4.0, abs=0.1)


# --- mel features ----------------------------------------------------------------


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


# --- HuBERT ----------------------------------------------------------------------


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
