"""FOPPAS windowing, outpainting and streaming, on real speech and synthetic models."""

import json

import numpy as np
import pytest
import soundfile as sf
import torch

from diffsheg_core.audio import load_audio, n_motion_frames
from diffsheg_core.checkpoints import untrained_bundle
from diffsheg_core.diffusion import Schedule
from diffsheg_core.foppas import (Foppas, FoppasConfig, FoppasStream, PRESETS, jump_schedule,
                                  model_calls, plan_windows, sample_long)
from diffsheg_core.pipeline import generate

CPU = torch.device("cpu")


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
    stream = FoppasStream(sampler, lambda cond: lambda x, i: counts.append(i) or torch.zeros_like(x),
                          torch.Generator().manual_seed(0), CPU)
    stream.push(torch.zeros(34 + 30 + 30, 1))
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
    return untrained_bundle()


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
        windows.append(out[0].clone())
        return out

    sampler.sample_window = recording
    motion = sample_long(sampler, make_eps_fn, torch.zeros(n_frames, 1), torch.Generator().manual_seed(seed), CPU)
    return motion, windows


def test_overlap_equals_previous_tail_exactly_without_blending(model):
    cfg = model.config
    sampler = Foppas(Schedule.linear(), FoppasConfig(steps=10, overlap=4, later_start=6, blend=False),
                     cfg.clip_len, cfg.dim)
    from diffsheg_core.pipeline import make_eps_fn_factory, style_onehot
    make = make_eps_fn_factory(model, sampler, style_onehot(model, 0), None, None)
    cond = torch.rand(100, cfg.mel_dim)
    windows = []
    original = sampler.sample_window
    sampler.sample_window = lambda *a, **k: windows.append(original(*a, **k)[0].clone()) or windows[-1][None]
    motion = sample_long(sampler, make, cond, torch.Generator().manual_seed(1), CPU)
    assert len(windows) == 4
    for prev, nxt in zip(windows, windows[1:]):
        assert torch.equal(nxt[:4], prev[-4:])
    assert torch.equal(motion[:30], windows[0][:30]) and torch.equal(motion[30:60], windows[1][:30])


def smooth_model():
    """The exact denoiser for smooth random motion: x0 drawn from a Gaussian process
    with a squared-exponential kernel (length 4 frames), so E[x0 | x_t] is linear."""
    sched = Schedule.linear().respaced(25)

    def make(cond):
        t = cond[0, :, 0]
        k = torch.exp(-0.5 * ((t[:, None] - t[None, :]) / 4.0) ** 2).double()
        eye = torch.eye(len(t), dtype=torch.float64)

        def eps(x, index):
            a, b = sched.x0_coefs(torch.tensor([index]), x)
            abar = float(1.0 / a.flatten()[0] ** 2)
            gain = abar ** 0.5 * k @ torch.linalg.inv(abar * k + (1 - abar) * eye + 1e-6 * eye)
            x0 = (gain @ x[0].double()).float()[None]
            return (a * x - x0) / b

        return eps

    return make


def seam_and_inside_steps(blend):
    sampler = Foppas(Schedule.linear(), FoppasConfig(overlap=4, blend=blend), 34, 2)
    frames = torch.arange(300, dtype=torch.float32).view(-1, 1)
    motion = sample_long(sampler, smooth_model(), frames, torch.Generator().manual_seed(0), CPU)
    steps = (motion[1:, 0] - motion[:-1, 0]).abs()
    seams = {s for start, _ in plan_windows(300, 34, 4)[1:] for s in range(start - 1, start + 4)}
    inside = [i for i in range(len(steps)) if i not in seams]
    return steps[sorted(seams)], steps[inside]


def test_blending_keeps_clip_boundaries_as_smooth_as_the_clips():
    seams, inside = seam_and_inside_steps(blend=True)
    assert seams.max() <= inside.max()
    unblended, _ = seam_and_inside_steps(blend=False)
    assert unblended.max() > seams.max()


def test_stream_equals_offline_and_emits_early(model):
    cfg = model.config
    from diffsheg_core.pipeline import make_eps_fn_factory, style_onehot
    cond = torch.rand(150, cfg.mel_dim)
    conf = FoppasConfig(steps=4, later_start=2)

    def sampler():
        return Foppas(Schedule.linear(), conf, cfg.clip_len, cfg.dim)

    s = sampler()
    make = make_eps_fn_factory(model, s, style_onehot(model, 0), None, None)
    offline = sample_long(s, make, cond, torch.Generator().manual_seed(3), CPU)
    stream = FoppasStream(sampler(), make, torch.Generator().manual_seed(3), CPU)
    parts, emitted_after = [], []
    for start in range(0, 150, 10):
        parts.append(stream.push(cond[start:start + 10]))
        emitted_after.append(sum(len(p) for p in parts))
    parts.append(stream.finish())
    streamed = torch.cat(parts)
    assert torch.equal(streamed, offline)
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

    def proposal(known: torch.Tensor, length: int, generator: torch.Generator) -> torch.Tensor:
        calls.append((tuple(known.shape), length))
        return torch.full((length, 4), 50.0)

    def first_inputs(sampler: Foppas) -> list[float]:
        means = []

        def make(cond):
            seen = []

            def eps_fn(x, index):
                if not seen:
                    seen.append(True)
                    means.append(float(x[0, config.overlap:].mean()))
                return torch.zeros_like(x)
            return eps_fn
        sample_long(sampler, make, torch.zeros(34 + 30 + 20, 1), torch.Generator().manual_seed(0), CPU)
        return means

    with_draw = first_inputs(Foppas(Schedule.linear(), config, 34, 4, proposal=proposal))
    assert calls == [((config.overlap, 4), 34), ((config.overlap, 4), 24)]  # the last window is short
    level = float(np.sqrt(Schedule.linear().respaced(config.steps).alphas_cumprod[config.start_index]))
    assert abs(with_draw[0]) < 0.5  # the first window: noise
    for mean in with_draw[1:]:
        assert abs(mean - 50.0 * level) < 0.5
    without = first_inputs(Foppas(Schedule.linear(), config, 34, 4))
    assert all(abs(m) < 0.5 for m in without)


def test_a_proposal_of_some_channels_leaves_the_others_noise_unchanged():
    """The proposal draws from its own generator: the channels it does not cover get the
    same noise as without it, so they come out the same."""
    config = PRESETS["official-beat"]

    def run(proposal) -> torch.Tensor:
        sampler = Foppas(Schedule.linear(), config, 34, 4, proposal=proposal)
        make = lambda cond: lambda x, i: 0.1 * x  # any model that treats the channels apart
        return sample_long(sampler, make, torch.zeros(80, 1), torch.Generator().manual_seed(3), CPU)

    def two_channels(known, length, generator):
        return torch.cat([known[:, :2], torch.randn(length - len(known), 2, generator=generator)])

    plain, proposed = run(None), run(two_channels)
    assert torch.equal(plain[:, 2:], proposed[:, 2:])
    assert torch.equal(plain[:30, :2], proposed[:30, :2])  # the first window has no proposal
    assert not torch.allclose(plain[30:, :2], proposed[30:, :2])
