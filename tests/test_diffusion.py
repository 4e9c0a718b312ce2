"""Schedule, DDIM and DDPM arithmetic."""

import numpy as np
import pytest
import torch

from diffsheg_core.diffusion import Schedule


def test_respaced_25_steps_are_every_40th():
    assert Schedule.linear().respaced(25).timesteps.tolist() == list(range(0, 1000, 40))


def test_respacing_keeps_alphas_cumprod_of_the_kept_steps():
    full, sub = Schedule.linear(), Schedule.linear().respaced(50)
    assert np.array_equal(sub.alphas_cumprod, full.alphas_cumprod[sub.timesteps])
    assert np.allclose(np.cumprod(1 - sub.betas), sub.alphas_cumprod)


@pytest.mark.parametrize("steps", [1, 7, 30, 999, 1000])
def test_respacing_gives_exactly_the_requested_count(steps):
    assert len(Schedule.linear().respaced(steps)) == steps


def test_linear_betas_match_the_official_schedule():
    betas = Schedule.linear().betas
    assert betas[0] == pytest.approx(1e-4) and betas[-1] == pytest.approx(0.02)


def toy_eps(x_t, index, schedule, target):
    """A toy model that knows the data point `target`: exact noise for it."""
    a, b = schedule.x0_coefs(torch.tensor([index]), x_t)
    return (a * x_t - target) / b


def test_ddim_with_1000_steps_and_eta_1_follows_the_ddpm_mean_path():
    sched = Schedule.linear()
    gen = torch.Generator().manual_seed(0)
    target = torch.randn(1, 6, 3, generator=gen)
    x_ddim = x_ddpm = torch.randn(1, 6, 3, generator=gen)
    for i in range(len(sched) - 1, -1, -1):
        noise = torch.randn(1, 6, 3, generator=gen)
        x_ddim, x0 = sched.ddim_step(x_ddim, i, toy_eps(x_ddim, i, sched, target), eta=1.0, noise=noise)
        mean = sched.ddpm_posterior_mean(x_ddpm, i, sched.predict_x0(
            x_ddpm, torch.tensor([i]), toy_eps(x_ddpm, i, sched, target)))
        x_ddpm = mean + (sched.ddpm_posterior_std(i) * noise if i > 0 else 0)
        assert torch.allclose(x_ddim, x_ddpm, atol=1e-4), i
    assert torch.allclose(x_ddim, target, atol=1e-4)


def test_predict_x0_inverts_exact_noise():
    sched = Schedule.linear()
    x, target = torch.randn(1, 4, 2), torch.randn(1, 4, 2)
    i = 500
    eps = toy_eps(x, i, sched, target)
    x0 = sched.predict_x0(x, torch.tensor([i]), eps)
    assert torch.allclose(x0, target, atol=1e-4)


def test_deterministic_ddim_25_recovers_the_data_point():
    sched = Schedule.linear().respaced(25)
    target = torch.randn(1, 5, 4)
    x = torch.randn(1, 5, 4)
    for i in range(24, -1, -1):
        x, _ = sched.ddim_step(x, i, toy_eps(x, i, sched, target))
    assert torch.allclose(x, target, atol=1e-4)


def test_q_sample_at_index_zero_is_almost_clean():
    sched = Schedule.linear()
    x0, noise = torch.ones(1, 3, 2), torch.randn(1, 3, 2)
    xt = sched.q_sample(x0, torch.tensor([0]), noise)
    assert torch.allclose(xt, x0, atol=0.05)
