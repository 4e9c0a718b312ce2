"""A Gaussian prior over gesture motion, used to start later FOPPAS windows.

FOPPAS starts every window after the first part-way down the schedule (`later_start`).
From pure noise there, the network reads the window as sitting at the mean pose (at high
noise it barely uses what little signal x_t holds), so each window pulls the posture
back toward the mean and the take's gestures drift less, and move less, than a real
speaker's. Started instead from a draw of this prior, conditioned on the overlap frames
and noised to the start level, the network has a plausible continuation to refine.

The prior is stationary: the gesture channels are rotated onto the principal axes of
their covariance, and each axis is a Gaussian process with its own temporal
autocovariance. It is fitted to the normalised training motion and stored with the model
(about 25 000 numbers). All numpy, float64 inside.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from .errors import CheckpointError, DiffshegError

PREFIX = "prior."


@dataclass
class GesturePrior:
    mean: np.ndarray      # (G,) mean of the normalised gesture channels
    axes: np.ndarray      # (G, G) orthonormal principal axes, one per column
    autocov: np.ndarray   # (G, L) autocovariance of each axis at lags 0 .. L-1
    _conditionals: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def dims(self) -> int:
        return self.mean.shape[0]

    @property
    def max_len(self) -> int:
        return self.autocov.shape[1]

    @classmethod
    def fit(cls, takes: Iterable[np.ndarray], dims: int, max_len: int) -> "GesturePrior":
        """Fit to normalised (T, >= dims) motion arrays, using their first `dims` channels."""
        series = [np.asarray(t[:, :dims], np.float64) for t in takes if len(t) >= max_len]
        if not series:
            raise DiffshegError(f"no take is {max_len} frames long: cannot fit the gesture prior")
        frames = np.concatenate(series)
        mean = frames.mean(0)
        _, axes = np.linalg.eigh(np.cov(frames - mean, rowvar=False))
        autocov = np.zeros((dims, max_len))
        for take in series:
            y = (take - mean) @ axes
            for lag in range(max_len):
                autocov[:, lag] += (y[lag:] * y[: len(y) - lag]).sum(0)
        autocov /= len(frames)  # the biased estimate, which keeps the covariance positive
        # rounded to the float32 it is stored in, so a saved model samples as the fitted one
        return cls(*(a.astype(np.float32).astype(np.float64) for a in (mean, axes, autocov)))

    def beside(self, other: "GesturePrior") -> "GesturePrior":
        """This prior's channels, then `other`'s, drawn apart (block-diagonal axes): a model
        widened with channels of a branch of their own keeps its source's prior for its own."""
        if other.max_len != self.max_len:
            raise DiffshegError(f"gesture priors over {self.max_len} and {other.max_len} frames cannot be joined")
        axes = np.zeros((self.dims + other.dims,) * 2)
        axes[:self.dims, :self.dims], axes[self.dims:, self.dims:] = self.axes, other.axes
        return GesturePrior(np.concatenate([self.mean, other.mean]), axes, np.concatenate([self.autocov, other.autocov]))

    def propose(self, known: np.ndarray, length: int, generator: np.random.Generator,
                spread: float = 1.0) -> np.ndarray:
        """A (length, dims) draw of the gesture channels whose first frames are those of
        `known` (n, >= dims), n < length <= max_len; `spread` scales the new frames' deviation
        from their mean given the known ones (1: the fitted prior's)."""
        n = known.shape[0]
        if not 0 < n < length <= self.max_len:
            raise DiffshegError(f"the gesture prior continues 1 to {self.max_len - 1} known frames "
                                f"within {self.max_len}; asked for {n} of {length}")
        gain, scale = self._conditional(n, length)
        given = np.asarray(known[:, : self.dims], np.float64)
        y_known = ((given - self.mean) @ self.axes).T                                     # (G, n)
        z = generator.standard_normal((self.dims, length - n))
        y_new = gain @ y_known[..., None] + spread * (scale @ z[..., None])               # (G, m, 1)
        drawn = y_new[..., 0].T @ self.axes.T + self.mean
        return np.concatenate([given, drawn]).astype(known.dtype)

    def _conditional(self, n: int, length: int) -> tuple[np.ndarray, np.ndarray]:
        """Per axis, the gain from the known frames to the mean of the new ones and a
        square root of the new frames' covariance given the known ones."""
        key = (n, length)
        if key not in self._conditionals:
            lags = np.abs(np.arange(length)[:, None] - np.arange(length)[None, :])
            cov = self.autocov[:, lags]                                                   # (G, L, L)
            c_kk, c_kn, c_nn = cov[:, :n, :n], cov[:, :n, n:], cov[:, n:, n:]
            ridge = 1e-6 * self.autocov[:, :1, None] * np.eye(n)
            gain = np.linalg.solve(c_kk + ridge, c_kn).transpose(0, 2, 1)                # (G, m, n)
            values, vectors = np.linalg.eigh(c_nn - gain @ c_kn)
            self._conditionals[key] = (gain, vectors * np.sqrt(np.clip(values, 0, None))[:, None, :])
        return self._conditionals[key]

    def tensors(self) -> dict[str, np.ndarray]:
        return {f"{PREFIX}{k}": np.ascontiguousarray(getattr(self, k), np.float32)
                for k in ("mean", "axes", "autocov")}

    @classmethod
    def from_tensors(cls, tensors: dict[str, np.ndarray], source: str) -> "GesturePrior | None":
        """The prior stored in a checkpoint's tensors, or None if it holds none."""
        names = [f"{PREFIX}{k}" for k in ("mean", "axes", "autocov")]
        if not any(n in tensors for n in names):
            return None
        try:
            mean, axes, autocov = (np.asarray(tensors[n], np.float64) for n in names)
        except KeyError as exc:
            raise CheckpointError(f"{source}: the gesture prior is incomplete (no {exc}); export it again") from None
        g = mean.shape[0]
        if axes.shape != (g, g) or autocov.ndim != 2 or autocov.shape[0] != g:
            raise CheckpointError(f"{source}: the gesture prior's shapes do not fit together "
                                f"(mean {tuple(mean.shape)}, axes {tuple(axes.shape)}, "
                                f"autocov {tuple(autocov.shape)}); export it again")
        return cls(mean, axes, autocov)
