"""FOPPAS: fast outpainting-based partial autoregressive sampling (DiffSHEG, Algorithm 1).

Long motion is sampled in windows of `clip_len` frames that overlap by `overlap`
frames. The first window is plain DDIM. In every later window the overlap frames
are fixed to the previous window's tail by RePaint masking at every step (the known
frames re-noised to the level of the step), with RePaint's resampling jumps, and
during the last steps the known overlap is cross-faded linearly into the generated
one. A shorter last window runs at its own length.

Replacement alone leaves a seam: early in a window the network's picture of the heavily
noised overlap is far from the known frames, the new frames are drawn to continue that
picture, and at low noise they can no longer move. With `carry` > 0, at every step the
gap between the known last overlap frame and the network's x0 for it is added to the
gestures' x0 of the new frames, fading out over `carry` frames (a raised cosine), before
the step is taken; see `carry_overlap`. The face keeps plain replacement: carried there
it made blinks rarer and the mouth follow the speech envelope less.

A later window starts at `later_start` from pure noise, as in the paper, or, given a
`Proposal`, from a draw that continues the overlap, noised to that level (see prior.py).

The fast wobble a small network leaves in its gestures builds up along the sampling path;
its own denoiser, shown the finished window as if it were still noisy, removes it. With
`refine` set, each finished window is passed through the network once more as if at that
schedule index (no noise is added), and the gestures are replaced by its x0; the face is
kept as sampled. `refine_skip` scales that pass's gesture skip guidance (see
`EpsFn`), which brings back the amplitude the denoising takes off.

Any frames and channels of a window can be held too (`Fixed`): they are painted in at
every step like the overlap, re-noised to the step's level, and are exact at the end.
`inpaint_range` samples a range of a finished motion anew this way, between the frames
before it (the known overlap) and after it (held): the animator's "regenerate this range".

The sampler is model-agnostic: it calls `eps_fn(x_t, index)` for a window, where
`index` is the step in the respaced schedule, and `make_eps_fn` makes that function of a
window's `Conditioning` (`Conditioning.frames`). `FoppasStream` takes conditioning
frames as they arrive and returns motion frames as soon as they are final.

Everything here is numpy, float32 motion: the noise comes from numpy's PCG64 generator
seeded with the sampling seed, so a seed gives the same noise whichever backend
(onnxruntime or torch, CPU or GPU) predicts it.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from typing import Callable, Optional, Protocol

import numpy as np

from .conditioning import Conditioning
from .diffusion import Schedule
from .errors import DiffshegError
from .progress import Progress, ProgressCallback, check_cancel
from .validate import CANDIDATES, check_seed

PROPOSAL_STREAM = 0x5EED0F9A0D  # the proposal's generator is seeded with (seed, this)
FACE_STREAM = 0xFACE5EED  # the face's generator is seeded with (face_seed, this)
BRANCH_STREAM = 0xB4A9C5  # a lower branch's channels: generators seeded with (seed, this[, PROPOSAL_STREAM])
SEAM_FRAMES = 5  # frames either side of a seam that best-of-N selection compares
HOLD_CARRY = 16  # frames at least that a held value's gap is carried into (a pin flows in and out)
MAX_PRIOR_SPREAD = 4.0  # FoppasConfig.prior_spread's upper bound: beyond it a draw is no longer the prior's

class EpsFn(Protocol):
    """(x_t of shape (B, L, D), schedule index) -> predicted noise (B, L, D). Only the
    refining pass passes `refine=True` (a guided model then multiplies its gesture
    skip-guidance scale by `FoppasConfig.refine_skip`, see pipeline.make_eps_fn_factory), and
    only a later window's face-first steps (`FoppasConfig.face_start`) pass `face_only=True`
    (only the face channels of the result are used: the expression branch alone runs), so a
    function of (x, index) serves a sampler without them."""

    def __call__(self, x: np.ndarray, index: int, refine: bool = False, face_only: bool = False
                 ) -> np.ndarray: ...

Proposal = Callable[[np.ndarray, int, np.random.Generator], np.ndarray]
"""(known overlap frames (n, D), window length, generator) -> a (length, C) draw of the
first C <= D channels; the others start from pure noise as without a proposal."""


@dataclass(frozen=True)
class FoppasConfig:
    """Sampling settings. The defaults are the official BEAT inference settings."""

    steps: int = 25                    # DDIM steps of the respaced schedule
    overlap: int = 4                   # frames shared by consecutive windows
    later_start: Optional[int] = 14    # schedule index later windows start from (None: steps - 1)
    jump_length: int = 3               # RePaint: steps gone back up per jump
    jump_n_sample: int = 2             # RePaint: each jump point is passed this many times
    blend: bool = True                 # cross-fade the overlap during the last steps
    blend_below: float = 0.2           # ... those landing at noise level sqrt(1 - abar) below this
    reference_renoise: bool = True     # jump back with the beta of the current index, as the official code
    eta: float = 0.0                   # 0: deterministic DDIM
    branch_eta: Optional[float] = None  # the eta of a lower branch's channels (None: eta)
    face_eta: Optional[float] = None   # the eta of the face's channels (None: eta)
    prior_start: bool = True           # later windows start from the model's gesture prior, if it has one
    prior_spread: float = 1.0          # its spread about its mean, times the fitted one's (the model's prior draws so)
    candidates: int = 1                # later windows sampled this many times in one batch; the best continues
    carry: int = 0                     # frames the overlap's x0 gap is carried into (0: off, as the official code)
    refine: Optional[int] = None       # schedule index of a last pass over each window's gestures (None: off)
    refine_skip: float = 1.0           # that pass's skip-guidance scale, as a multiple of the steps'
    timesteps: Optional[tuple] = None  # the steps' model timesteps, ascending (None: the even 'ddim<steps>' spacing)
    face_start: Optional[int] = None   # schedule index a later window's face starts from (None: later_start)

    def __post_init__(self):
        if isinstance(self.timesteps, list):  # read back from a model file's JSON
            object.__setattr__(self, "timesteps", tuple(self.timesteps))

    def check(self, clip_len: int) -> None:
        """Raise ValueError naming any setting that cannot work with `clip_len`-frame windows."""
        if self.steps < 1:
            raise ValueError(f"diffusion steps must be at least 1, got {self.steps}")
        if not 0 <= self.overlap < clip_len:
            raise ValueError(
                f"overlap must be between 0 and {clip_len - 1} frames for {clip_len}-frame windows, "
                f"got {self.overlap}")
        if self.later_start is not None and not 0 <= self.later_start < self.steps:
            raise ValueError(
                f"later windows must start at a step index below {self.steps}, got {self.later_start}")
        if self.jump_length < 1 or self.jump_n_sample < 1:
            raise ValueError("jump_length and jump_n_sample must be at least 1")
        if isinstance(self.candidates, bool) or not isinstance(self.candidates, int) \
                or not CANDIDATES[0] <= self.candidates <= CANDIDATES[1]:
            raise ValueError(f"candidates must be a whole number from {CANDIDATES[0]} to {CANDIDATES[1]}, "
                             f"got {self.candidates!r}")
        if isinstance(self.carry, bool) or not isinstance(self.carry, int) or self.carry < 0:
            raise ValueError(f"carry must be a whole number of frames >= 0, got {self.carry!r}")
        if self.refine is not None and (isinstance(self.refine, bool) or not isinstance(self.refine, int)
                                        or not 0 <= self.refine < self.steps):
            raise ValueError(f"refine must be None (off) or a step index from 0 to {self.steps - 1}, "
                             f"got {self.refine!r}")
        for name in ("branch_eta", "face_eta"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not 0 <= value <= 1):
                raise ValueError(f"{name} must be None (eta) or a number from 0 to 1, got {value!r}")
        if self.timesteps is not None:
            values = self.timesteps
            if not isinstance(values, tuple) or len(values) != self.steps or not all(
                    isinstance(t, int) and not isinstance(t, bool) for t in values):
                raise ValueError(f"timesteps must be {self.steps} whole numbers, one per step, got {values!r}")
            Schedule.linear().at(values)  # ascending, distinct, in range: or a ValueError saying so
        if self.face_start is not None and (isinstance(self.face_start, bool) or not isinstance(self.face_start, int)
                                            or not self.start_index <= self.face_start < self.steps):
            raise ValueError(f"face_start must be None (later_start) or a step index from later_start "
                             f"({self.start_index}) to {self.steps - 1}, got {self.face_start!r}")
        if isinstance(self.refine_skip, bool) or not isinstance(self.refine_skip, (int, float)) \
                or not 0 <= self.refine_skip < float("inf"):
            raise ValueError(f"refine_skip must be a finite number >= 0, got {self.refine_skip!r}")
        if isinstance(self.prior_spread, bool) or not isinstance(self.prior_spread, (int, float)) \
                or not 0 < self.prior_spread <= MAX_PRIOR_SPREAD:
            raise ValueError(f"prior_spread must be a number above 0 and at most {MAX_PRIOR_SPREAD:g}, "
                             f"got {self.prior_spread!r}")

    def with_steps(self, steps: int) -> "FoppasConfig":
        """The same settings with `steps` DDIM steps; later windows keep starting, and the
        refining pass keeps running, at the same fraction of the schedule (official: later
        windows at index 14 of 25)."""

        def rescale(index: Optional[int]) -> Optional[int]:
            if index is None or self.steps <= 1:
                return index
            return min(steps - 1, round(index * (steps - 1) / (self.steps - 1)))

        if steps == self.steps:
            return self
        return replace(self, steps=steps, later_start=rescale(self.later_start), refine=rescale(self.refine),
                       face_start=rescale(self.face_start), timesteps=None)

    @property
    def start_index(self) -> int:
        return self.steps - 1 if self.later_start is None else self.later_start

    @property
    def face_index(self) -> int:
        """The schedule index a later window's face starts from (at or above `start_index`)."""
        return self.start_index if self.face_start is None else self.face_start

    def schedule(self, base: Schedule) -> Schedule:
        """The steps' sub-schedule of `base`: at `timesteps`, or evenly spaced."""
        return base.respaced(self.steps) if self.timesteps is None else base.at(self.timesteps)


PRESETS: dict[str, FoppasConfig] = {
    "official-beat": FoppasConfig(),
    "official-show": FoppasConfig(overlap=10),
    "official-beat-n5": FoppasConfig(jump_n_sample=5),
    "no-resample": FoppasConfig(jump_length=1, jump_n_sample=1),
}

FAST_TIMESTEPS = (50, 300, 450, 650, 900)
"""The fast sampling's steps (model timesteps), chosen with bench/bench_sampling.py on the
bundled model: the face steps at all five (the expression branch alone above the gestures'
start: five face steps keep its blinks, three lose nine in ten), the gestures at the lowest
three, from the gesture prior (from the lowest two their jitter on unseen speech was 1.17x the
25 steps'), low enough to leave no wobble after the refining pass (docs/foppas.md)."""

FAST_PRIOR_SPREAD = 1.2
"""The fast sampling's gesture prior draws, the hips' and legs' among them
(`FoppasConfig.prior_spread`, offline and live): its three gesture steps
calm a draw of the fitted spread (the gestures' window Fréchet distance to the capture 1.18x the
25 steps', wrist speed on unseen speech 0.94x). Over seeds 0-7 with the int8 student, 1.1x left
the window FD at 1.08x and diversity at 0.89-0.92x; 1.2x brings them to 0.93x / 0.91x (take /
held-out) and 0.93-0.98x, wrist speed 0.97-1.03x, jitter 1.00-1.05x; 1.3x overshoots (wrists
1.05-1.07x, jitter 1.08x) (bench/bench_sampling.py, 2026-12-06; docs/foppas.md)."""

SAMPLINGS = ("fast", "quality")
"""The named samplings: `fast` (the default) and `quality` (the model's own settings, 25 steps
for the bundled model); `sampling_settings` turns a name, or a preset's, into settings."""

SAMPLING_NAMES = SAMPLINGS + tuple(PRESETS)
"""Every name a sampling setting takes (`--sampling`, a manifest's column, the panel)."""


def fast_sampling(config: FoppasConfig) -> FoppasConfig:
    """A model's sampling settings `config` at FAST_TIMESTEPS: the first window from the top;
    a later window's gestures from the third step (from the gesture prior, continuing the
    overlap) and its face from the top, the face's steps above the gestures' running the
    expression branch alone (`face_start`) and deterministic (`face_eta` 0: with stochastic
    steps this few, the face loses its blinks); no RePaint jumps; the refining pass, if the
    model has one, at the lowest step; the gesture prior's draws FAST_PRIOR_SPREAD as wide. A
    later window costs three full network calls, two of the expression branch and the refining
    pass's gesture branch, instead of 18 and the pass."""
    return replace(config, steps=len(FAST_TIMESTEPS), timesteps=FAST_TIMESTEPS, later_start=2,
                   face_start=len(FAST_TIMESTEPS) - 1, face_eta=0.0, jump_length=1, jump_n_sample=1,
                   refine=None if config.refine is None else 0, prior_spread=FAST_PRIOR_SPREAD)


def sampling_settings(model_sampling: FoppasConfig, name: str) -> FoppasConfig:
    """The settings a sampling `name` means for a model whose own are `model_sampling`: `fast`,
    `quality` (the model's) or a preset (PRESETS, the official code's settings)."""
    if name == "fast":
        return fast_sampling(model_sampling)
    if name == "quality":
        return model_sampling
    if name in PRESETS:
        return PRESETS[name]
    raise DiffshegError(f"unknown sampling {name!r}: use {', '.join(SAMPLING_NAMES)}")


def jump_schedule(start: int, jump_length: int = 1, jump_n_sample: int = 1) -> list[int]:
    """Schedule indices a later window visits, from `start` down to -1 (done).

    RePaint's resampling: at every `jump_length`-th index below start - jump_length
    the walk goes back up `jump_length` steps, `jump_n_sample - 1` times.
    """
    n = start + 1
    jumps = {j: jump_n_sample - 1 for j in range(0, n - jump_length, jump_length)}
    t, times = n, []
    while t >= 1:
        t -= 1
        times.append(t)
        if jumps.get(t, 0) > 0:
            jumps[t] -= 1
            for _ in range(jump_length):
                t += 1
                times.append(t)
    times.append(-1)
    return times


def model_calls(times: list[int]) -> int:
    return sum(1 for a, b in zip(times, times[1:]) if b < a)


def plan_windows(n_frames: int, clip_len: int, overlap: int) -> list[tuple[int, int]]:
    """(start, end) frame ranges of the windows covering n_frames."""
    windows, start = [], 0
    while True:
        end = min(start + clip_len, n_frames)
        windows.append((start, end))
        if end >= n_frames:
            return windows
        start = end - overlap


def noised(values: np.ndarray, level: float, noise: np.ndarray) -> np.ndarray:
    """`values` (clean) at noise level `level` (sqrt(1 - abar)), with `noise` drawn for them."""
    return float((1 - level ** 2) ** 0.5) * values + level * noise


@dataclass(frozen=True)
class Fixed:
    """Values a window must pass through: `values` (1, L, D) wherever `mask` (1, L, D) is true."""

    values: np.ndarray
    mask: np.ndarray

    def paint(self, x: np.ndarray, level: float, noise: np.ndarray) -> np.ndarray:
        """`x` with the held values put in at noise level `level` (sqrt(1 - abar))."""
        return np.where(self.mask, noised(self.values, level, noise), x).astype(np.float32, copy=False)


class Foppas:
    """Samples one window at a time with a fixed schedule, settings and window size."""

    def __init__(self, schedule: Schedule, config: FoppasConfig, clip_len: int, dim: int,
                 proposal: Optional[Proposal] = None, gestures: Optional[int] = None, branch: int = 0):
        """gestures: how many leading channels are gestures, the rest face (default: all
        gestures). Best-of-N compares the gestures; a face seed draws the face's noise apart.
        branch: how many of the gestures, the last, a lower branch makes: their noise comes
        from streams of their own (see `Noise`), and best-of-N compares the others."""
        config.check(clip_len)
        self.schedule = config.schedule(schedule)
        self.config = config
        self.clip_len = clip_len
        self.dim = dim
        self.proposal = proposal
        self.gestures = dim if gestures is None else gestures
        self.branch = branch

    @property
    def upper(self) -> int:
        """The gesture channels before a lower branch's (all of them without one)."""
        return self.gestures - self.branch

    def noise(self, seed: int, face_seed: Optional[int] = None) -> "Noise":
        """The random numbers of one sampling run with `seed` (and `face_seed`)."""
        return Noise(seed, face_seed, self.gestures, (self.upper, self.gestures) if self.branch else None)

    def times(self, has_known: bool) -> list[int]:
        if not has_known:
            return list(range(self.config.steps - 1, -1, -1)) + [-1]
        return jump_schedule(self.config.start_index, self.config.jump_length, self.config.jump_n_sample)

    def sample_window(self, eps_fn: EpsFn, length: int, known: Optional[np.ndarray], noise: "Noise",
                      on_step: Callable[[int, int], None] = lambda step, n: None,
                      fixed: Optional[Fixed] = None) -> np.ndarray:
        """Sample a (1, length, dim) window; `known` (1, overlap, dim) fixes its first frames,
        `fixed` any others (painted at every step, exact in the result).
        The proposal draws from its own generator, so the noise of every channel it does not
        cover is the same as without it. A later window is sampled `candidates` times in one
        batch and the one that best continues `known` is kept (see `seam_scores`)."""
        config, sched = self.config, self.schedule
        randn = noise.draw
        batch = config.candidates if known is not None else 1

        x = randn(batch, length, self.dim)
        if known is not None and self.proposal is not None:
            draw = np.stack([self.proposal(known[0], length, noise.proposal) for _ in range(batch)])
            c = draw.shape[-1]
            x[..., :c] = sched.q_sample(draw.astype(np.float32), config.start_index, x[..., :c])
        times = self.times(known is not None)
        face_times = list(range(config.face_index, config.start_index, -1)) if known is not None else []
        n_calls, call = model_calls(times) + len(face_times) + (config.refine is not None), 0
        for t_now in face_times:  # the face from higher up: the gestures wait at their start
            x = self.face_step(eps_fn, x, t_now, known, fixed, randn)
            on_step(call, n_calls)
            call += 1
        for t_now, t_next in zip(times, times[1:]):
            if t_next > t_now:
                beta_index = t_now if config.reference_renoise else t_next
                x = sched.renoise(x, beta_index, randn(*x.shape))
                continue
            eps = eps_fn(x, t_now)
            if known is not None and config.carry > 0:
                eps = carry_overlap(sched, x, t_now, eps, known, config.carry, self.gestures)
            if fixed is not None:
                eps = carry_fixed(sched, x, t_now, eps, fixed, max(config.carry, HOLD_CARRY), self.gestures)
            x = self.step(x, t_now, eps, randn(*x.shape) if self._steps_draw_noise else None)
            if known is not None:
                level = sched.noise_level_prev(t_now)
                x = self.paint_overlap(x, noised(known, level, randn(batch, *known.shape[1:])), level)
            if fixed is not None:
                x = fixed.paint(x, sched.noise_level_prev(t_now), randn(*x.shape))
            on_step(call, n_calls)
            call += 1
        if batch > 1:
            upper = self.upper  # a lower branch follows them: the best of those is the best
            best = int(np.argmin(seam_scores(x[..., :upper], known[..., :upper])))
            x = x[best: best + 1]
        if config.refine is not None:
            x = self.refine_window(eps_fn, x, known, fixed)
            on_step(call, n_calls)
        return x if fixed is None else fixed.paint(x, 0.0, x)

    def face_step(self, eps_fn: EpsFn, x: np.ndarray, index: int, known: Optional[np.ndarray],
                  fixed: Optional[Fixed], randn: Callable[..., np.ndarray]) -> np.ndarray:
        """One step of the face channels alone from schedule `index` (the expression branch
        sees only the face, so it runs without the gesture branch); the gestures stay as they
        are. The known overlap and held values of the face are painted in as in a full step."""
        g, sched = self.gestures, self.schedule
        eps = eps_fn(x, index, face_only=True)
        noise = randn(*x.shape)[..., g:] if self._steps_draw_noise else None  # as a full step draws
        face, _ = sched.ddim_step(x[..., g:], index, eps[..., g:], self.face_eta, noise)
        level = sched.noise_level_prev(index)
        if known is not None:
            face = self.paint_overlap(face, noised(known[..., g:], level, randn(len(x), *known.shape[1:])[..., g:]),
                                      level)
        if fixed is not None:
            face = fixed.paint(np.concatenate([x[..., :g], face], axis=-1), level, randn(*x.shape))[..., g:]
        return np.concatenate([x[..., :g], face], axis=-1).astype(np.float32, copy=False)

    @property
    def branch_eta(self) -> float:
        """The eta a lower branch's channels are stepped with (0 without a branch)."""
        if not self.branch:
            return 0.0
        return self.config.eta if self.config.branch_eta is None else self.config.branch_eta

    @property
    def _steps_draw_noise(self) -> bool:
        """Whether a step draws noise (some channels are stepped stochastically)."""
        return max(self.config.eta, self.branch_eta, self.face_eta) > 0

    @property
    def face_eta(self) -> float:
        """The eta the face's channels are stepped with."""
        return self.config.eta if self.config.face_eta is None else self.config.face_eta

    def step(self, x: np.ndarray, index: int, eps: np.ndarray, noise: Optional[np.ndarray]) -> np.ndarray:
        """One DDIM step of every channel from schedule `index`, a lower branch's and the face's
        with their own eta."""
        x_next, _ = self.schedule.ddim_step(x, index, eps, self.config.eta, noise)
        own = [(slice(self.upper, self.gestures), self.branch_eta)] if self.branch else []
        own += [(slice(self.gestures, None), self.face_eta)] if self.gestures < self.dim else []
        for channels, eta in own:
            if eta != self.config.eta:
                x_next[..., channels], _ = self.schedule.ddim_step(x[..., channels], index, eps[..., channels], eta,
                                                                   None if noise is None else noise[..., channels])
        return x_next

    def paint_overlap(self, x: np.ndarray, known: np.ndarray, level: float) -> np.ndarray:
        """`x` (B, L, C) with its first frames replaced by `known` (B or 1, n, C), already at
        x's noise level `level`; below `blend_below` (with `blend`) the known frames are
        cross-faded linearly into x's own."""
        n = known.shape[1]
        if self.config.blend and level < self.config.blend_below:
            ramp = np.linspace(0, 1, n, dtype=np.float32).reshape(1, -1, 1)
            known = known * (1 - ramp) + x[:, :n] * ramp
        return np.concatenate([np.broadcast_to(known, (len(x),) + known.shape[1:]), x[:, n:]], axis=1)

    def refine_window(self, eps_fn: EpsFn, x: np.ndarray, known: Optional[np.ndarray],
                      fixed: Optional[Fixed] = None) -> np.ndarray:
        """The finished (B, L, D) window `x` with its gestures replaced by the network's x0
        for it taken as noisy at schedule index `refine`, the known overlap painted back as
        the last step paints it; the face channels are returned as they were. It runs after
        best-of-N has chosen and draws no noise, so the face, the choice and every later
        window's noise are the same as without it. Held frames (`fixed`) are carried into
        their neighbours as in the sampling steps."""
        config, sched, g = self.config, self.schedule, self.gestures
        eps = eps_fn(x, config.refine, refine=True)
        if fixed is not None:
            eps = carry_fixed(sched, x, config.refine, eps, fixed, max(config.carry, HOLD_CARRY), g)
        out = x.copy()
        out[..., :g] = sched.predict_x0(x[..., :g], np.full(len(x), config.refine), eps[..., :g])
        if known is not None:
            out[..., :g] = self.paint_overlap(out[..., :g], known[..., :g], level=0.0)
        return out


def carry_overlap(sched: Schedule, x: np.ndarray, index: int, eps: np.ndarray, known: np.ndarray,
                  width: int, channels: int) -> np.ndarray:
    """The noise prediction `eps` for (B, L, D) `x` at `index` with the x0 of its first
    `channels` channels made to continue `known` (1, n, D): the overlap's x0 set to the
    known frames and the gap at the last of them added to the new frames' x0, weighted
    0.5 (1 + cos(pi k / width)) at the k-th new frame (k = 1 .. width - 1). Frames further
    from the seam, and the face's channels, keep the network's prediction."""
    n, c = known.shape[1], channels
    a, b = sched.x0_coefs(np.full(x.shape[0], index), x)
    x0 = a * x[..., :c] - b * eps[..., :c]
    gap = known[:, -1:, :c] - x0[:, n - 1: n]
    k = np.arange(1, x.shape[1] - n + 1, dtype=np.float32)
    fade = np.where(k < width, 0.5 * (1.0 + np.cos(np.pi * k / width)), 0.0).astype(np.float32)
    x0[:, :n] = known[..., :c]
    x0[:, n:] += gap * fade.reshape(1, -1, 1)
    out = eps.copy()
    out[..., :c] = (a * x[..., :c] - x0) / b
    return out


def carry_fixed(sched: Schedule, x: np.ndarray, index: int, eps: np.ndarray, fixed: Fixed,
                width: int, channels: int) -> np.ndarray:
    """`eps` with the x0 of the first `channels` channels of (B, L, D) `x` made to pass
    through the held values and leave them smoothly. The x0 of held frames is set to their
    values; at each edge of the held frames (a held frame beside a free one) the gap
    between the value and the network's x0, and where the frame behind the edge is held
    too the gap in velocity, are carried into the free frames beyond it: gap + d * velocity
    gap, weighted 0.5 (1 + cos(pi d / width)) at d frames from the edge (where two edges
    reach a free frame their weights are shared). So the new frames continue the held ones
    in position and velocity; replacement alone leaves a jump where a held range begins or
    at a pin, as `carry_overlap` explains for the overlap."""
    c, length = channels, x.shape[1]
    a, b = sched.x0_coefs(np.full(x.shape[0], index), x)
    x0 = a * x[..., :c] - b * eps[..., :c]
    held = np.broadcast_to(fixed.mask[..., :c], x0.shape)
    values = np.broadcast_to(fixed.values[..., :c], x0.shape)
    gap = np.where(held, values - x0, 0.0)
    spread, weight = np.zeros_like(x0), np.zeros_like(x0)
    for step in (1, -1):  # edges whose free side is later (1) or earlier (-1) in time
        ahead = np.roll(held, -step, axis=1)  # the frame on the free side
        behind = np.roll(held, step, axis=1)
        edge_of = slice(0, length - 1) if step == 1 else slice(1, length)
        edge = np.zeros_like(held)
        edge[:, edge_of] = held[:, edge_of] & ~ahead[:, edge_of]
        turn = np.where(behind & edge, gap - np.roll(gap, step, axis=1), 0.0)  # velocity gap, away from the edge
        if step == 1:
            turn[:, 0] = 0.0
        else:
            turn[:, -1] = 0.0
        for d in range(1, min(width, length)):
            w = np.float32(0.5 * (1.0 + np.cos(np.pi * d / width)))
            src = slice(0, length - d) if step == 1 else slice(d, length)
            dst = slice(d, length) if step == 1 else slice(0, length - d)
            spread[:, dst] += w * edge[:, src] * (gap[:, src] + d * turn[:, src])
            weight[:, dst] += w * edge[:, src]
    x0 = np.where(held, values, x0 + spread / np.maximum(weight, 1.0))
    out = eps.copy()
    out[..., :c] = (a * x[..., :c] - x0) / b
    return out


def seam_scores(candidates: np.ndarray, known: np.ndarray, frames: int = SEAM_FRAMES) -> np.ndarray:
    """(N,) lower-better scores of (N, L, C) candidate windows continuing `known` (1, n, C),
    after S2G-MDDiffusion's optimal motion selection: position coherence (L1 distance between
    the mean of the last `frames` frames before the seam and of the first `frames` after it,
    per channel) plus velocity consistency (the angle between the mean velocity over those
    frames before and after). The seam is where the known overlap ends."""
    n = known.shape[1]
    before = candidates[:, max(0, n - frames): n]
    after = candidates[:, n: n + frames]
    position = np.abs(after.mean(axis=1) - before.mean(axis=1)).mean(axis=1)
    v_before = np.diff(candidates[:, max(0, n - frames - 1): n], axis=1).mean(axis=1)
    v_after = np.diff(candidates[:, n - 1: n + frames], axis=1).mean(axis=1)
    cosine = (v_before * v_after).sum(1) / np.maximum(
        np.linalg.norm(v_before, axis=1) * np.linalg.norm(v_after, axis=1), 1e-12)
    return position + np.arccos(np.clip(cosine, -1.0, 1.0))


class Noise:
    """The sampler's random numbers: float32 standard normal draws from numpy's PCG64, seeded
    with the sampling seed, the same on every backend and device. With a `face_seed`, the
    channels from `face_from` on (the face) come from a stream of their own: the expression
    branch sees only them, so the face is the same whatever the seed, while the gestures,
    which see the face, follow it and the seed. The gesture prior draws from a third stream.

    With `branch` (start, stop), the channels a lower branch makes draw from streams of their
    own too, in the sampler and in the prior's proposal. The branch sees the other channels and
    they never see it, so a model widened with one samples its source's channels exactly as the
    source does for the same seed: the same gestures and face, now with legs."""

    def __init__(self, seed: int, face_seed: Optional[int] = None, face_from: Optional[int] = None,
                 branch: Optional[tuple[int, int]] = None):
        seed = check_seed(seed)
        self.face = None if face_seed is None else np.random.default_rng([check_seed(face_seed), FACE_STREAM])
        if self.face is not None and face_from is None:
            raise ValueError("a face seed needs the channel the face starts at")
        self.face_from = face_from
        self.main = np.random.default_rng(seed)
        self.proposal = np.random.default_rng([seed, PROPOSAL_STREAM])
        if branch is not None:
            self.main = _Spliced(self.main, np.random.default_rng([seed, BRANCH_STREAM]), branch, axis=-1)
            self.proposal = _Spliced(self.proposal, np.random.default_rng([seed, BRANCH_STREAM, PROPOSAL_STREAM]),
                                     branch, axis=0)  # the prior draws (channels, frames)

    def draw(self, *shape: int) -> np.ndarray:
        """Noise of `shape` (batch, frames, channels); with a face seed, every candidate of a
        batch gets the same face noise, so best-of-N keeps the face too."""
        if self.face is None:
            return self.main.standard_normal(shape, dtype=np.float32)
        lead, channels = shape[:-1], shape[-1]
        face = self.face.standard_normal((1,) + lead[1:] + (channels - self.face_from,), dtype=np.float32)
        return np.concatenate([self.main.standard_normal(lead + (self.face_from,), dtype=np.float32),
                               np.broadcast_to(face, lead + face.shape[-1:])], axis=-1)


class _Spliced:
    """Draws of `main` with the entries [start, stop) along `axis` spliced in from `own`."""

    def __init__(self, main: np.random.Generator, own: np.random.Generator, span: tuple[int, int], axis: int):
        self.main, self.own, self.span, self.axis = main, own, span, axis

    def standard_normal(self, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        shape, (start, stop) = tuple(shape), self.span
        axis = self.axis % len(shape)
        around = self.main.standard_normal(shape[:axis] + (shape[axis] - (stop - start),) + shape[axis + 1:], dtype=dtype)
        inside = self.own.standard_normal(shape[:axis] + (stop - start,) + shape[axis + 1:], dtype=dtype)
        return np.concatenate([around.take(range(start), axis), inside,
                               around.take(range(start, around.shape[axis]), axis)], axis=axis)


class FoppasStream:
    """Streaming FOPPAS: push conditioning frames, get back final motion frames.

    `make_eps_fn(cond)` turns the `Conditioning` of a window's L frames into an
    `EpsFn`. A window is sampled as soon as its conditioning is complete; its last
    `overlap` frames are held back until the next window has re-painted them, so the
    latency is at most one window plus its compute.
    """

    def __init__(self, sampler: Foppas, make_eps_fn: Callable[[Conditioning], EpsFn], seed: int,
                 progress: Optional[ProgressCallback] = None,
                 cancel: Optional[threading.Event] = None, expected_frames: Optional[int] = None,
                 face_seed: Optional[int] = None):
        self.sampler = sampler
        self.make_eps_fn = make_eps_fn
        self.noise = sampler.noise(seed, face_seed)
        self.progress = progress
        self.cancel = cancel
        self.expected_windows = (
            len(plan_windows(expected_frames, sampler.clip_len, sampler.config.overlap))
            if expected_frames else 0)
        self._cond: Optional[Conditioning] = None  # conditioning from the current window start
        self._tail: Optional[np.ndarray] = None   # held-back overlap frames (1, overlap, D)
        self._window = 0

    def push(self, cond: Conditioning) -> np.ndarray:
        """Add n frames' conditioning; return the (k, D) motion frames now final."""
        self._cond = cond if self._cond is None else Conditioning.join([self._cond, cond])
        out = []
        while len(self._cond) >= self.sampler.clip_len:
            out.append(self._run_window(self.sampler.clip_len))
        return self._stack(out)

    def finish(self) -> np.ndarray:
        """Sample what is left (a shorter last window) and return the remaining frames."""
        out = []
        held = 0 if self._tail is None else self._tail.shape[1]
        if self._cond is not None and len(self._cond) > held:
            out.append(self._run_window(len(self._cond)))
        if self._tail is not None:
            out.append(self._tail[0])
            self._tail = None
        self._cond = None
        return self._stack(out)

    def _run_window(self, length: int) -> np.ndarray:
        overlap = self.sampler.config.overlap
        cond = self._cond.frames(0, length)
        known = self._tail if (self._tail is not None and overlap > 0) else None
        clip, total = self._window, max(self.expected_windows, self._window + 1)

        def on_step(step: int, n_steps: int) -> None:
            if self.progress is not None:
                self.progress(Progress(clip=clip, n_clips=total, step=step, n_steps=n_steps))

        def eps_fn(x: np.ndarray, index: int, **options) -> np.ndarray:
            check_cancel(self.cancel)
            return base_fn(x, index, **options)

        base_fn = self.make_eps_fn(cond)
        window = self.sampler.sample_window(eps_fn, length, known, self.noise, on_step)
        self._window += 1
        keep = length - overlap if length == self.sampler.clip_len else length
        self._tail = window[:, keep:] if keep < length else None
        self._cond = self._cond.frames(keep, len(self._cond))
        return window[0, :keep]

    def _stack(self, parts: list[np.ndarray]) -> np.ndarray:
        if not parts:
            return np.zeros((0, self.sampler.dim), np.float32)
        return np.concatenate(parts)


def inpaint_range(sampler: Foppas, make_eps_fn: Callable[[Conditioning], EpsFn], cond: Conditioning,
                  motion: np.ndarray, start: int, end: int, seed: int, hold: Optional[np.ndarray] = None,
                  progress: Optional[ProgressCallback] = None, cancel: Optional[threading.Event] = None,
                  face_seed: Optional[int] = None) -> np.ndarray:
    """Frames [start, end) of the (T, D) normalised `motion` sampled anew for its T frames'
    conditioning `cond`, continuing the `overlap` frames before the range and joining the
    `overlap` frames after it. Windows run left to right over the range with its context;
    each continues what is final before it (FOPPAS's known overlap) and holds the frames
    after the range, and wherever the (T, D) bool `hold` is set (a kept face, pins), at
    `motion`'s values. Returns the (end - start, D) new frames."""
    n, length, overlap = len(motion), sampler.clip_len, sampler.config.overlap
    if not 0 <= start < end <= n or len(cond) != n:
        raise DiffshegError(f"frames {start}-{end} are not a range of the {n}-frame motion")
    s0, e0 = max(0, start - max(overlap, 1)), min(n, end + max(overlap, 1))
    work = motion[s0:e0].astype(np.float32, copy=True)
    held = np.zeros(work.shape, dtype=bool) if hold is None else hold[s0:e0].copy()
    held[end - s0:] = True
    held[: start - s0] = True
    width = max(sampler.config.carry, HOLD_CARRY)
    pins = np.flatnonzero(held[: end - s0, : sampler.upper].any(axis=1))  # a lower branch's held legs are no pins
    windows = _range_windows(e0 - s0, start - s0, length, overlap, pins, width)
    noise = sampler.noise(seed, face_seed)
    done = start - s0
    for w, (a, b) in enumerate(windows):
        n_known = max(0, done - a) if w else 0  # the first window holds the left context as it holds the right

        def on_step(step: int, n_steps: int, w=w) -> None:
            check_cancel(cancel)
            if progress is not None:
                progress(Progress(clip=w, n_clips=len(windows), step=step, n_steps=n_steps))

        window = sampler.sample_window(make_eps_fn(cond.frames(s0 + a, s0 + b)), b - a,
                                       work[None, a: a + n_known] if n_known else None, noise, on_step,
                                       Fixed(work[None, a:b], held[None, a:b]))
        stop = min(b, end - s0)
        work[a + n_known: stop] = np.where(held[a + n_known: stop], work[a + n_known: stop],
                                           window[0, n_known: stop - a])
        done = b
    return work[start - s0: end - s0]


def _range_windows(span: int, done: int, length: int, overlap: int, pins: np.ndarray = (),
                   lead: int = 0) -> list[tuple[int, int]]:
    """Windows over `span` frames whose first `done` (the left context) are final: the last
    window, at full length where the span allows, holds the range's end and the frames
    after it; the windows before it reach `overlap` frames into it. A window before it ends
    early where the next would begin fewer than `lead` free frames before a pin (frames in
    `pins`), so that the motion can turn towards the pin in the window that holds it."""
    last = (max(0, span - length), span)
    head_end = last[0] + overlap
    windows, a = [], 0
    while done < head_end:
        b = min(a + length, head_end)
        late = [p for p in pins if b <= p < b + lead and p - lead > done]
        if late and b < head_end:
            b = min(late) - lead
        windows.append((a, b))
        a, done = b - overlap, b
    return windows + [last]


def sample_long(sampler: Foppas, make_eps_fn: Callable[[Conditioning], EpsFn], cond: Conditioning,
                seed: int, progress: Optional[ProgressCallback] = None,
                cancel: Optional[threading.Event] = None) -> np.ndarray:
    """Sample (T, D) motion for the conditioning of T frames."""
    stream = FoppasStream(sampler, make_eps_fn, seed, progress, cancel, expected_frames=len(cond))
    return np.concatenate([stream.push(cond), stream.finish()])


def with_overrides(config: FoppasConfig, steps: Optional[int] = None, **overrides) -> FoppasConfig:
    """`config` with the given fields replaced, skipping those set to None."""
    if steps is not None:
        config = config.with_steps(steps)
    return replace(config, **{k: v for k, v in overrides.items() if v is not None})
