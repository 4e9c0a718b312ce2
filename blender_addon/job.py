"""One press of Generate (or one line of a batch), and the background job that runs it.

A `Request` is resolved on the main thread: what to generate (the whole clip, from the
character's pose where asked, or a range of the take playing) and how to key it. Its
`run` makes the Motion and touches no Blender data, so `GenerationJob` runs it in a
daemon thread, with progress and a cancel event; `apply` keys the result on the main
thread. `RequestQueue` runs several requests (one per sound strip) one after another,
under one cancel event, for the main thread to key each as it finishes.

`BackgroundJob` is the daemon thread a modal operator polls: `GenerationJob` here, the
pip install of the preferences (preferences.InstallJob) too.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Request:
    """One press of Generate, resolved on the main thread: the whole clip as a new take
    (from the character's pose where asked), or a range of the take playing generated anew."""

    path: Path
    options: object                  # BakeOptions
    generation: object               # GenerateSettings
    keep_face: bool = False
    pins: tuple = ()                 # whole clip: the pose to start from
    range: object | None = None      # regenerate.RangeRequest

    def run(self, progress, cancel):
        """The Motion (worker thread; touches no Blender data)."""
        import diffsheg_core

        if self.range is None:
            return diffsheg_core.generate(str(self.path), settings=self.generation, pins=self.pins,
                                          progress=progress, cancel=cancel)
        r = self.range
        return diffsheg_core.regenerate(r.source.motion, str(self.path), start=r.start, end=r.end,
                                        settings=self.generation, keep_face=self.keep_face, pins=r.pins,
                                        progress=progress, cancel=cancel)

    def made_with(self, motion) -> dict:
        """What the result was made with (model, seed, ...): a range's own record."""
        return motion.meta["regenerated"][-1] if self.range is not None else motion.meta

    def apply(self, scene, motion):
        """Key `motion` (main thread): a new take of the whole clip, or of the range."""
        if self.range is None:
            from .bake import bake_motion

            return bake_motion(scene, motion, str(self.path), self.options)
        from .regenerate import apply_range

        return apply_range(scene, self.range, motion, self.options)


class BackgroundJob:
    """`work` in a daemon thread: `start` it, poll `done` (or `wait`), then read what it left."""

    def __init__(self):
        self.started = time.perf_counter()
        self._thread = threading.Thread(target=self.work, daemon=True)

    def work(self) -> None:
        raise NotImplementedError

    def start(self):
        self._thread.start()
        return self

    @property
    def elapsed(self) -> float:
        """Seconds since the job was made."""
        return time.perf_counter() - self.started

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)


class GenerationJob(BackgroundJob):
    """A request's generation in a daemon thread; poll `done`, then read `motion`/`error`.
    `elapsed` counts generation, then keying."""

    def __init__(self, request: Request, cancel: threading.Event | None = None):
        super().__init__()
        self.request = request
        self.cancel = cancel if cancel is not None else threading.Event()
        self.fraction = 0.0
        self.motion = None
        self.error: BaseException | None = None

    def work(self) -> None:
        try:
            self.motion = self.request.run(self._progress, self.cancel)
        except BaseException as exc:  # handed to the main thread, which reports it
            self.error = exc

    def _progress(self, p) -> None:
        self.fraction = p.fraction


class RequestQueue:
    """Requests generated one after another, each in its own `GenerationJob`, all under one
    cancel event. The main thread calls `advance` to start the next request once it has
    keyed the previous one's Motion (Blender data are written on the main thread only)."""

    def __init__(self, requests: list[Request]):
        self.requests = list(requests)
        self.cancel = threading.Event()
        self.index = -1                          # the request under way (or last run)
        self.job: GenerationJob | None = None
        self.started = time.perf_counter()

    def advance(self) -> GenerationJob | None:
        """Start the next request's job; None when all have run or the queue was cancelled."""
        if self.cancel.is_set() or self.index + 1 >= len(self.requests):
            self.job = None
            return None
        self.index += 1
        self.job = GenerationJob(self.requests[self.index], self.cancel).start()
        return self.job

    @property
    def fraction(self) -> float:
        """How far the whole queue is (each request an equal share)."""
        if not self.requests:
            return 1.0
        current = self.job.fraction if self.job is not None else 0.0
        return min(1.0, (max(self.index, 0) + current) / len(self.requests))

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.started
