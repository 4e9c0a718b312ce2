"""The gesture prior (diffsheg_core/prior.py), fitted to real motion capture: continuations
of held-out frames look like the capture in spread, speed and continuity."""

from pathlib import Path

import numpy as np
import pytest

from diffsheg_core.training.data.beat import read_gesture
from diffsheg_core.errors import DiffshegError
from diffsheg_core.prior import GesturePrior

REAL_BVH = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "beat" / "2_scott_0_1_1.bvh"
CLIP, KNOWN, FACE = 34, 4, 5


@pytest.fixture(scope="module")
def capture() -> tuple[np.ndarray, np.ndarray]:
    """Normalised gesture channels of the real take, plus FACE channels the prior does not
    draw: the first 80 % to fit on, the rest held out."""
    gestures = read_gesture(REAL_BVH, 15.0, source_fps=15.0)
    gestures = (gestures - gestures.mean(0)) / np.maximum(gestures.std(0), 1e-3)
    motion = np.concatenate([gestures, np.ones((len(gestures), FACE))], axis=1)
    cut = int(0.8 * len(motion))
    return motion[:cut], motion[cut:]


@pytest.fixture(scope="module")
def prior(capture) -> GesturePrior:
    return GesturePrior.fit([capture[0]], capture[0].shape[1] - FACE, CLIP)


def _continuations(prior: GesturePrior, held: np.ndarray, seed: int = 0,
                   spread: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(real windows, drawn windows) for every window start in the held-out frames."""
    gen = np.random.default_rng(seed)
    real = np.stack([held[s: s + CLIP] for s in range(0, len(held) - CLIP, 8)])
    drawn = np.stack([prior.propose(w[:KNOWN].astype(np.float32), CLIP, gen, spread=spread) for w in real])
    return real, drawn


def test_continuations_move_like_the_capture(prior, capture):
    real, drawn = _continuations(prior, capture[1])
    g = prior.dims
    new_real, new_drawn = real[:, KNOWN:, :g], drawn[:, KNOWN:]
    spread = lambda w: float(w.std(axis=(0, 1)).mean())
    speed = lambda w: float(np.abs(np.diff(w, axis=1)).mean())
    # seeds 0-2 (numpy's PCG64) measure: spread 1.00-1.03x, frame-to-frame speed 1.45-1.47x,
    # first step 1.4x
    assert 0.75 < spread(new_drawn) / spread(new_real) < 1.33
    # smooth (white noise of that spread would move 5x faster), a little rougher than the capture
    assert 0.6 < speed(new_drawn) / speed(new_real) < 1.8
    # the draw continues from the last known frame without a jump
    jump = np.abs(drawn[:, KNOWN] - drawn[:, KNOWN - 1]).mean()
    assert jump < 2 * speed(new_real)
    # and the posture of its next half second follows the known frames (0.49-0.59x the
    # distance to the known frames of another window)
    posture = new_drawn[:, :8].mean(1)
    near = np.abs(posture - real[:, :KNOWN, :g].mean(1)).mean()
    other = np.abs(posture - np.roll(real[:, :KNOWN, :g].mean(1), 7, axis=0)).mean()
    assert near < 0.7 * other


def test_known_frames_kept_and_only_the_gesture_channels_drawn(prior, capture):
    known = capture[1][:KNOWN].astype(np.float32)
    draw = prior.propose(known, CLIP, np.random.default_rng(0))
    assert isinstance(draw, np.ndarray)
    assert draw.shape == (CLIP, prior.dims) and draw.dtype == np.float32
    assert np.array_equal(draw[:KNOWN], known[:, : prior.dims])
    again = prior.propose(known, CLIP, np.random.default_rng(0))
    assert np.array_equal(draw, again)
    other = prior.propose(known, CLIP, np.random.default_rng(1))
    assert not np.array_equal(draw, other)
    shorter = prior.propose(known, 20, np.random.default_rng(0))  # a short last window
    assert shorter.shape == (20, prior.dims)


def test_spread_scales_a_draw_about_its_mean_given_the_known_frames(prior, capture):
    """`spread` (the fast sampling's FoppasConfig.prior_spread) multiplies the new frames'
    deviation from their conditional mean, drawn with the same numbers; the known frames and
    where the draw is centred stay as they were."""
    known = capture[1][:KNOWN].astype(np.float32)
    draws = {k: prior.propose(known, CLIP, np.random.default_rng(0), spread=k).astype(np.float64)
             for k in (1.0, 1.1, 2.0)}
    mean = 2 * draws[1.0] - draws[2.0]  # the conditional mean: the draws are linear in spread
    assert np.allclose(draws[1.1] - mean, 1.1 * (draws[1.0] - mean), atol=1e-5)
    assert np.array_equal(draws[1.1][:KNOWN], known[:, : prior.dims])
    _, one = _continuations(prior, capture[1])
    _, wider = _continuations(prior, capture[1], spread=1.1)  # the same numbers drawn
    ratio = wider[:, KNOWN:].std() / one[:, KNOWN:].std()
    print(f"the new frames' spread at 1.1: {ratio:.3f}x the fitted draw's")
    assert 1.02 < ratio < 1.1  # the part the known frames fix is not widened


def test_bad_requests_are_refused(prior, capture):
    known = capture[1][:KNOWN].astype(np.float32)
    with pytest.raises(DiffshegError, match="known frames"):
        prior.propose(known, CLIP + 1, np.random.default_rng())
    with pytest.raises(DiffshegError, match="known frames"):
        prior.propose(known[:0], CLIP, np.random.default_rng())
    with pytest.raises(DiffshegError, match="cannot fit"):
        GesturePrior.fit([capture[1][:10]], prior.dims, CLIP)


def test_tensors_round_trip(prior):
    tensors = prior.tensors()
    assert all(isinstance(v, np.ndarray) and v.dtype == np.float32 for v in tensors.values())
    back = GesturePrior.from_tensors(tensors, "test")
    assert back.dims == prior.dims and back.max_len == CLIP
    assert np.array_equal(back.mean, prior.mean)
    assert np.array_equal(back.axes, prior.axes) and np.array_equal(back.autocov, prior.autocov)
    assert GesturePrior.from_tensors({}, "test") is None
    with pytest.raises(DiffshegError, match="incomplete"):
        GesturePrior.from_tensors({k: v for k, v in tensors.items() if "autocov" not in k}, "model.safetensors")
