"""One recorded take in model space: motion and speech features at the model's frame
rate, and the checks that decide whether a take is fit for training."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...audio import Audio, mel_features, n_motion_frames
from ...errors import DiffshegError

MAX_LENGTH_MISMATCH_S = 0.5
"""Audio and motion of one take may differ by this much; the longer one is trimmed."""


class TakeError(DiffshegError):
    """One take is unusable (broken or mismatched files); datasets report and skip it."""


@dataclass
class Take:
    """motion: (T, D) float32 in layout order (gesture then expression), at the layout's fps;
    mel: (T, 128) float32 features of the same frames; mask: (D,) bool, False for channels
    the recording does not hold (e.g. no face capture); style: speaker / style class;
    extra: (T, E) the model's second speech input (HuBERT or phonetic), when it has one;
    taught: (D,) bool, the channels in the data loss when they are fewer than the take
    holds (a dataset's face = "source": held, so the clips carry it, but taught by the
    source model), None for `mask`."""

    name: str
    motion: np.ndarray
    mel: np.ndarray
    style: int
    mask: np.ndarray
    extra: np.ndarray | None = None
    taught: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return len(self.motion)


def check_finite(name: str, what: str, values: np.ndarray) -> None:
    """TakeError naming the frames that hold NaN or infinite values."""
    bad = ~np.isfinite(values.reshape(len(values), -1)).all(axis=1)
    if bad.any():
        frames = np.flatnonzero(bad)
        shown = ", ".join(str(f) for f in frames[:5]) + (" ..." if len(frames) > 5 else "")
        raise TakeError(f"{name}: {what} has NaN or infinite values in {len(frames)} frames ({shown})")


def decimate(values: np.ndarray, source_fps: float, target_fps: float, name: str) -> np.ndarray:
    """Every k-th frame, where k = source_fps / target_fps must be a whole number."""
    ratio = source_fps / target_fps
    if ratio < 1 - 1e-6 or abs(ratio - round(ratio)) > 1e-3 * ratio:
        raise TakeError(
            f"{name}: motion at {source_fps:g} fps cannot be brought to {target_fps:g} fps by taking "
            f"every n-th frame; record or export it at a multiple of {target_fps:g} fps")
    return values[:: int(round(ratio))]


def make_take(name: str, motion: np.ndarray, audio: Audio, fps: float, style: int,
              mask: np.ndarray, max_mismatch: float = MAX_LENGTH_MISMATCH_S) -> Take:
    """Check a take's motion (already at `fps`) against its audio and compute its features."""
    check_finite(name, "the motion", motion)
    n_audio = n_motion_frames(audio, fps)
    gap = (len(motion) - n_audio) / fps
    if gap > max_mismatch:
        raise TakeError(
            f"{name}: the audio ({n_audio / fps:.2f} s) is shorter than the motion "
            f"({len(motion) / fps:.2f} s); is it the right audio file, or the motion's frame rate wrong?")
    if -gap > max_mismatch:
        raise TakeError(
            f"{name}: the motion ({len(motion) / fps:.2f} s) is shorter than the audio "
            f"({n_audio / fps:.2f} s); is it the right motion file, or its frame rate wrong?")
    mel = mel_features(audio, fps)
    n = min(len(motion), len(mel))
    return Take(name, np.ascontiguousarray(motion[:n], dtype=np.float32), mel[:n], style,
                np.asarray(mask, dtype=bool))
