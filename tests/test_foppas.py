"""FOPPAS windowing, outpainting and streaming, on real speech and synthetic models."""

import json
from dataclasses import replace

import numpy as np
import pytest
import soundfile as sf

from conftest import random_bundle
from diffsheg_core.audio import load_audio, n_motion_frames
from diffsheg_core.conditioning import Conditioning, SpeechFeatures
from diffsheg_core.diffusion import Schedule
from diffsheg_core.errors import DiffshegError
from diffsheg_core.foppas import (PROPOSAL_STREAM, Foppas, FoppasConfig, FoppasStream, PRESETS,
                                  carry_overlap, inpaint_range, jump_schedule, model_calls, plan_windows, sample_long)
from diffsheg_core.guidance import Guidance
from diffsheg_core.pipeline import generate, make_eps_fn_factory
from diffsheg_core.prior import GesturePrior
from diffsheg_core.runtime.backends import open_network
from diffsheg_core.style import StyleTrack, style_track, style_vector
from diffsheg_core.validate import check_seed


def conditioning(mel: np.ndarray, model=None) -> Conditioning:
    """(T, F) `mel` as the conditioning of T frames: a mel-only model's speech features, with
    `model`'s default style throughout (toy models, without a model, read the mel alone)."""
    if model is None:
        return Conditioning(SpeechFeatures(mel), StyleTrack(np.zeros((len(mel), 1), np.float32)))
    return Conditioning(SpeechFeatures(mel), style_track(model, None, None, len(mel)))


def test_official_schedules_match_golden(golden_dir):
    golden = json.loads((golden_dir / "schedules.json").read_text())
    for (jl, jn), calls in {(1, 1): 15, (3, 2): 27, (3, 5): 63}.items():
        times = jump_schedule(14, jl, jn)
        entry = golden[f"ddim25_jump_length{jl}_jump_n_sample{jn}"]
        assert times == entry["times"]
        assert model_calls(times) == entry["model_calls"] == calls


def test_official_preset_makes_27_model_calls_per_later_clip():
    sampler = Foppas(Schedule.linear(), PRESETS["official-beat"], 34, 4)
    counts = []
    stream = FoppasStream(sampler, lambda cond: lambda x, i: counts.append(i) or np.zeros_like(x), 0)
    stream.push(conditioning(np.zeros((34 + 30 + 30, 1), np.float32)))
    stream.finish()
    per_clip = [counts[:25], counts[25:52], counts[52:79]]
    assert [len(c) for c in per_clip] == [25, 27, 27] and len(counts) == 79
    assert per_clip[1][0] == 14  # later clips start at respaced t = 14


@pytest.mark.parametrize("n,expected", [
    (10, [(0, 10)]), (34, [(0, 34)]), (35, [(0, 34), (30, 35)]),
    (100, [(0, 34), (30, 64), (60, 94), (90, 100)]),
])
def test_plan_windows(n, expected):
    assert plan_windows(n, 34, 4) == expected


@pytest.fixture(scope="module")
def model():
    return random_bundle()


def cut(data_dir, tmp_path, n_frames):
    """Real speech cut to exactly n_frames motion frames (15 fps)."""
    samples, sr = sf.read(data_dir / "audio" / "2_scott_0_3_3.wav", dtype="float32")
    path = tmp_path / f"cut{n_frames}.wav"
    sf.write(path, samples[: int(sr * (n_frames + 0.5) / 15)], sr)
    return path


@pytest.mark.parametrize("n_frames", [20, 34, 35, 400])
def test_output_length_equals_audio_frame_count(data_dir, tmp_path, model, n_frames):
    path = cut(data_dir, tmp_path, n_frames)
    assert n_motion_frames(load_audio(path)) == n_frames
    motion = generate(path, model=model, steps=5, device="cpu")
    assert motion.n_frames == n_frames
    assert np.isfinite(motion.rotations).all()


def test_far_above_one_clip_on_a_whole_recording(data_dir, model):
    path = data_dir / "audio" / "12_zhao_2_3_3.wav"
    motion = generate(path, model=model, steps=3, overlap=4, device="cpu")
    assert motion.n_frames == n_motion_frames(load_audio(path)) > 20 * 34


def window_outputs(sampler, make_eps_fn, n_frames, seed=0):
    """Run the stream and record every window the sampler produced."""
    windows = []
    original = sampler.sample_window

    def recording(*args, **kwargs):
        out = original(*args, **kwargs)
        windows.append(out[0].copy())
        return out

    sampler.sample_window = recording
    motion = sample_long(sampler, make_eps_fn, conditioning(np.zeros((n_frames, 1), np.float32)), seed)
    return motion, windows


@pytest.mark.parametrize("backend", ["onnx", "torch"])
def test_overlap_equals_previous_tail_exactly_without_blending(model, backend):
    cfg = model.config
    sampler = Foppas(Schedule.linear(), FoppasConfig(steps=10, overlap=4, later_start=6, blend=False),
                     cfg.clip_len, cfg.dim)
    network = open_network(model, backend=backend, device="cpu")
    make = make_eps_fn_factory(model, network, sampler, Guidance())
    cond = conditioning(np.random.default_rng(0).random((100, cfg.mel_dim), dtype=np.float32), model)
    windows = []
    original = sampler.sample_window
    sampler.sample_window = lambda *a, **k: windows.append(original(*a, **k)[0].copy()) or windows[-1][None]
    motion = sample_long(sampler, make, cond, 1)
    assert len(windows) == 4
    for prev, nxt in zip(windows, windows[1:]):
        assert np.array_equal(nxt[:4], prev[-4:])
    assert np.array_equal(motion[:30], windows[0][:30]) and np.array_equal(motion[30:60], windows[1][:30])


def smooth_model():
    """The exact denoiser for smooth random motion: x0 drawn from a Gaussian process
    with a squared-exponential kernel (length 4 frames), so E[x0 | x_t] is linear."""
    sched = Schedule.linear().respaced(25)

    def make(cond):
        t = cond.features.mel[:, 0].astype(np.float64)
        k = np.exp(-0.5 * ((t[:, None] - t[None, :]) / 4.0) ** 2)
        eye = np.eye(len(t))

        def eps(x, index):
            a, b = sched.x0_coefs(np.array([index]), x)
            abar = float(1.0 / a.reshape(-1)[0] ** 2)
            gain = abar ** 0.5 * k @ np.linalg.inv(abar * k + (1 - abar) * eye + 1e-6 * eye)
            x0 = (gain @ x[0].astype(np.float64)).astype(np.float32)[None]
            return (a * x - x0) / b

        return eps

    return make


def seam_and_inside_steps(blend, carry=0, order=1):
    """|order-th differences| of motion sampled with the exact denoiser, at the window seams
    (from a frame before a window to two past its overlap) and everywhere else."""
    sampler = Foppas(Schedule.linear(), FoppasConfig(overlap=4, blend=blend, carry=carry), 34, 2)
    frames = np.arange(300, dtype=np.float32).reshape(-1, 1)
    motion = sample_long(sampler, smooth_model(), conditioning(frames), 0)
    steps = np.abs(np.diff(motion[:, 0], n=order))
    seams = {s for start, _ in plan_windows(300, 34, 4)[1:] for s in range(start - 1, start + 4 + order)}
    inside = [i for i in range(len(steps)) if i not in seams]
    return steps[sorted(seams)], steps[inside]


def test_blending_keeps_clip_boundaries_as_smooth_as_the_clips():
    seams, inside = seam_and_inside_steps(blend=True)
    assert seams.max() <= inside.max()
    unblended, _ = seam_and_inside_steps(blend=False)
    assert unblended.max() > seams.max()


def test_carrying_the_overlap_gap_leaves_no_seam_in_the_acceleration():
    """Even with the exact denoiser, replacing the overlap leaves a kink where a window
    takes over (the cross-fade only shortens it); carrying the gap removes it."""
    seams, inside = seam_and_inside_steps(blend=False, carry=12, order=2)
    assert seams.max() <= inside.max() and seams.mean() <= 1.1 * inside.mean()
    faded, _ = seam_and_inside_steps(blend=True, order=2)
    assert faded.max() > 1.5 * inside.max()


def test_carry_overlap_moves_only_the_frames_next_to_the_seam():
    sched = Schedule.linear().respaced(25)
    rng = np.random.default_rng(0)
    x, eps = rng.standard_normal((2, 2, 34, 5)).astype(np.float32)
    known = rng.standard_normal((1, 4, 5)).astype(np.float32)
    index, width = 7, 12
    carried = carry_overlap(sched, x, index, eps, known, width, channels=3)
    assert np.array_equal(carried[..., 3:], eps[..., 3:])  # the face keeps its prediction
    before, after = (sched.predict_x0(x, np.full(2, index), e)[..., :3] for e in (eps, carried))
    gap = known[:, -1, :3] - before[:, 3]
    assert np.allclose(after[:, :4], known[..., :3], atol=1e-4)
    shift = after[:, 4:] - before[:, 4:]
    fade = 0.5 * (1 + np.cos(np.pi * np.arange(1, width) / width))
    assert np.allclose(shift[:, : width - 1], gap[:, None] * fade[None, :, None], atol=1e-4)
    assert np.allclose(shift[:, width - 1:], 0.0, atol=1e-4)


@pytest.mark.parametrize("carry", [-1, 2.5, True])
def test_a_bad_carry_is_refused(carry):
    with pytest.raises(ValueError, match="carry"):
        Foppas(Schedule.linear(), FoppasConfig(carry=carry), 34, 4)


def leaky_model(leak: float):
    """The exact denoiser of `smooth_model`, except that on the first channel (the gestures)
    it lets a share `leak` of its input's frame-to-frame detail through into x0, as a small
    network leaves part of the noise it is shown. The detail left by the last steps is too
    fine for the lowest step to tell from motion: it stays, as fast wobble."""
    sched = Schedule.linear().respaced(25)
    exact = smooth_model()

    def make(cond):
        eps_exact = exact(cond)

        def eps(x, index, refine=False):
            a, b = sched.x0_coefs(np.array([index]), x)
            x0 = a * x - b * eps_exact(x, index)
            padded = np.pad(x[..., :1], ((0, 0), (1, 1), (0, 0)), mode="edge")
            detail = x[..., :1] - 0.25 * padded[:, :-2] - 0.5 * padded[:, 1:-1] - 0.25 * padded[:, 2:]
            x0[..., :1] += leak * detail
            return (a * x - x0) / b

        return eps

    return make


def sampled_with_leak(leak: float, refine=None) -> np.ndarray:
    """300 frames of 2 channels (the second the face) at eta 1, as the bundled model samples."""
    config = FoppasConfig(overlap=4, carry=12, eta=1.0, refine=refine)
    sampler = Foppas(Schedule.linear(), config, 34, 2, gestures=1)
    return sample_long(sampler, leaky_model(leak), conditioning(np.arange(300, dtype=np.float32).reshape(-1, 1)), 0)


def test_refining_takes_the_leftover_wobble_out_of_the_gestures_and_keeps_the_face():
    """A denoiser that lets part of its input's fine detail through leaves the gestures
    jerkier than the exact one (about 2x); one more pass over each finished window, as if
    it were at the second-lowest noise level, sees little fine detail left and takes most
    of the excess out, keeping the slow motion. The face is returned as sampled, bit for
    bit: the pass draws no noise, so every later window's noise is unchanged."""
    jerk = lambda m: float(np.abs(np.diff(m[:, 0], n=2)).mean())
    slow = lambda m: np.convolve(m[:, 0], np.ones(9) / 9, mode="valid")
    exact, rough, refined = sampled_with_leak(0.0), sampled_with_leak(0.5), sampled_with_leak(0.5, refine=1)
    # measured: 0.067 exact, 0.131 leaky, 0.095 leaky and refined
    assert jerk(rough) > 1.8 * jerk(exact)
    assert jerk(refined) - jerk(exact) < 0.5 * (jerk(rough) - jerk(exact))
    assert np.abs(slow(refined) - slow(rough)).mean() < 0.1 * np.abs(slow(rough)).mean()
    assert np.array_equal(refined[:, 1], rough[:, 1])


def test_refine_window_replaces_the_gestures_by_the_x0_at_its_step_and_paints_the_overlap():
    sampler = Foppas(Schedule.linear(), FoppasConfig(overlap=4, refine=2), 34, 5, gestures=3)
    sched = sampler.schedule
    rng = np.random.default_rng(0)
    x, eps = rng.standard_normal((2, 2, 34, 5)).astype(np.float32)
    known = rng.standard_normal((1, 4, 5)).astype(np.float32)
    calls = []

    def eps_fn(window, index, refine=False):
        calls.append((index, refine))
        return eps

    out = sampler.refine_window(eps_fn, x, known)
    assert calls == [(2, True)]
    assert np.array_equal(out[..., 3:], x[..., 3:])  # the face as sampled
    x0 = sched.predict_x0(x, np.full(2, 2), eps)[..., :3]
    np.testing.assert_allclose(out[:, 4:, :3], x0[:, 4:], atol=1e-5)
    ramp = np.linspace(0, 1, 4).reshape(1, -1, 1)
    np.testing.assert_allclose(out[:, :4, :3], known[..., :3] * (1 - ramp) + x0[:, :4] * ramp, atol=1e-5)
    assert np.array_equal(out[:, 0, :3], np.broadcast_to(known[:, 0, :3], (2, 3)))
    # without the cross-fade at the lowest level, the overlap is the known frames, as the last step leaves it
    unblended = Foppas(Schedule.linear(), FoppasConfig(overlap=4, refine=2, blend_below=0.0), 34, 5, gestures=3)
    out = unblended.refine_window(eps_fn, x, known)
    assert np.array_equal(out[:, :4, :3], np.broadcast_to(known[..., :3], (2, 4, 3)))


def test_the_refining_pass_steers_with_the_skip_scale_times_refine_skip(model):
    """eps_fn(..., refine=True) is the gesture branch with skip guidance s * refine_skip, fed
    the window's face as the face's x0 (it is final: the expression branch does not run
    again); without skip guidance it is the plain gesture branch. The face's part is zero."""
    from diffsheg_core.guidance import face_eps, gesture_eps

    cfg = model.config
    sampler = Foppas(Schedule.linear(), FoppasConfig(refine=1, refine_skip=3.5), cfg.clip_len, cfg.dim)
    network = open_network(model, backend="onnx", device="cpu")
    style = style_vector(model, {0: 1.0})
    rng = np.random.default_rng(0)
    mel = rng.random((1, cfg.clip_len, cfg.mel_dim), dtype=np.float32)
    x = rng.standard_normal((1, cfg.clip_len, cfg.dim)).astype(np.float32)
    g, t = cfg.gesture_dim, sampler.schedule.model_timesteps(np.array([1]))
    audio = face_eps(network, x[..., g:], t, mel, None, style)[1]

    def eps(guidance, refine):
        return make_eps_fn_factory(model, network, sampler, guidance)(conditioning(mel[0], model))(x, 1, refine=refine)

    for given, steered in ((Guidance(skip=0.1), Guidance(skip=0.1 * 3.5)), (Guidance(), Guidance())):
        refined = eps(given, True)
        assert not refined[..., g:].any()
        np.testing.assert_allclose(refined[..., :g], gesture_eps(network, x[..., :g], t, audio, None, style,
                                                                 x[..., g:], steered), atol=1e-6)
    assert not np.allclose(eps(Guidance(skip=0.1), True)[..., :g], eps(Guidance(skip=0.1), False)[..., :g])


def test_refine_follows_the_number_of_steps():
    config = FoppasConfig(later_start=17, refine=1)
    assert config.with_steps(50).refine == 2 and config.with_steps(10).refine == 0
    assert FoppasConfig().with_steps(50).refine is None


@pytest.mark.parametrize("setting", [{"refine": -1}, {"refine": 25}, {"refine": 1.0}, {"refine": True},
                                     {"refine_skip": -0.5}, {"refine_skip": float("nan")},
                                     {"refine_skip": float("inf")}, {"refine_skip": True}, {"refine_skip": "2"}])
def test_bad_refine_settings_are_refused(setting):
    name = next(iter(setting))
    with pytest.raises(ValueError, match=f"{name} must be"):
        Foppas(Schedule.linear(), FoppasConfig(**setting), 34, 4)


@pytest.mark.parametrize("backend", ["onnx", "torch"])
def test_stream_equals_offline_and_emits_early(model, backend):
    cfg = model.config
    cond = conditioning(np.random.default_rng(0).random((150, cfg.mel_dim), dtype=np.float32), model)
    conf = FoppasConfig(steps=4, later_start=2)

    def sampler():
        return Foppas(Schedule.linear(), conf, cfg.clip_len, cfg.dim)

    s = sampler()
    network = open_network(model, backend=backend, device="cpu")
    make = make_eps_fn_factory(model, network, s, Guidance())
    offline = sample_long(s, make, cond, 3)
    stream = FoppasStream(sampler(), make, 3)
    parts, emitted_after = [], []
    for start in range(0, 150, 10):
        parts.append(stream.push(cond.frames(start, start + 10)))
        emitted_after.append(sum(len(p) for p in parts))
    parts.append(stream.finish())
    streamed = np.concatenate(parts)
    assert streamed.dtype == offline.dtype == np.float32
    assert np.array_equal(streamed, offline)
    # latency: after 40 frames of speech the first 30 frames are out
    assert emitted_after[3] >= 30
    assert all(received - out <= cfg.clip_len for received, out in zip(range(10, 160, 10), emitted_after))


def test_bad_overlap_is_refused():
    with pytest.raises(ValueError, match="overlap"):
        Foppas(Schedule.linear(), FoppasConfig(overlap=34), 34, 4)


def test_later_windows_start_from_the_proposal_noised_to_the_start_level():
    """Given a proposal, a later window's first model input is q(x_start | draw); the first
    window and a sampler without a proposal start from pure noise."""
    config = PRESETS["official-beat"]
    calls = []

    def proposal(known: np.ndarray, length: int, generator: np.random.Generator) -> np.ndarray:
        calls.append((tuple(known.shape), length))
        return np.full((length, 4), 50.0, np.float32)

    def first_inputs(sampler: Foppas) -> list[float]:
        means = []

        def make(cond):
            seen = []

            def eps_fn(x, index):
                if not seen:
                    seen.append(True)
                    means.append(float(x[0, config.overlap:].mean()))
                return np.zeros_like(x)
            return eps_fn
        sample_long(sampler, make, conditioning(np.zeros((34 + 30 + 20, 1), np.float32)), 0)
        return means

    with_draw = first_inputs(Foppas(Schedule.linear(), config, 34, 4, proposal=proposal))
    assert calls == [((config.overlap, 4), 34), ((config.overlap, 4), 24)]  # the last window is short
    level = float(np.sqrt(Schedule.linear().respaced(config.steps).alphas_cumprod[config.start_index]))
    assert abs(with_draw[0]) < 0.5  # the first window: noise
    for mean in with_draw[1:]:
        assert abs(mean - 50.0 * level) < 0.5
    without = first_inputs(Foppas(Schedule.linear(), config, 34, 4))
    assert all(abs(m) < 0.5 for m in without)


def two_channels(known, length, generator):
    """A proposal of the first two channels: the known frames, then noise from its generator."""
    return np.concatenate([known[:, :2], generator.standard_normal((length - len(known), 2), dtype=np.float32)])


def test_a_proposal_of_some_channels_leaves_the_others_noise_unchanged():
    """The proposal draws from its own generator: the channels it does not cover get the
    same noise as without it, so they come out the same."""
    config = PRESETS["official-beat"]

    def run(proposal) -> np.ndarray:
        sampler = Foppas(Schedule.linear(), config, 34, 4, proposal=proposal)
        make = lambda cond: lambda x, i: 0.1 * x  # any model that treats the channels apart
        return sample_long(sampler, make, conditioning(np.zeros((80, 1), np.float32)), 3)

    plain, proposed = run(None), run(two_channels)
    assert np.array_equal(plain[:, 2:], proposed[:, 2:])
    assert np.array_equal(plain[:30, :2], proposed[:30, :2])  # the first window has no proposal
    assert not np.allclose(plain[30:, :2], proposed[30:, :2])


def widened(upper: int, branch: int, face: int):
    """A toy UniEG widened with a lower branch: its first `upper` gesture channels and the
    face treat each channel apart (eps = 0.1 x); the branch's `branch` channels, after them,
    also see the others (their mean), as the lower branch sees the upper body."""

    def make(cond):
        def eps_fn(x, index, refine=False):
            eps = 0.1 * x
            eps[..., upper: upper + branch] += 0.05 * x[..., :upper].mean(-1, keepdims=True)
            return eps
        return eps_fn

    return make


@pytest.mark.parametrize("options", [{}, {"face_seed": 9}, {"candidates": 3}])
def test_a_lower_branch_leaves_the_other_channels_as_the_model_without_it_samples_them(options):
    """A model widened with a lower branch samples its source's channels exactly as the source
    does for the same seed (the branch's noise, in the sampler and in the prior's proposal,
    comes from streams of its own, and best-of-N compares the source's channels): after the
    widening, a seed gives the same gestures and face, now with legs. So does a regenerated range."""
    upper, branch, face, frames = 3, 2, 2, 100
    rng = np.random.default_rng(1)
    walk = np.cumsum(rng.standard_normal((2000, upper + branch)), axis=0) * 0.05
    walk -= walk.mean(0)
    prior = GesturePrior.fit([walk[:, :upper]], upper, 34)
    legs = GesturePrior.fit([walk[:, upper:]], branch, 34)
    config = replace(PRESETS["official-beat"], candidates=options.get("candidates", 1))

    def run(g: int, with_branch: int, proposal) -> tuple[np.ndarray, np.ndarray]:
        sampler = Foppas(Schedule.linear(), config, 34, g + face, proposal=proposal.propose, gestures=g,
                         branch=with_branch)
        cond = conditioning(np.zeros((frames, 1), np.float32))
        make = widened(upper, with_branch, face)
        stream = FoppasStream(sampler, make, 4, face_seed=options.get("face_seed"), expected_frames=frames)
        whole = np.concatenate([stream.push(cond), stream.finish()])
        ranged = inpaint_range(sampler, make, cond, whole, 40, 70, 5, face_seed=options.get("face_seed"))
        own = np.r_[0:upper, g:g + face]  # the source's channels
        return whole[:, own], ranged[:, own]

    source = run(upper, 0, prior)
    with_legs = run(upper + branch, branch, prior.beside(legs))
    for a, b in zip(source, with_legs):
        np.testing.assert_allclose(a, b, atol=1e-5)


def test_a_lower_branch_can_be_stepped_with_an_eta_of_its_own():
    """branch_eta steps only the lower branch's channels with another eta (live samples the
    legs deterministically): the other channels are the same to the bit, the legs differ;
    branch_eta equal to eta changes nothing, and one outside 0-1 is refused."""
    upper, branch, face, frames = 3, 2, 2, 100
    g = upper + branch

    def run(**change) -> np.ndarray:
        config = replace(PRESETS["official-beat"], eta=1.0, **change)
        sampler = Foppas(Schedule.linear(), config, 34, g + face, gestures=g, branch=branch)
        stream = FoppasStream(sampler, widened(upper, branch, face), 4, expected_frames=frames)
        cond = conditioning(np.zeros((frames, 1), np.float32))
        return np.concatenate([stream.push(cond), stream.finish()])

    model, same, legs_still = run(), run(branch_eta=1.0), run(branch_eta=0.0)
    others = np.r_[0:upper, g:g + face]
    assert np.array_equal(model, same)
    assert np.array_equal(model[:, others], legs_still[:, others])
    assert not np.allclose(model[:, upper:g], legs_still[:, upper:g])
    with pytest.raises(ValueError, match="branch_eta"):
        replace(PRESETS["official-beat"], branch_eta=1.5).check(34)


# ---------------------------------------------------------------- seeds

def first_model_inputs(seed, n_frames=80, proposal=None, dim=4):
    """(the first x_t each window's model sees, the generators the proposal was handed, output)
    for a deterministic model (eps = 0.1 x)."""
    sampler = Foppas(Schedule.linear(), PRESETS["official-beat"], 34, dim, proposal=proposal)
    firsts = []

    def make(cond):
        def eps_fn(x, index):
            if len(firsts) < len(made):
                firsts.append(x.copy())
            return 0.1 * x
        made.append(True)
        return eps_fn

    made = []
    out = sample_long(sampler, make, conditioning(np.zeros((n_frames, 1), np.float32)), seed)
    return firsts, out


@pytest.mark.parametrize("seed", [0, 7, 2**100])
def test_the_noise_is_numpy_pcg64_seeded_with_the_seed(seed):
    """The first window starts from default_rng(seed)'s first draw, and the proposal draws
    from default_rng([seed, PROPOSAL_STREAM]): nothing of the backend or device enters."""
    firsts, _ = first_model_inputs(seed)
    expected = np.random.default_rng(seed).standard_normal((1, 34, 4), dtype=np.float32)
    assert firsts[0].dtype == np.float32 and np.array_equal(firsts[0], expected)

    handed = []

    def recording(known, length, generator):
        handed.append(generator.bit_generator.state)
        return two_channels(known, length, generator)

    first_model_inputs(seed, proposal=recording)
    assert handed[0] == np.random.default_rng([seed, PROPOSAL_STREAM]).bit_generator.state


def test_a_huge_seed_works_and_is_deterministic(data_dir, tmp_path, model):
    seed = 2**100
    firsts, out = first_model_inputs(seed, proposal=two_channels)
    again_firsts, again = first_model_inputs(seed, proposal=two_channels)
    assert np.array_equal(out, again) and all(np.array_equal(a, b) for a, b in zip(firsts, again_firsts))
    _, other = first_model_inputs(seed + 1, proposal=two_channels)
    assert not np.allclose(out, other)
    path = cut(data_dir, tmp_path, 40)
    a = generate(path, model=model, seed=seed, steps=3, device="cpu")
    b = generate(path, model=model, seed=seed, steps=3, device="cpu")
    assert a.meta["seed"] == seed
    assert np.array_equal(a.rotations, b.rotations) and np.array_equal(a.face, b.face)
    c = generate(path, model=model, seed=seed + 1, steps=3, device="cpu")
    assert not np.allclose(a.rotations, c.rotations)


@pytest.mark.parametrize("seed", [-1, -(2**100), 1.5, 2.0, True, "3", None])
def test_bad_seeds_are_refused(model, seed):
    with pytest.raises(DiffshegError, match="seed"):
        check_seed(seed)
    sampler = Foppas(Schedule.linear(), PRESETS["official-beat"], 34, 4)
    make = lambda cond: lambda x, i: np.zeros_like(x)
    with pytest.raises(DiffshegError, match="seed"):
        sample_long(sampler, make, conditioning(np.zeros((40, 1), np.float32)), seed)
    with pytest.raises(DiffshegError, match="seed"):
        FoppasStream(sampler, make, seed)
    with pytest.raises(DiffshegError, match="seed"):
        generate(np.zeros(16000, np.float32), 16000, model=model, seed=seed)


def test_a_seed_gives_the_same_motion_on_either_backend(data_dir, tmp_path, model):
    """Same seed, same noise, whichever backend predicts it: onnxruntime and torch agree
    (within float32 rounding) on real speech over several windows, with a gesture prior."""
    rng = np.random.default_rng(5)
    walk = np.cumsum(rng.standard_normal((400, model.config.gesture_dim)), axis=0) * 0.1
    bundle = replace(model, prior=GesturePrior.fit([walk - walk.mean(0)], model.config.gesture_dim, 34))
    path = cut(data_dir, tmp_path, 110)  # windows 34 + 30 + 30 + a short last one
    runs = {backend: generate(path, model=bundle, seed=11, backend=backend, device="cpu")
            for backend in ("onnx", "torch")}
    onnx_run, torch_run = runs["onnx"], runs["torch"]
    assert onnx_run.meta["backend"] == "onnx" and torch_run.meta["backend"] == "torch"
    assert onnx_run.meta["prior_start"] and onnx_run.n_frames == torch_run.n_frames == 110
    # measured: 5e-5 on rotations of up to 20 (the random network drifts far from the rest pose)
    assert np.abs(onnx_run.rotations - torch_run.rotations).max() <= 1e-3
    assert np.abs(onnx_run.face - torch_run.face).max() <= 1e-3
    other = generate(path, model=bundle, seed=12, backend="torch", device="cpu")
    assert np.abs(other.rotations - torch_run.rotations).max() > 100 * 1e-3  # the seed does matter


def test_best_of_n_keeps_the_candidate_that_continues_the_motion():
    """A toy model that knows each candidate's target: candidate k continues the known tail
    with a jump of size k at the seam (candidate 2 none). The selection keeps candidate 2."""
    from diffsheg_core.foppas import Noise, seam_scores

    config = FoppasConfig(overlap=4, blend=False, candidates=4, jump_length=1, jump_n_sample=1)
    sampler = Foppas(Schedule.linear(), config, 34, 3)
    sched = sampler.schedule
    ramp = np.linspace(0.0, 1.0, 34, dtype=np.float32)[:, None] * np.ones(3, np.float32)
    known = ramp[None, :4]
    jumps = np.array([3.0, 1.0, 0.0, 2.0], np.float32)
    targets = np.stack([np.concatenate([ramp[:4], ramp[4:] + j]) for j in jumps])

    def eps_fn(x, index):
        a, b = sched.x0_coefs(np.full(len(x), index), x)
        return (a * x - targets[: len(x)]) / b

    window = sampler.sample_window(eps_fn, 34, known, Noise(0))
    assert window.shape == (1, 34, 3)
    np.testing.assert_allclose(window[0, 4:], targets[2, 4:], atol=1e-3)
    scores = seam_scores(targets, known)
    assert int(np.argmin(scores)) == 2 and list(np.argsort(scores)) == [2, 1, 3, 0]

    refined_rows = []

    def refining_eps_fn(x, index, refine=False):
        if refine:
            refined_rows.append(len(x))
        return eps_fn(x, index)

    refining = Foppas(Schedule.linear(), replace(config, refine=1), 34, 3)
    assert refining.sample_window(refining_eps_fn, 34, known, Noise(0)).shape == (1, 34, 3)
    assert refined_rows == [1]  # the refining pass runs on the chosen candidate alone


def test_best_of_n_is_recorded_changes_only_later_windows_and_keeps_a_fixed_face(model, data_dir):
    from diffsheg_core.audio import Audio

    speech = load_audio(data_dir / "audio" / "2_scott_0_4_4.wav")
    speech = Audio(speech.samples[: 6 * speech.sample_rate], speech.sample_rate)
    one = generate(speech, model=model, steps=3, seed=2, face_seed=5)
    four = generate(speech, model=model, steps=3, seed=2, face_seed=5, candidates=4)
    assert one.meta["candidates"] == 1 and four.meta["candidates"] == 4
    first = model.config.clip_len - model.sampling.overlap
    assert np.array_equal(one.rotations[:first], four.rotations[:first])
    assert not np.allclose(one.rotations[first:], four.rotations[first:])
    assert np.array_equal(one.face, four.face)  # every candidate had the face seed's face
    for bad in (0, 17, 2.5):
        with pytest.raises(DiffshegError, match="candidates must be a whole number from 1 to 16"):
            generate(speech, model=model, steps=3, candidates=bad)


# ---------------------------------------------------------------- the fast sampling

def test_the_fast_sampling_steps_at_its_own_timesteps_and_keeps_the_models_settings():
    """`fast_sampling` of a model's settings: five steps at FAST_TIMESTEPS (the schedule's
    model timesteps), later windows' gestures from the third step and the face from the top
    (deterministic), no RePaint jumps, the refining pass at the lowest step, the prior's draws
    1.2x as wide; the rest (carry, the prior, eta, refine_skip) as the model has them. --steps N
    gives N even steps."""
    from diffsheg_core.foppas import FAST_PRIOR_SPREAD, FAST_TIMESTEPS, fast_sampling, sampling_settings

    model = replace(PRESETS["no-resample"], eta=1.0, carry=12, refine=1, refine_skip=3.5)
    fast = fast_sampling(model)
    assert fast.timesteps == FAST_TIMESTEPS and fast.steps == len(FAST_TIMESTEPS)
    assert (fast.later_start, fast.face_start, fast.face_eta, fast.refine) == (2, 4, 0.0, 0)
    assert (fast.eta, fast.carry, fast.refine_skip, fast.prior_start) == (1.0, 12, 3.5, True)
    assert fast.prior_spread == FAST_PRIOR_SPREAD == 1.2 and model.prior_spread == 1.0  # the fast steps' draws wider
    assert list(Foppas(Schedule.linear(), fast, 34, 4).schedule.timesteps) == list(FAST_TIMESTEPS)
    assert fast_sampling(replace(model, refine=None)).refine is None
    assert sampling_settings(model, "fast") == fast and sampling_settings(model, "quality") == model
    assert sampling_settings(model, "official-show") == PRESETS["official-show"]
    with pytest.raises(DiffshegError, match="unknown sampling 'slow': use fast, quality, official-beat"):
        sampling_settings(model, "slow")
    six = fast.with_steps(6)
    assert six.timesteps is None and six.steps == 6 and six.later_start == 2 and six.face_start == 5
    assert fast.with_steps(5) == fast
    # the settings survive a model file's JSON (a list comes back as the tuple)
    assert FoppasConfig(**json.loads(json.dumps(fast.__dict__))) == fast


@pytest.mark.parametrize("setting,match", [
    (dict(timesteps=(50, 300, 450)), "timesteps must be 5 whole numbers"),
    (dict(timesteps=(50, 300, 300, 650, 900)), "distinct, ascending"),
    (dict(timesteps=(50, 300, 450, 650, 1000)), "from 0 to 999"),
    (dict(timesteps=(50, 300, 450, 650, 900.0)), "whole numbers"),
    (dict(face_start=0), "face_start must be None"),
    (dict(face_start=5), "face_start must be None"),
    (dict(face_eta=1.5), "face_eta must be None"),
    (dict(prior_spread=0), "prior_spread must be a number above 0 and at most 4"),
    (dict(prior_spread=5.0), "prior_spread must be a number above 0"),
    (dict(prior_spread=True), "prior_spread must be a number"),
])
def test_bad_fast_settings_are_refused(setting, match):
    from diffsheg_core.foppas import fast_sampling

    config = replace(fast_sampling(PRESETS["no-resample"]), **setting)
    with pytest.raises(ValueError, match=match):
        config.check(34)


def test_a_later_windows_face_steps_first_alone_and_the_gestures_wait_at_their_start():
    """Above the gestures' start, a later window runs the expression branch alone
    (`face_only`) at the higher steps; the gesture channels it is given stay as they were
    drawn and are not stepped until the gestures' start; then every step is a full one."""
    from diffsheg_core.foppas import fast_sampling

    g, d = 3, 5
    config = replace(fast_sampling(PRESETS["no-resample"]), refine=None, eta=1.0)
    sampler = Foppas(Schedule.linear(), config, 34, d, gestures=g)
    calls, seen = [], []

    def eps_fn(x, index, refine=False, face_only=False):
        calls.append((index, face_only))
        seen.append(x[..., :g].copy())
        return np.full_like(x, 0.1)

    known = np.zeros((1, 4, d), np.float32)
    sampler.sample_window(eps_fn, 34, known, sampler.noise(0))
    assert calls == [(4, True), (3, True), (2, False), (1, False), (0, False)]
    assert np.array_equal(seen[0], seen[1]) and np.array_equal(seen[1], seen[2])
    calls.clear()
    sampler.sample_window(eps_fn, 34, None, sampler.noise(0))  # the first window: every step full
    assert calls == [(i, False) for i in range(4, -1, -1)]


def test_the_face_steps_alone_are_the_steps_a_joint_sampler_takes():
    """The expression branch never sees the gestures, so a face stepped alone above the
    gestures' start is the face a joint step would give: with an eps_fn whose face noise
    depends only on the face, a window's face with face_start is that of the same settings
    with the gestures starting at the top (to float rounding), for a deterministic face."""
    g, d = 3, 5
    base = replace(PRESETS["no-resample"], steps=5, timesteps=(50, 300, 450, 650, 900), later_start=4, eta=0.0,
                   prior_start=False)
    face_first = replace(base, later_start=1, face_start=4)

    def eps_fn(x, index, refine=False, face_only=False):
        out = np.zeros_like(x)
        out[..., g:] = np.tanh(x[..., g:]) * (1 + index) / 5
        out[..., :g] = 0.0 if face_only else np.sin(x[..., :g])
        return out

    known = np.ones((1, 4, d), np.float32)
    faces = [Foppas(Schedule.linear(), c, 34, d, gestures=g).sample_window(eps_fn, 34, known, Foppas(
        Schedule.linear(), c, 34, d, gestures=g).noise(3))[..., g:] for c in (base, face_first)]
    np.testing.assert_allclose(faces[0], faces[1], atol=1e-5)
