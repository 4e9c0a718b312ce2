"""Schedule, DDIM and DDPM arithmetic, on numpy arrays (sampling) and torch tensors (training)."""

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


class Numpy:
    """float32 numpy arrays and numpy indices: what the sampler passes."""

    name = "numpy"

    def __init__(self, seed=0):
        self.gen = np.random.default_rng(seed)

    def randn(self, *shape):
        return self.gen.standard_normal(shape, dtype=np.float32)

    def ones(self, *shape):
        return np.ones(shape, np.float32)

    def index(self, i):
        return np.array([i])

    @staticmethod
    def allclose(a, b, atol):
        assert isinstance(a, np.ndarray) and a.dtype == np.float32  # no silent float64 upcast
        return np.allclose(a, b, rtol=1e-5, atol=atol)


class Torch:
    """float32 torch tensors and torch indices: what the trainer passes."""

    name = "torch"

    def __init__(self, seed=0):
        self.gen = torch.Generator().manual_seed(seed)

    def randn(self, *shape):
        return torch.randn(*shape, generator=self.gen)

    def ones(self, *shape):
        return torch.ones(*shape)

    def index(self, i):
        return torch.tensor([i])

    @staticmethod
    def allclose(a, b, atol):
        assert isinstance(a, torch.Tensor) and a.dtype == torch.float32
        return torch.allclose(a, b, atol=atol)


@pytest.fixture(params=[Numpy, Torch], ids=["numpy", "torch"])
def xp(request):
    return request.param()


def toy_eps(x_t, index, schedule, target, xp):
    """A toy model that knows the data point `target`: exact noise for it."""
    a, b = schedule.x0_coefs(xp.index(index), x_t)
    return (a * x_t - target) / b


def test_coefficients_come_back_as_the_kind_of_array_they_multiply(xp):
    sched = Schedule.linear().respaced(25)
    x = xp.randn(1, 4, 3)
    a, b = sched.x0_coefs(xp.index(10), x)
    assert type(a) is type(x) and a.dtype == x.dtype and tuple(a.shape) == (1, 1, 1)
    assert float(a.reshape(-1)[0]) == pytest.approx(np.sqrt(1.0 / sched.alphas_cumprod[10]), rel=1e-6)
    assert float(b.reshape(-1)[0]) == pytest.approx(np.sqrt(1.0 / sched.alphas_cumprod[10] - 1.0), rel=1e-6)
    steps = sched.model_timesteps(xp.index(10))
    assert type(steps) is type(x) and steps.tolist() == [400]
    assert sched.model_timesteps(10).tolist() == [400]  # a plain int too


def test_ddim_with_1000_steps_and_eta_1_follows_the_ddpm_mean_path(xp):
    sched = Schedule.linear()
    target = xp.randn(1, 6, 3)
    x_ddim = x_ddpm = xp.randn(1, 6, 3)
    for i in range(len(sched) - 1, -1, -1):
        noise = xp.randn(1, 6, 3)
        x_ddim, x0 = sched.ddim_step(x_ddim, i, toy_eps(x_ddim, i, sched, target, xp), eta=1.0, noise=noise)
        mean = sched.ddpm_posterior_mean(x_ddpm, i, sched.predict_x0(
            x_ddpm, xp.index(i), toy_eps(x_ddpm, i, sched, target, xp)))
        x_ddpm = mean + (sched.ddpm_posterior_std(i) * noise if i > 0 else 0)
        assert xp.allclose(x_ddim, x_ddpm, atol=1e-4), i
    assert xp.allclose(x_ddim, target, atol=1e-4)


def test_predict_x0_inverts_exact_noise(xp):
    sched = Schedule.linear()
    x, target = xp.randn(1, 4, 2), xp.randn(1, 4, 2)
    i = 500
    eps = toy_eps(x, i, sched, target, xp)
    x0 = sched.predict_x0(x, xp.index(i), eps)
    assert xp.allclose(x0, target, atol=1e-4)


def test_deterministic_ddim_25_recovers_the_data_point(xp):
    sched = Schedule.linear().respaced(25)
    target = xp.randn(1, 5, 4)
    x = xp.randn(1, 5, 4)
    for i in range(24, -1, -1):
        x, _ = sched.ddim_step(x, i, toy_eps(x, i, sched, target, xp))
    assert xp.allclose(x, target, atol=1e-4)


def test_q_sample_at_index_zero_is_almost_clean(xp):
    sched = Schedule.linear()
    x0, noise = xp.ones(1, 3, 2), xp.randn(1, 3, 2)
    xt = sched.q_sample(x0, xp.index(0), noise)
    assert xp.allclose(xt, x0, atol=0.05)
