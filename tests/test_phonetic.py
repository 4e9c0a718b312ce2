"""The phonetic encoder: phone labels per frame, the stacked features' alignment, training
on real synthesised speech with exact phone timings, and storage inside model files."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import random_bundle

from diffsheg_core.audio import SAMPLE_SPEECH, Audio, load_audio, n_motion_frames
from diffsheg_core.checkpoints import ModelBundle, load_model, save_checkpoint
from diffsheg_core.errors import CheckpointError, DiffshegError
from diffsheg_core.foppas import PRESETS
from diffsheg_core.phonetic import (ENCODER_RATE, PHONES, PhoneticConfig, encoder_speech, log_mel, raw_log_mel,
                                   recogniser_frames, stack_posteriors)
from diffsheg_core.pipeline import generate
from diffsheg_core.speech_features import speech_features
from diffsheg_core.runtime.backends import open_network
from diffsheg_core.torch_layer.export import with_graphs
from diffsheg_core.torch_layer.model import PhoneticEncoder, state_arrays
from diffsheg_core.training.corpus.build import BuildConfig, build
from diffsheg_core.training.corpus.phones import Phone
from diffsheg_core.training.train_phonetic import (
    corpus_utterances, evaluate_phonetic, frame_labels, labelled_mels, load_phonetic, main, save_phonetic,
    torch_posteriors,
)

SENTENCES = (
    "Peter and Bob bought a map of the big park.",
    "My mother met a man by the pub in March.",
    "Please put the pepper back on the top shelf.",
    "Bring me both books about maps and boats.",
)


def test_frame_labels_follow_phone_times():
    phones = [Phone("SIL", 0.0, 0.1), Phone("M", 0.1, 0.2), Phone("AA", 0.2, 0.4)]
    labels = frame_labels(phones, 30, 60.0)
    assert [PHONES[i] for i in labels[[0, 5, 6, 11, 12, 23, 24, 29]]] == \
        ["SIL", "SIL", "M", "M", "AA", "AA", "SIL", "SIL"]


def test_utterance_normalisation_takes_the_recording_level_out(data_dir):
    """A real voice 10 dB louder (another microphone gain) gives nearly the same input."""
    speech = load_audio(data_dir / "beat2" / "2_scott_0_1_1.wav")
    louder = Audio(speech.samples * np.sqrt(10.0), speech.sample_rate)
    cfg, raw = PhoneticConfig(), PhoneticConfig(normalise="none")
    assert cfg.normalise == "utterance"
    a, b = log_mel(speech, cfg), log_mel(louder, cfg)
    assert np.abs(a.mean(axis=1)).max() < 1e-4
    # where the voice is well above the 1e-5 floor the raw level moves by exactly 1 (10 dB);
    # normalised, by the share of floored frames only
    voiced = log_mel(speech, raw) > -3.0
    shift = log_mel(louder, raw) - log_mel(speech, raw)
    assert np.abs(shift[voiced] - 1.0).max() < 0.01
    assert np.abs(a - b)[voiced].mean() < 0.3
    # encoders saved before the option existed saw raw levels
    old = json.dumps({"channels": 16, "phones": list(PHONES)})
    assert PhoneticConfig.from_metadata(old, "old encoder").normalise == "none"
    with pytest.raises(DiffshegError, match="normalise must be one of utterance, none"):
        PhoneticConfig(normalise="global")


def test_features_stack_four_recogniser_frames_per_motion_frame():
    torch.manual_seed(0)
    encoder = PhoneticEncoder(PhoneticConfig(channels=16, dilations=(1,))).eval()
    audio = load_audio(SAMPLE_SPEECH)
    n = n_motion_frames(audio)
    post = torch_posteriors(encoder)(log_mel(audio, encoder.cfg))
    feats = stack_posteriors(post, n, encoder.cfg.subframes)
    assert post.shape[1] == len(PHONES) and abs(len(post) - 4 * n) <= 2
    assert feats.shape == (n, 4 * len(PHONES)) and feats.dtype == np.float32
    np.testing.assert_allclose(feats.reshape(n, 4, -1).sum(-1), 1.0, atol=1e-5)
    i = n // 2  # motion frame i (at i / 15 s) holds recogniser frames 4i-2 .. 4i+1
    np.testing.assert_allclose(feats[i].reshape(4, -1), post[4 * i - 2: 4 * i + 2], atol=1e-6)


def test_the_encoder_hears_what_its_corpus_holds_at_any_rate(data_dir):
    """Speech faster than the corpus's 16 kHz is band-limited to 8 kHz before the log-mel, the
    same however it arrives; 16 kHz and slower is heard as it is (bit for bit as before)."""
    from diffsheg_core.audio import resample
    from diffsheg_core.training.corpus.augment import SAMPLE_RATE

    assert ENCODER_RATE == SAMPLE_RATE
    cfg = PhoneticConfig()
    speech = load_audio(data_dir / "audio" / "lang" / "fr_css10_1.wav")  # 22.05 kHz, energy up to 11 kHz
    speech = speech.read(0, 3 * speech.sample_rate)
    at_16k = resample(speech, 16000)
    assert np.array_equal(encoder_speech(at_16k).samples, resample(at_16k, 18000).samples)
    reference = raw_log_mel(at_16k, cfg)
    for rate in (22050, 44100, 48000):
        mel = raw_log_mel(resample(speech, rate), cfg)
        assert mel.shape == reference.shape
        assert np.abs(mel - reference).max() < 1e-2, rate  # before: up to 2 in the bands above 8 kHz
        assert mel[-1].max() < -4.5, rate  # the top band (above 8 kHz) stays at the floor
    for n, rate in ((48000, 16000), (66150, 22050), (132301, 44100), (8001, 8000), (1234567, 48000)):
        assert recogniser_frames(n, rate, cfg) == raw_log_mel(Audio(np.zeros(n, np.float32), rate), cfg).shape[1]


@pytest.fixture(scope="module")
def tiny_corpus(tmp_path_factory):
    out = tmp_path_factory.mktemp("phonetic_corpus")
    text = out / "texts.txt"
    text.write_text("\n\n".join(SENTENCES))
    build(BuildConfig(out=out / "c", hours=24 / 3600, jobs=1, seed=1, engines=("espeak",),
                      text_files=(text,)), progress=False)
    return out / "c"


def test_trained_encoder_recognises_bilabials(tiny_corpus, tmp_path, capsys):
    torch.set_num_threads(2)
    out = tmp_path / "phonetic.safetensors"
    assert main(["--corpus", str(tiny_corpus), "--out", str(out), "--epochs", "120"]) == 0
    assert '"train_utterances"' in capsys.readouterr().out
    encoder = load_phonetic(out)
    data = labelled_mels(corpus_utterances(tiny_corpus, "train", 0.1), encoder.cfg)
    scores = evaluate_phonetic(encoder, data)
    assert scores["frame_accuracy"] > 0.6
    assert scores["p_bilabial_at_bilabials"] > 4 * scores["p_bilabial_at_other_phones"]


def _phonetic_bundle() -> tuple[ModelBundle, PhoneticEncoder]:
    torch.manual_seed(0)
    encoder = PhoneticEncoder(PhoneticConfig(channels=16, dilations=(1,))).eval()
    bundle = random_bundle(graphs=False, latent=32, layers=1, ff=64, heads=4, style_dim=1,
                           speech_encoder="phonetic", speech_dim=encoder.cfg.dim, speech_latent=16)
    bundle = replace(bundle, sampling=PRESETS["no-resample"], model_id="phonetic-test",
                     phonetic=encoder.cfg, phonetic_weights=state_arrays(encoder))
    return with_graphs(bundle), encoder


def test_model_files_carry_their_phonetic_encoder(tmp_path):
    bundle, encoder = _phonetic_bundle()
    assert set(bundle.graphs) == {"expression", "gesture", "phonetic"}
    path = save_checkpoint(bundle, tmp_path / "m.safetensors")
    loaded = load_model(path)
    assert loaded.phonetic is not None and loaded.config.speech_encoder == "phonetic"
    audio = load_audio(SAMPLE_SPEECH)
    features = {backend: speech_features(loaded, open_network(loaded, backend), audio)
                for backend in ("onnx", "torch")}
    reference = speech_features(bundle, open_network(bundle, "torch"), audio)
    for found, atol in ((features["torch"], 0), (features["onnx"], 1e-5)):
        np.testing.assert_allclose(found.mel, reference.mel, atol=atol)
        np.testing.assert_allclose(found.speech, reference.speech, atol=atol)
    assert reference.mel.shape[1] == 128 and reference.speech.shape[1] == 4 * len(PHONES)
    assert generate(audio, model=loaded, steps=3, device="cpu").n_frames == n_motion_frames(audio)

    save_checkpoint(replace(bundle, phonetic=None, phonetic_weights={}), tmp_path / "bare.safetensors")
    with pytest.raises(CheckpointError, match="holds no phonetic encoder"):
        load_model(tmp_path / "bare.safetensors")
    save_phonetic(encoder, tmp_path / "p.safetensors", {})
    # a training run may name a model file for its encoder: the one stored in it
    stored = load_phonetic(path)
    assert stored.cfg == encoder.cfg
    for key, value in state_arrays(encoder).items():
        np.testing.assert_array_equal(state_arrays(stored)[key], value)
    with pytest.raises(CheckpointError, match="holds no phonetic encoder"):
        load_phonetic(tmp_path / "bare.safetensors")
    from diffsheg_core.checkpoints import write_safetensors

    write_safetensors({"x": np.zeros(2, np.float32)}, {"format": "something-else/1"}, tmp_path / "other.safetensors")
    with pytest.raises(CheckpointError, match="not a phonetic encoder nor a model file"):
        load_phonetic(tmp_path / "other.safetensors")
    with pytest.raises(CheckpointError, match="train-phonetic"):
        load_phonetic(tmp_path / "absent.safetensors")
