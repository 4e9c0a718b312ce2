"""The bundled default model (diffsheg_core/weights/default.safetensors) on real speech it
never saw: coarse versions of the quality bars of its model card, measured with the
project's metrics on 30 s of BEAT speaker scott (2_scott_0_3_3.wav), and lip-sync by
phonemes on 30 s of the real take 2_scott_0_1_1 with its real phone timings."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from diffsheg_core.audio import Audio, load_audio
from diffsheg_core.checkpoints import DEFAULT_WEIGHTS, load_model
from diffsheg_core.foppas import fast_sampling
from diffsheg_core.training.data.beat import read_gesture
from diffsheg_core.training.metrics import (
    blink_signal, blink_stats, diversity, envelope_correlation, layout_array, mean_jerk,
    mouth_opening, phone_tier, phoneme_contrast, read_textgrid, speed,
)
from diffsheg_core.training.metrics.channels import face_channel
from diffsheg_core.training.metrics.lipsync import base_phone
from diffsheg_core.phonetic import PHONES, log_mel
from diffsheg_core.pipeline import generate
from diffsheg_core.runtime.backends import open_network
from diffsheg_core.rigs import BEAT

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SPEECH = DATA / "audio" / "2_scott_0_3_3.wav"
REAL_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
TAKE_TEXTGRID = DATA / "beat2" / "2_scott_0_1_1.TextGrid"
SECONDS = 30.0
ARMS = ("RightArm", "RightForeArm", "LeftArm", "LeftForeArm")


@pytest.fixture(scope="module")
def bundle():
    return load_model()


def _first_seconds(path: Path) -> Audio:
    audio = load_audio(path)
    return Audio(samples=audio.samples[: int(SECONDS * audio.sample_rate)],
                 sample_rate=audio.sample_rate, path=audio.path)


@pytest.fixture(scope="module")
def speech() -> Audio:
    return _first_seconds(SPEECH)


@pytest.fixture(scope="module")
def samples(bundle, speech):
    return [generate(speech, model=bundle, seed=seed, device="cpu", upper_body_only=True) for seed in (0, 1)]


def _arm_columns() -> list[int]:
    return [3 * BEAT.joint_names.index(j) + k for j in ARMS for k in range(3)]


def test_bundled_weights_load(bundle):
    assert DEFAULT_WEIGHTS.is_file()
    # float16 weights for the torch backend and the same weights as ONNX graphs for onnxruntime
    assert DEFAULT_WEIGHTS.stat().st_size < 60e6 and bundle.has_graphs  # issue 29: under 60 MB
    assert bundle.trained and bundle.model_id == "diffsheg-default-v10"
    # issue 42: Mandarin's own face beside the shared one, fine-tuned from v10 on the capture alone
    assert sorted(bundle.faces) == ["zh"] and bundle.faces["zh"].record["model_id"] == "diffsheg-default-v10-zh"
    assert [d["kind"] for d in bundle.faces["zh"].record["datasets"]] == ["facegood"]
    # issue 42: v10's face learnt from the real captured Mandarin face beside the English rehearsal
    assert [d["kind"] for d in bundle.info["datasets"]] == ["facegood", "facegood"]
    assert bundle.info["training"]["trains"] == "face" and bundle.info["training"]["keep_unsaid"] == 1.0
    assert bundle.config.temporal_kernel == 5  # the gesture branch's temporal convolutions
    assert bundle.style_names == ["calm", "conversational", "animated"] and bundle.null_style
    assert bundle.default_style == "conversational"
    assert bundle.config.classifier_free and bundle.guidance == 2.0  # generation is guided by default
    assert bundle.skip_guidance == 0.1
    assert bundle.sampling.refine == 1 and bundle.sampling.refine_skip == 3.5  # the refining pass
    assert bundle.sampling.prior_start and bundle.prior is not None
    cfg = bundle.config
    assert cfg.layout == "beat_body" and cfg.fps == 15.0 and cfg.clip_len == 34  # the whole body
    assert cfg.lower_dim == 30 and bundle.prior.dims == cfg.gesture_dim == 171
    assert cfg.speech_encoder == "phonetic" and bundle.phonetic is not None
    assert bundle.info["trained_steps"] > 0 and "licence" in bundle.info
    assert np.isfinite(bundle.mean).all() and (bundle.std > 0).all()


def test_motion_from_real_speech_passes_coarse_bars(samples, speech):
    motion = samples[0]
    assert motion.rig == "beat" and motion.fps == 15.0
    assert abs(motion.n_frames - SECONDS * 15) <= 2
    assert np.isfinite(motion.rotations).all() and np.isfinite(motion.face).all()

    # lip-sync by voice: the jaw follows the speech envelope at a small lag
    r, lag = envelope_correlation(mouth_opening(motion), motion.fps, speech.samples, speech.sample_rate)
    assert r > 0.1 and abs(lag) <= 0.15

    # blinks at a human rate and of a human length
    blinks = blink_stats(blink_signal(motion), motion.fps)
    assert 4 <= blinks["per_minute"] <= 40
    assert 0.05 <= blinks["mean_duration"] <= 0.5

    # the arms move during speech, neither frozen nor shaking far beyond the real capture
    real = read_gesture(REAL_BVH, 15.0, source_fps=15.0)[1:]
    arms = layout_array(motion, BEAT)[:, _arm_columns()]
    real_arms = real[:, _arm_columns()]
    arm_speed, real_speed = float(speed(arms, 15.0).mean()), float(speed(real_arms, 15.0).mean())
    assert 0.1 * real_speed < arm_speed < 5 * real_speed
    assert mean_jerk(arms, 15.0) < 5 * mean_jerk(real_arms, 15.0)


def test_skip_guidance_brings_the_arms_to_the_real_captures_speed(bundle, samples, speech):
    """Skip guidance makes the arms faster (v8 with the refining pass, seed 0: 0.88x the real
    capture's mean joint speed on these 30 s with it, 0.66x without; v7 0.84x; v6 moved at
    1.04-1.20x, trained on the jerkier teacher v1)."""
    real = read_gesture(REAL_BVH, 15.0, source_fps=15.0)[1:, _arm_columns()]
    real_speed = float(speed(real, 15.0).mean())

    def arm_speed(motion) -> float:
        return float(speed(layout_array(motion, BEAT)[:, _arm_columns()], 15.0).mean())

    off = generate(speech, model=bundle, seed=0, device="cpu", skip_guidance=0.0)
    assert arm_speed(samples[0]) > 1.2 * arm_speed(off)
    assert 0.8 * real_speed < arm_speed(samples[0]) < 1.4 * real_speed
    # the face is untouched (against the guided steps themselves: by default the distilled student makes them)
    guided = generate(speech, model=replace(bundle, student=None), seed=0, device="cpu")
    assert np.array_equal(off.face, guided.face)


def test_the_gesture_prior_gives_the_gestures_the_real_captures_spread(bundle, samples, speech):
    """Gesture spread (std over the 30 s, mean over all 141 channels, fingers and spine too)
    against the real capture's over 30 s stretches: v8 0.76x and 1.04x with the prior for seeds 0
    and 1 (v7: 0.69x and 0.88x; v6: 0.81-0.92x;
    the wrists alone, the measure of issue 17: 1.04x on the whole take), more than from pure
    noise. The first window is the same either way, and so is the face."""
    real = read_gesture(REAL_BVH, 15.0, source_fps=15.0)[1:, : BEAT.gesture_dim]
    n = samples[0].n_frames
    real_spread = np.mean([real[s: s + n].std(0).mean() for s in range(0, len(real) - n, 150)])

    def spread(motion) -> float:
        return float(layout_array(motion, BEAT)[:, : BEAT.gesture_dim].std(0).mean())

    for sample in samples:  # the default sampling's (the distilled student's steps)
        assert samples[0].meta["prior_start"] and 0.6 * real_spread < spread(sample) < 1.25 * real_spread
    # the prior against pure noise, both with the model's own guided steps
    teacher, fast = replace(bundle, student=None), fast_sampling(bundle.sampling)
    with_prior, noise_starts = ([generate(speech, model=teacher, seed=seed, device="cpu", sampling=sampling,
                                          upper_body_only=True) for seed in (0, 1)]
                                for sampling in (fast, replace(fast, prior_start=False)))
    noise_start = noise_starts[0]
    assert not noise_start.meta["prior_start"]
    assert sum(map(spread, with_prior)) > 1.1 * sum(map(spread, noise_starts))
    first = bundle.config.clip_len - bundle.sampling.overlap
    assert np.array_equal(noise_start.rotations[:first], with_prior[0].rotations[:first])
    assert np.array_equal(noise_start.face, with_prior[0].face)


def test_seeds_give_different_gestures_with_the_same_lip_sync(samples, speech):
    gestures = np.stack([layout_array(m, BEAT)[:, : BEAT.gesture_dim] for m in samples])
    assert diversity(gestures) > 0.01
    mouths = [mouth_opening(m) for m in samples]
    assert np.corrcoef(mouths[0], mouths[1])[0, 1] > 0.5


def test_lips_close_for_bilabials_in_real_speech(bundle):
    take = _first_seconds(TAKE_WAV)
    phones = phone_tier(read_textgrid(TAKE_TEXTGRID))
    motion = generate(take, model=bundle, seed=0, device="cpu")
    jaw = phoneme_contrast(mouth_opening(motion), motion.fps, phones)
    assert jaw["n_bilabial"] >= 20 and jaw["ratio"] > 1.8  # 30 s: 2.07-2.28 over seeds 0-3; whole take: 2.44
    close = phoneme_contrast(face_channel(motion, "mouthClose"), motion.fps, phones)
    assert close["bilabial"] - close["open"] > 0.1  # 30 s: 0.20-0.21; whole take: 0.21

    # the default guidance shuts the jaw further at p/b/m (30 s, seeds 0-3: unguided 0.30-0.45 lower)
    unguided = generate(take, model=bundle, seed=0, device="cpu", guidance=1.0)
    assert phoneme_contrast(mouth_opening(unguided), unguided.fps, phones)["ratio"] < jaw["ratio"] - 0.15

    # the phonetic encoder hears p/b/m in a real voice (it was trained on synthetic ones)
    post = open_network(bundle).phone_posteriors(log_mel(take, bundle.phonetic))
    rate = bundle.phonetic.fps * bundle.phonetic.subframes
    bilabial = [PHONES.index(p) for p in ("P", "B", "M")]

    def p_bilabial(labels: tuple[str, ...]) -> float:
        frames = [int(p.middle * rate) for p in phones
                  if base_phone(p.label) in labels and p.middle * rate < len(post)]
        return float(post[frames][:, bilabial].sum(axis=1).mean())

    assert p_bilabial(("P", "B", "M")) > 2 * p_bilabial(("T", "D", "N"))


def test_onnx_and_torch_backends_agree_on_the_bundled_model(bundle, speech):
    """The same seed gives the same motion on either backend: the noise is numpy's, so in the
    model's own steps only float32 rounding in the network differs (per call at most 1e-4;
    whole takes 1e-3). The distilled student's products by weights are int8: torch runs the
    weights the file holds in float, onnxruntime rounds each call's activations to 8 bits too,
    so its fast takes agree within a small part of what a seed changes."""
    from diffsheg_core.diffusion import Schedule
    from diffsheg_core.guidance import Guidance, step_eps
    from diffsheg_core.speech_features import speech_features
    from diffsheg_core.style import style_vector

    short = Audio(speech.samples[: 10 * speech.sample_rate], speech.sample_rate)
    onnx, torch_net = open_network(bundle, "onnx"), open_network(bundle, "torch", "cpu")
    features, on_torch = speech_features(bundle, onnx, short), speech_features(bundle, torch_net, short)
    np.testing.assert_allclose(features.mel, on_torch.mel, atol=1e-5)
    np.testing.assert_allclose(features.speech, on_torch.speech, atol=1e-5)
    cfg, sched, rng = bundle.config, Schedule.linear().respaced(25), np.random.default_rng(0)
    x = rng.standard_normal((1, cfg.clip_len, cfg.dim), dtype=np.float32)
    window = features.frames(40, 40 + cfg.clip_len)
    mel, extra = window.mel[None], window.speech[None]
    for index in (24, 12, 0):
        i = np.array([index])
        args = (cfg.gesture_dim, x, sched.model_timesteps(i), mel, extra, style_vector(bundle, {1: 1.0}),
                sched.x0_coefs(i, x), Guidance(bundle.guidance, bundle.skip_guidance))
        assert np.abs(step_eps(onnx, *args)[0] - step_eps(torch_net, *args)[0]).max() <= 1e-4
    a = generate(short, model=bundle, seed=5, backend="onnx", sampling="quality")
    b = generate(short, model=bundle, seed=5, backend="torch", device="cpu", sampling="quality")
    assert a.meta["backend"] == "onnx" and b.meta["backend"] == "torch"
    assert np.abs(a.rotations - b.rotations).max() <= 1e-3 and np.abs(a.face - b.face).max() <= 1e-3
    fast = {backend: generate(short, model=bundle, seed=5, backend=backend, device="cpu") for backend in ("onnx", "torch")}
    other = generate(short, model=bundle, seed=6)
    assert fast["onnx"].meta["student"] == fast["torch"].meta["student"] == bundle.student.model_id
    for key in ("rotations", "face"):
        apart, seeds = (np.abs(getattr(fast["onnx"], key) - getattr(m, key)).mean() for m in (fast["torch"], other))
        assert 0 < apart < 0.15 * seeds, (key, apart, seeds)  # measured 0.045x (rotations), 0.07x (face)


@pytest.fixture(scope="module")
def take_30s() -> Audio:
    return _first_seconds(TAKE_WAV)


@pytest.fixture(scope="module")
def by_style(bundle, take_30s):
    """Two seeds of every named style, of a calm-animated mix and of animated guided beyond
    itself, on 30 s of the real take."""
    settings = {name: {"style": name} for name in bundle.style_names}
    settings["mix"] = {"style": {"calm": 0.5, "animated": 0.5}}
    settings["beyond"] = {"style": "animated", "style_guidance": 2.0}
    return {k: [generate(take_30s, model=bundle, seed=s, **v) for s in (0, 1)] for k, v in settings.items()}


def _wrists(motions) -> dict[str, float]:
    from diffsheg_core.training.metrics.posture import naturalness

    values = [naturalness(m) for m in motions]
    return {k.split(" (")[0]: float(np.mean([v[k] for v in values])) for k in values[0]}


def test_named_styles_are_told_apart_and_mix(by_style):
    """calm < conversational < animated in wrist speed and spread, the mix between calm and
    animated, and style guidance past animated livelier still without getting jerkier for
    its speed."""
    w = {k: _wrists(v) for k, v in by_style.items()}
    for key in ("wrist speed", "wrist spread"):
        assert w["calm"][key] < w["conversational"][key] < w["animated"][key], key
        assert w["calm"][key] < w["mix"][key] < w["animated"][key], key
    assert w["animated"]["wrist speed"] > 1.5 * w["calm"]["wrist speed"]
    assert w["beyond"]["wrist speed"] > 1.05 * w["animated"]["wrist speed"]
    jerk = {k: w[k]["wrist jitter"] / w[k]["wrist speed"] for k in ("animated", "beyond")}
    assert jerk["beyond"] < 1.15 * jerk["animated"], jerk


def test_every_style_keeps_the_face(by_style, take_30s):
    """The lip-sync and blink bars of the model card hold in every style."""
    phones = phone_tier(read_textgrid(TAKE_TEXTGRID))
    for name, motions in by_style.items():
        motion = motions[0]
        jaw = phoneme_contrast(mouth_opening(motion), motion.fps, phones)
        assert jaw["ratio"] > 1.8, (name, jaw)
        close = phoneme_contrast(face_channel(motion, "mouthClose"), motion.fps, phones)
        assert close["bilabial"] - close["open"] > 0.1, name
        blinks = blink_stats(blink_signal(motion), motion.fps)
        assert 4 <= blinks["per_minute"] <= 40, name


@pytest.fixture(scope="module")
def whole_take(bundle):
    """Two seeds of the default style on the whole real take 2_scott_0_1_1 (64 s), sampled fast
    (the default)."""
    take = load_audio(TAKE_WAV)
    return [generate(take, model=bundle, seed=s) for s in (0, 1)]


@pytest.fixture(scope="module")
def whole_take_quality(bundle):
    """The same, with the model's own 25-step sampling."""
    take = load_audio(TAKE_WAV)
    return [generate(take, model=bundle, seed=s, sampling="quality") for s in (0, 1)]


def test_gestures_move_about_as_the_capture_does(whole_take, whole_take_quality):
    """Issue 17's goals on the real take 2_scott_0_1_1, 2 seeds of the default style, with the
    model's own sampling (these two: wrist speed 0.94x the capture's, jitter 1.02x, spread
    1.04x, head pitch 1.1 degrees above the capture's; model card, 3 seeds: 0.93x, 1.00x,
    1.04x; v8 before the refining pass: 0.90x, 1.09x, 1.03x; v7: 0.83x, 1.06x, 0.92x; v6:
    1.09x, 1.46x, 0.86x and 4.1 degrees down). The fast sampling holds issue 39's bars against
    it: wrist speed 0.9-1.1x, jitter at most 1.1x (these seeds: 1.00x, 1.03x)."""
    from diffsheg_core.training.evaluate import load_reference
    from diffsheg_core.training.metrics.posture import naturalness

    real = naturalness(load_reference(REAL_BVH, fps=15.0))
    quality = _wrists(whole_take_quality)
    ratio = {k.split(" (")[0]: quality[k.split(" (")[0]] / v for k, v in real.items() if "pitch" not in k}
    assert ratio["wrist jitter"] < 1.1 and 0.9 < ratio["wrist speed"] < 1.1 and 0.9 < ratio["wrist spread"] < 1.1, ratio
    assert abs(quality["head pitch"] - real["head pitch (deg, down)"]) < 3
    fast = _wrists(whole_take)
    assert 0.9 < fast["wrist speed"] / quality["wrist speed"] < 1.1, (fast, quality)
    assert fast["wrist jitter"] / quality["wrist jitter"] <= 1.1, (fast, quality)
    assert abs(fast["head pitch"] - real["head pitch (deg, down)"]) < 3


def _seam_acceleration(motion, clip_len: int) -> float:
    """Mean wrist acceleration at the frames where each later window takes over from its
    known overlap (the last overlap frame and the two around it), over the mean of all frames."""
    from diffsheg_core.foppas import plan_windows
    from diffsheg_core.training.metrics.posture import wrist_positions

    acc = np.linalg.norm(np.diff(wrist_positions(motion), n=2, axis=0), axis=-1).mean(-1)
    overlap = motion.meta["overlap"]
    starts = [s for s, _ in plan_windows(motion.n_frames, clip_len, overlap)[1:] if s + overlap < len(acc)]
    return float(np.mean([acc[s + overlap - 3: s + overlap].mean() for s in starts]) / acc.mean())


def test_later_windows_continue_the_overlap_without_a_jump(bundle, whole_take):
    """The bundled sampling carries the overlap's gap into the new frames (FoppasConfig.carry):
    the wrists accelerate no harder where a window takes over than elsewhere. Without it they
    did, 1.33x the mean (seed 0), and the seams held most of the jitter above the capture's."""
    assert bundle.sampling.carry > 0 and all(m.meta["carry"] == bundle.sampling.carry for m in whole_take)
    seams = [_seam_acceleration(m, bundle.config.clip_len) for m in whole_take]
    assert max(seams) < 1.1, seams
    uncarried = generate(load_audio(TAKE_WAV), model=bundle, seed=0, sampling=replace(bundle.sampling, carry=0))
    assert _seam_acceleration(uncarried, bundle.config.clip_len) > 1.2


def test_the_refining_pass_takes_the_fast_wobble_out_of_the_gestures(bundle, whole_take):
    """Each finished window's gestures through the network once more (FoppasConfig.refine):
    against the same sampling without that pass, the wrists move faster with no more jitter
    (seed 0: 0.98 against 0.88 arm lengths/s, jitter 8.27 against 8.30), and the face is the
    same to the bit."""
    assert all(m.meta["refine"] == 0 and m.meta["refine_skip"] == 3.5 for m in whole_take)  # fast: its lowest step
    # with the model's own guided steps (by default the distilled student makes them, the pass included)
    fast, speech = fast_sampling(bundle.sampling), load_audio(TAKE_WAV)
    refined, unrefined = (generate(speech, model=bundle, seed=0, sampling=replace(fast, refine=refine))
                          for refine in (fast.refine, None))
    assert unrefined.meta["refine"] is None and unrefined.meta["refine_skip"] is None
    ours, before = _wrists([refined]), _wrists([unrefined])
    jerk = {k: w["wrist jitter"] / w["wrist speed"] for k, w in (("refined", ours), ("unrefined", before))}
    assert jerk["refined"] < 0.93 * jerk["unrefined"], jerk
    assert ours["wrist speed"] > before["wrist speed"]
    assert np.array_equal(unrefined.face, refined.face)
