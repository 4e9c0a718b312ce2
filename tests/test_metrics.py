"""Metrics on cases whose answer is known, on real speech and real phone timings."""

import json
from pathlib import Path

import numpy as np
import pytest

from diffsheg_core.audio import load_audio
from diffsheg_core.errors import DiffshegError
from diffsheg_core.training.metrics import (
    audio_beats, beat_alignment, blink_stats, diversity, envelope_correlation, foppas_seams,
    frechet_distance, mean_jerk, motion_beats, pcm, phone_tier, phoneme_contrast, read_textgrid,
    reference_correlation, seam_smoothness, srgr,
)
from diffsheg_core.training.metrics.lipsync import ENVELOPE_RATE, speech_envelope_db, voiced_reference_correlation

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SPEECH = DATA / "audio" / "2_scott_0_3_3.wav"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
TEXTGRID = DATA / "beat2" / "2_scott_0_1_1.TextGrid"
FPS = 15.0


@pytest.fixture(scope="module")
def speech():
    audio = load_audio(SPEECH)
    n = int(20 * audio.sample_rate)
    return audio.samples[:n], audio.sample_rate


def test_frechet_distance_is_zero_on_itself_and_grows_with_shift():
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(400, 16)) @ rng.normal(size=(16, 16))
    assert frechet_distance(feats, feats) == pytest.approx(0.0, abs=1e-6)
    distances = [frechet_distance(feats, feats + s) for s in (0.5, 1.0, 2.0)]
    assert distances[0] > 0.1 and distances[0] < distances[1] < distances[2]
    assert distances[2] == pytest.approx(16 * 4.0, rel=1e-3)  # |mu shift|^2, covariances equal
    other = rng.normal(size=(400, 16)) @ rng.normal(size=(16, 16))
    assert frechet_distance(feats, other) > distances[0]


def test_frechet_distance_rejects_mismatched_or_tiny_sets():
    with pytest.raises(DiffshegError, match="differ in width"):
        frechet_distance(np.zeros((5, 3)), np.zeros((5, 4)))
    with pytest.raises(DiffshegError, match="at least two"):
        frechet_distance(np.zeros((1, 3)), np.zeros((5, 3)))


def test_diversity_of_identical_samples_is_zero():
    clip = np.random.default_rng(1).normal(size=(34, 192))
    assert diversity(np.stack([clip] * 5)) == 0.0
    assert diversity(np.stack([clip, clip + 1.0])) == pytest.approx(1.0)
    assert diversity(np.random.default_rng(2).normal(size=(6, 34, 192))) > 1.0


def _motion_stopping_at(times: np.ndarray, n_frames: int) -> np.ndarray:
    """(T, 3) one joint swinging back and forth, coming to rest exactly at `times`."""
    t = np.arange(n_frames) / FPS
    fine = np.linspace(0, t[-1], 20 * n_frames)
    speed = np.min(np.abs(fine[:, None] - times[None, :]), axis=1)  # 0 at every stop
    position = np.cumsum(speed) * (fine[1] - fine[0])
    angle = np.interp(t, fine, position)
    return np.stack([angle, 0.5 * angle, np.zeros_like(angle)], axis=1)


def test_beat_alignment_prefers_motion_that_stops_on_audio_onsets(speech):
    samples, sr = speech
    onsets = audio_beats(samples, sr)
    assert 20 < len(onsets) < 100  # real speech: a few onsets per second
    assert np.diff(onsets).min() >= 0.2
    n = int(20 * FPS)
    aligned = motion_beats(_motion_stopping_at(onsets, n), FPS)
    assert len(aligned) == len(onsets)
    halfway = (onsets[:-1] + onsets[1:]) / 2  # stops half a beat off
    shifted = motion_beats(_motion_stopping_at(halfway, n), FPS)
    ba_aligned, ba_shifted = beat_alignment(onsets, aligned), beat_alignment(onsets, shifted)
    assert ba_aligned > 0.98
    assert ba_aligned > ba_shifted + 0.1
    late = motion_beats(_motion_stopping_at(onsets + 0.1, n), FPS)
    assert ba_shifted < beat_alignment(onsets, late) < ba_aligned
    assert beat_alignment(onsets, np.zeros(0)) == 0.0
    still = np.zeros((n, 3))
    assert len(motion_beats(still, FPS)) == 0


def test_pcm_and_srgr():
    rng = np.random.default_rng(3)
    gt = rng.normal(size=(50, 12))
    assert pcm(gt, gt) == 1.0
    off = gt.copy()
    off[:, :3] += 2.0  # first joint of four is always wrong
    assert pcm(off, gt, delta=1.0) == pytest.approx(0.75)
    weights = np.zeros(50)
    weights[:10] = 1.0
    off2 = gt.copy()
    off2[10:] += 5.0  # wrong only where the weight is 0
    assert srgr(off2, gt, weights) == 1.0
    assert pcm(off2, gt) == pytest.approx(0.2)
    with pytest.raises(DiffshegError, match="same frame count"):
        pcm(gt[:10], gt)


def test_jitter_and_seam_smoothness():
    t = np.arange(300) / FPS
    smooth = np.stack([np.sin(t), np.cos(0.7 * t)], axis=1)
    noisy = smooth + np.random.default_rng(4).normal(scale=0.02, size=smooth.shape)
    assert mean_jerk(noisy, FPS) > 10 * mean_jerk(smooth, FPS)

    seams = foppas_seams(300, 34, 4)
    assert seams[:3] == [30, 60, 90] and seams[-1] < 300
    assert seam_smoothness(smooth, FPS, seams, 4) == pytest.approx(1.0, abs=0.3)
    stepped = smooth.copy()
    for s in seams:
        stepped[s:] += 0.05  # a visible jump at every clip boundary
    assert seam_smoothness(stepped, FPS, seams, 4) > 3.0


def test_textgrid_reads_long_and_short_format(tmp_path):
    tiers = read_textgrid(TEXTGRID)
    assert set(tiers) == {"words", "phones"}
    phones = phone_tier(tiers)
    assert len(phones) == 684 and phones[1].label == "DH"
    assert phones[1].start == pytest.approx(1.42) and phones[-1].end == pytest.approx(64.097375)
    short = tmp_path / "short.TextGrid"
    short.write_text('File type = "ooTextFile"\nObject class = "TextGrid"\n\n0\n1.5\n<exists>\n1\n'
                     '"IntervalTier"\n"phones"\n0\n1.5\n2\n0\n0.7\n"AA1"\n0.7\n1.5\n"say ""hi"""\n')
    got = read_textgrid(short)["phones"]
    assert [(i.start, i.end, i.label) for i in got] == [(0, 0.7, "AA1"), (0.7, 1.5, 'say "hi"')]
    broken = tmp_path / "broken.TextGrid"
    broken.write_text("hello")
    with pytest.raises(DiffshegError, match="not a Praat TextGrid"):
        read_textgrid(broken)


def test_phoneme_contrast_on_real_phone_timings():
    phones = phone_tier(read_textgrid(TEXTGRID))
    n = int(64 * FPS)
    times = np.arange(n) / FPS
    jaw = np.full(n, 0.1)
    for p in phones:
        base = p.label.rstrip("012")
        if base in ("AA", "AE", "AH", "AO", "AW", "AY"):
            jaw[(times >= p.start) & (times < p.end)] = 0.6
        elif base in ("P", "B", "M"):
            jaw[(times >= p.start) & (times < p.end)] = 0.0
    result = phoneme_contrast(jaw, FPS, phones)
    assert result["n_open"] > 50 and result["n_bilabial"] > 30
    assert result["ratio"] > 2.0
    flat = phoneme_contrast(np.full(n, 0.3), FPS, phones)
    assert flat["ratio"] == pytest.approx(1.0)


def test_envelope_correlation_finds_the_lag():
    audio = load_audio(TAKE_WAV)
    samples = audio.samples[: 30 * audio.sample_rate]
    env = speech_envelope_db(samples, audio.sample_rate)
    # a mouth that follows the envelope 100 ms late, sampled at the motion rate
    t_env = np.arange(len(env)) / ENVELOPE_RATE
    mouth = np.interp(np.arange(int(30 * FPS)) / FPS - 0.1, t_env, env)
    r, lag = envelope_correlation(mouth, FPS, samples, audio.sample_rate)
    assert r > 0.7 and lag == pytest.approx(0.1, abs=0.02)
    r_ref, lag_ref = reference_correlation(mouth, mouth, FPS)
    assert r_ref == pytest.approx(1.0) and lag_ref == 0.0
    noise = np.random.default_rng(5).random(len(mouth))
    assert envelope_correlation(noise, FPS, samples, audio.sample_rate)[0] < 0.3


def test_voiced_reference_correlation_leaves_the_pauses_out():
    """Two mouths that move together while the voice sounds agree fully over voiced frames,
    however they differ in the pauses (where a whole-clip correlation is pulled down)."""
    from diffsheg_core.qc import voiced_frames

    audio = load_audio(TAKE_WAV)
    samples = audio.samples[: 30 * audio.sample_rate]
    n = int(30 * FPS)
    voiced = voiced_frames(samples, audio.sample_rate, FPS, n)
    assert 0.3 < voiced.mean() < 0.9
    rng = np.random.default_rng(2)
    mouth = rng.random(n)
    other = np.where(voiced, mouth, 1.0 - mouth)
    assert voiced_reference_correlation(mouth, other, FPS, samples, audio.sample_rate) == pytest.approx(1.0)
    assert reference_correlation(mouth, other, FPS)[0] < 0.5
    assert abs(voiced_reference_correlation(mouth, rng.random(n), FPS, samples, audio.sample_rate)) < 0.3


def test_blink_rate_and_duration():
    n = int(60 * FPS)
    t = np.arange(n) / FPS
    signal = np.full(n, 0.05)
    for start in (3.0, 15.0, 27.0, 40.0, 55.0):  # five 200 ms blinks (triangular, peak 1)
        signal = np.maximum(signal, 1.0 - np.abs(t - start - 0.2) / 0.2)
    stats = blink_stats(signal, FPS)
    assert stats["count"] == 5 and stats["per_minute"] == pytest.approx(5.0)
    assert stats["mean_duration"] == pytest.approx(0.2, abs=0.04)
    assert blink_stats(np.full(n, 0.05), FPS)["count"] == 0


# ---------------------------------------------------------------- autoencoder and the evaluate command

REAL_NPZ = DATA / "beat2" / "2_scott_0_1_1.npz"


@pytest.fixture(scope="module")
def real_take():
    from diffsheg_core.training.evaluate import load_reference

    return load_reference(REAL_NPZ)


@pytest.fixture(scope="module")
def autoencoder(real_take, tmp_path_factory):
    from diffsheg_core.training.autoencoder import AutoencoderConfig, MotionFeatures, train_autoencoders
    from diffsheg_core.training.metrics import layout_array
    from diffsheg_core.rigs import SMPLX

    motion = layout_array(real_take, SMPLX)
    cfg = AutoencoderConfig(clip_len=16, hidden=32, latent=8, steps=150, batch_size=32)
    feats, errors = train_autoencoders([motion[:600]], SMPLX, motion.mean(0), motion.std(0) + 1e-3, cfg)
    assert errors["gesture"] < 0.9  # reconstructs better than predicting the mean (~0.8)
    path = feats.save(tmp_path_factory.mktemp("ae") / "ae.pt")
    loaded = MotionFeatures.load(path)
    a, b = feats.features([motion]), loaded.features([motion])
    np.testing.assert_allclose(a["motion"], b["motion"], rtol=1e-5)
    return path


def test_frechet_distances_in_autoencoder_space_grow_with_jitter(real_take, autoencoder):
    from diffsheg_core.training.autoencoder import MotionFeatures
    from diffsheg_core.training.metrics import layout_array
    from diffsheg_core.rigs import SMPLX

    feats = MotionFeatures.load(autoencoder)
    motion = layout_array(real_take, SMPLX)
    real = feats.features([motion])["gesture"]
    assert len(real) == len(motion) // 16
    assert frechet_distance(real, real) == pytest.approx(0.0, abs=1e-6)
    noise = np.random.default_rng(6).normal(size=motion.shape)
    fgd = [frechet_distance(real, feats.features([motion + s * noise * motion.std(0)])["gesture"])
           for s in (0.1, 0.5, 1.5)]
    assert 0 < fgd[0] < fgd[1] < fgd[2]


def test_evaluate_command_writes_a_report_on_the_real_take(real_take, autoencoder, tmp_path):
    from diffsheg_core.training.evaluate import main

    generated = [tmp_path / "seed0.npz", tmp_path / "seed1.npz"]
    real_take.save_npz(generated[0])
    jittered = real_take.rotations + np.random.default_rng(7).normal(scale=0.02, size=real_take.rotations.shape)
    from diffsheg_core.motion import Motion

    Motion(fps=real_take.fps, rig=real_take.rig, joint_names=real_take.joint_names, rotations=jittered,
           face_names=real_take.face_names, face=real_take.face).save_npz(generated[1])
    out = tmp_path / "report"
    assert main(["--audio", str(TAKE_WAV), "--motion", *map(str, generated), "--reference", str(REAL_NPZ),
                 "--textgrid", str(TEXTGRID), "--autoencoder", str(autoencoder), "--clip-len", "34",
                 "--overlap", "4", "--out", str(out)]) == 0
    result = json.loads((out / "metrics.json").read_text())
    gen, ref, cmp = result["generated"], result["reference"], result["comparison"]
    assert 0.5 < ref["BA"] <= 1.0
    assert 0.15 < ref["mouth-envelope r"] < 0.35 and abs(ref["mouth-envelope lag (s)"]) <= 0.15
    assert ref["mouth open: vowels / bilabials"] > 2.0
    assert 0.8 < ref["seam acceleration / in-clip"] < 1.25  # real capture has no seams
    assert gen["jitter (mean jerk, rad/s^3)"] > ref["jitter (mean jerk, rad/s^3)"]
    assert cmp["jitter / reference jitter"] > 1.5
    assert cmp["Div between samples (gesture, rad)"] > 0
    assert cmp["FGD"] > 0 and cmp["FMD"] > 0 and cmp["FED"] >= 0
    assert 0.5 < cmp["PCM gesture (delta 1.0)"] <= 1.0
    report = (out / "report.md").read_text()
    assert "| BA |" in report and "FGD" in report
    for png in ("curves.png", "speed_histogram.png", "mouth_vs_speech.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(DiffshegError, match="nothing to evaluate"):
        main(["--audio", str(TAKE_WAV), "--out", str(out)])


def test_evaluate_accepts_a_body_only_bvh_reference(tmp_path):
    """The real BEAT capture as BVH has no face: gesture metrics and PCM, no mouth metrics."""
    from diffsheg_core.bvh import bvh_to_motion, read_bvh
    from diffsheg_core.training.evaluate import main
    from diffsheg_core.motion import Motion
    from diffsheg_core.rigs import ARKIT51

    bvh_path = DATA / "beat" / "2_scott_0_1_1.bvh"
    body = bvh_to_motion(read_bvh(bvh_path, fps=15.0))
    generated = tmp_path / "gen.npz"
    Motion(fps=15.0, rig="beat", joint_names=body.joint_names, rotations=body.rotations,
           face_names=list(ARKIT51), face=np.zeros((body.n_frames, 51), np.float32)).save_npz(generated)
    out = tmp_path / "report"
    assert main(["--audio", str(TAKE_WAV), "--motion", str(generated), "--reference", str(bvh_path),
                 "--reference-fps", "15", "--out", str(out), "--no-plots"]) == 0
    result = json.loads((out / "metrics.json").read_text())
    ref, cmp = result["reference"], result["comparison"]
    assert 0.5 < ref["BA"] <= 1.0 and "mouth-envelope r" not in ref
    assert cmp["PCM gesture (delta 1.0)"] == pytest.approx(1.0)
    assert "mouth r with reference" not in cmp


def test_naturalness_does_not_depend_on_the_skeleton():
    """The BEAT BVH and the BEAT2 SMPL-X version of the same capture give the same wrist
    figures (measured: 5 % apart); the capture holds its head about 13 degrees down."""
    from diffsheg_core.training.evaluate import load_reference
    from diffsheg_core.training.metrics.posture import naturalness

    data = Path(__file__).resolve().parents[2] / "shared" / "data"
    bvh = naturalness(load_reference(data / "beat" / "2_scott_0_1_1.bvh", fps=15))
    smplx = naturalness(load_reference(data / "beat2" / "2_scott_0_1_1.npz", fps=15))
    for key in ("wrist speed (arm lengths/s)", "wrist jitter (arm lengths/s^2)", "wrist spread (arm lengths)"):
        assert abs(bvh[key] / smplx[key] - 1) < 0.1, key
    assert 11 < bvh["head pitch (deg, down)"] < 15
