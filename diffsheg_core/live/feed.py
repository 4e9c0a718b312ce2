"""The audio feed between a live source and the generator: a bounded, thread-safe queue
of mono float32 chunks, each stamped with the wall-clock time it arrived.

A source (microphone, a file played at real time, a socket) puts chunks from its own
thread and closes the feed when it ends, with the reason when it ended badly (the device
vanished, the socket closed mid-sample). The generator takes them. A producer faster
than the generator can follow fills the feed: what does not fit is dropped, counted and
reported, and never blocks the producer. A producer slower than real time is the
session's business (it eases the avatar to rest, `session.LiveSession`).
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import DiffshegError

DEFAULT_CAPACITY_S = 4.0  # audio the feed holds before it drops: far more than one hop waits


@dataclass(frozen=True)
class Chunk:
    """Mono float32 samples and the `time.monotonic()` at which they arrived."""

    samples: np.ndarray
    arrived: float


class FeedClosed(Exception):
    """Raised by `AudioFeed.get` once the source has ended and every chunk was taken."""


class AudioFeed:
    """Chunks from one source at one sample rate, at most `capacity_s` seconds held."""

    def __init__(self, sample_rate: int, capacity_s: float = DEFAULT_CAPACITY_S):
        if isinstance(sample_rate, bool) or not isinstance(sample_rate, int) or sample_rate <= 0:
            raise DiffshegError(f"a live source's sample rate must be a whole number of Hz above 0, "
                                f"got {sample_rate!r}")
        if not capacity_s > 0:
            raise DiffshegError(f"the live audio buffer must hold more than 0 seconds, got {capacity_s!r}")
        self.sample_rate = sample_rate
        self.capacity = int(round(capacity_s * sample_rate))
        self._chunks: collections.deque[Chunk] = collections.deque()
        self._held = 0
        self._lock = threading.Condition()
        self._closed = False
        self.error: Optional[str] = None  # why the source ended, when it ended badly
        self.dropped = 0  # samples dropped because the feed was full
        self.received = 0  # samples put, dropped ones included

    def put(self, samples: np.ndarray, arrived: Optional[float] = None) -> None:
        """Add mono samples (any float or int16 array, converted to float32 in [-1, 1]).
        What does not fit is dropped and counted in `dropped`; a closed feed ignores it."""
        samples = _as_float(samples)
        stamp = time.monotonic() if arrived is None else arrived
        with self._lock:
            if self._closed or not len(samples):
                return
            self.received += len(samples)
            room = self.capacity - self._held
            if room < len(samples):
                self.dropped += len(samples) - max(room, 0)
                samples = samples[: max(room, 0)]
            if len(samples):
                self._chunks.append(Chunk(samples, stamp))
                self._held += len(samples)
                self._lock.notify_all()

    def close(self, error: Optional[str] = None) -> None:
        """The source has ended; `error` says why when it ended badly. Chunks already put can
        still be taken."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self.error = error
            self._lock.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def get(self, timeout: float) -> Optional[Chunk]:
        """The oldest chunk, waiting up to `timeout` seconds: None when nothing came in time;
        raises FeedClosed when the source has ended and everything was taken."""
        deadline = time.monotonic() + max(timeout, 0.0)
        with self._lock:
            while not self._chunks:
                if self._closed:
                    raise FeedClosed(self.error or "the source ended")
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._lock.wait(left)
            chunk = self._chunks.popleft()
            self._held -= len(chunk.samples)
            return chunk

    @property
    def dropped_seconds(self) -> float:
        return self.dropped / self.sample_rate


def _as_float(samples: np.ndarray) -> np.ndarray:
    """Mono float32 samples: int16 PCM scaled to [-1, 1], anything else cast; a 2-D array
    (frames, channels) is mixed down."""
    array = np.asarray(samples)
    scale = 1.0 / 32768.0 if array.dtype == np.int16 else 1.0
    array = array.astype(np.float32) * np.float32(scale)
    if array.ndim == 2:
        array = array.mean(axis=1)
    if array.ndim != 1:
        raise DiffshegError(f"live audio must be mono samples (n,) or (n, channels), got shape {array.shape}")
    return np.ascontiguousarray(array, dtype=np.float32)
