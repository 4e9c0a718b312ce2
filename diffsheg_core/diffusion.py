"""Noise schedule and the DDIM / DDPM update rules, kept apart from any model.

`Schedule` is the 1000-step linear-beta diffusion the model is trained on.
`Schedule.respaced(n)` gives the n-step sub-schedule DDIM samples with (the official
"ddimN" spacing: every 1000 // n-th step, so 25 steps use t in {0, 40, ..., 960}).
All arithmetic on the schedule is done in float64, as in the reference code. The update
rules take numpy arrays (sampling) or torch tensors (training) alike: coefficients come
back as the type, dtype and device of the array they multiply, and nothing here imports
torch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def linear_betas(num_steps: int = 1000, beta_start: float = 1e-4, beta_end: float = 0.02) -> np.ndarray:
    scale = 1000.0 / num_steps
    return np.linspace(scale * beta_start, scale * beta_end, num_steps, dtype=np.float64)


def _indices(index) -> np.ndarray:
    """Schedule indices as a numpy array, from an int, a numpy array or a torch tensor."""
    return np.asarray(index.cpu() if hasattr(index, "cpu") else index).reshape(-1)


def _gather(values: np.ndarray, index, like):
    """values[index] shaped (B, 1, 1, ...) to broadcast against `like`, as its kind of array."""
    out = values[_indices(index)].reshape(-1, *([1] * (like.ndim - 1)))
    if hasattr(like, "new_tensor"):  # a torch tensor: same dtype and device
        return like.new_tensor(out)
    return out.astype(like.dtype)


@dataclass(frozen=True)
class Schedule:
    """A diffusion schedule over `timesteps` (original 1000-step indices, ascending).

    Index i of this schedule is the model's timestep `timesteps[i]`; `alphas_cumprod[i]`
    is abar at that step and `betas[i] = 1 - abar[i] / abar[i-1]`.
    """

    alphas_cumprod: np.ndarray
    timesteps: np.ndarray

    @classmethod
    def linear(cls, num_steps: int = 1000, beta_start: float = 1e-4, beta_end: float = 0.02) -> "Schedule":
        abar = np.cumprod(1.0 - linear_betas(num_steps, beta_start, beta_end))
        return cls(alphas_cumprod=abar, timesteps=np.arange(num_steps))

    def __len__(self) -> int:
        return len(self.timesteps)

    @property
    def betas(self) -> np.ndarray:
        prev = np.append(1.0, self.alphas_cumprod[:-1])
        return 1.0 - self.alphas_cumprod / prev

    @property
    def alphas_cumprod_prev(self) -> np.ndarray:
        return np.append(1.0, self.alphas_cumprod[:-1])

    def respaced(self, steps: int) -> "Schedule":
        """The `steps`-step sub-schedule (official 'ddim<steps>' spacing)."""
        n = len(self)
        if not 1 <= steps <= n:
            raise ValueError(f"diffusion steps must be between 1 and {n}, got {steps}")
        keep = next((np.arange(0, n, stride) for stride in range(1, n + 1) if -(-n // stride) == steps),
                    None)
        if keep is None:  # no even stride gives exactly `steps`: spread them as evenly as possible
            keep = np.unique(np.round(np.linspace(0, n - 1, steps)).astype(np.int64))
        return Schedule(alphas_cumprod=self.alphas_cumprod[keep], timesteps=self.timesteps[keep])

    def at(self, timesteps) -> "Schedule":
        """The sub-schedule at the given timesteps of this one (ascending, distinct): a few-step
        sampler's own spacing rather than the even 'ddim<steps>' one."""
        keep = np.asarray(timesteps, dtype=np.int64)
        if keep.ndim != 1 or not len(keep) or np.any(np.diff(keep) <= 0) or keep[0] < 0 or keep[-1] >= len(self):
            raise ValueError(f"timesteps must be distinct, ascending and from 0 to {len(self) - 1}, "
                             f"got {list(np.asarray(timesteps).tolist())}")
        return Schedule(alphas_cumprod=self.alphas_cumprod[keep], timesteps=self.timesteps[keep])

    def model_timesteps(self, index):
        """Original-indexing timesteps the model is conditioned on, for schedule indices
        (an array of the same kind as `index`)."""
        steps = self.timesteps[_indices(index)]
        return index.new_tensor(steps) if hasattr(index, "new_tensor") else steps

    def x0_coefs(self, index, like):
        """sqrt(1/abar) and sqrt(1/abar - 1) at `index`: x0 = a * x_t - b * eps."""
        abar = self.alphas_cumprod
        return (_gather(np.sqrt(1.0 / abar), index, like), _gather(np.sqrt(1.0 / abar - 1.0), index, like))

    def predict_x0(self, x_t, index, eps):
        a, b = self.x0_coefs(index, x_t)
        return a * x_t - b * eps

    def q_sample(self, x0, index, noise):
        """Sample x_t ~ q(x_t | x0)."""
        abar = self.alphas_cumprod
        return _gather(np.sqrt(abar), index, x0) * x0 + _gather(np.sqrt(1.0 - abar), index, x0) * noise

    def noise_level_prev(self, i: int) -> float:
        """sqrt(1 - abar) of the level a step from index i lands on."""
        return float(np.sqrt(1.0 - self.alphas_cumprod_prev[i]))

    def ddim_step(self, x_t, i: int, eps, eta: float = 0.0, noise=None) -> tuple:
        """One DDIM update from index i to i-1. Returns (x_{i-1}, predicted x0).

        eta = 0 is the deterministic DDIM path; eta = 1 has DDPM's posterior mean and
        variance. x0 is not clipped.
        """
        x0 = self.predict_x0(x_t, np.full(x_t.shape[0], i), eps)
        abar, abar_prev = self.alphas_cumprod[i], self.alphas_cumprod_prev[i]
        sigma = eta * np.sqrt((1 - abar_prev) / (1 - abar)) * np.sqrt(1 - abar / abar_prev)
        # eps re-derived from the x0 estimate, as the reference implementation does
        eps = (float(np.sqrt(1.0 / abar)) * x_t - x0) / float(np.sqrt(1.0 / abar - 1.0))
        mean = float(np.sqrt(abar_prev)) * x0 + float(np.sqrt(1 - abar_prev - sigma ** 2)) * eps
        if sigma > 0 and i > 0:
            mean = mean + float(sigma) * noise
        return mean, x0

    def ddpm_posterior_mean(self, x_t, i: int, x0):
        """Mean of q(x_{i-1} | x_i, x0): the DDPM update without its noise."""
        beta = self.betas[i]
        abar, abar_prev = self.alphas_cumprod[i], self.alphas_cumprod_prev[i]
        c0 = beta * np.sqrt(abar_prev) / (1.0 - abar)
        ct = (1.0 - abar_prev) * np.sqrt(1.0 - beta) / (1.0 - abar)
        return float(c0) * x0 + float(ct) * x_t

    def ddpm_posterior_std(self, i: int) -> float:
        abar, abar_prev = self.alphas_cumprod[i], self.alphas_cumprod_prev[i]
        return float(np.sqrt(self.betas[i] * (1.0 - abar_prev) / (1.0 - abar)))

    def renoise(self, x, beta_index: int, noise):
        """One forward diffusion step with the beta at `beta_index`: going from index i to
        i + 1 is exact with beta_index = i + 1 (the reference sampler uses i)."""
        beta = float(self.betas[beta_index])
        return float(np.sqrt(1.0 - beta)) * x + float(np.sqrt(beta)) * noise
