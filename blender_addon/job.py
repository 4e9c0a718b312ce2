"""One press of Generate (or one line of a batch), and the background job that runs it.

A `Request` is resolved on the main thread: what to generate (the whole clip, from the
character's pose where asked, or a range of the take playing) and how to key it. Its
`run` makes the Motion and touches no Blender data, so `GenerationJob` runs it in a
daemon thread, with progress and a cancel event; `apply` keys the result on the main
thread.
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

    def apply(self, scene, motion):
        """Key `motion` (main thread): a new take of the whole clip, or of the range."""
        if self.range is None:
            from .bake import bake_motion

            return bake_motion(scene, motion, str(self.path), self.options)
        from .regenerate import apply_range

        return apply_range(scene, self.range, motion, self.options)


class GenerationJob:
    """A request's generation in a daemon thread; poll `done`, then read `motion`/`error`."""

    def __init__(self, request: Request):
        self.cancel = threading.Event()
        self.fraction = 0.0
        self.motion = None
        self.started = time.perf_counter()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(request,), daemon=True)

    def start(self) -> "GenerationJob":
        self._thread.start()
        return self

    def _run(self, request: Request) -> None:
        try:
            self.motion = request.run(self._progress, self.cancel)
        except BaseException as exc:  # handed to the main thread, which reports it
            self.error = exc

    def _progress(self, p) -> None:
        self.fraction = p.fraction

    @property
    def elapsed(self) -> float:
        """Seconds since the job started (generation, then keying)."""
        return time.perf_counter() - self.started

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self) -> None:
        self._thread.join()
