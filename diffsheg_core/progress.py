"""Progress reports and cancellation for long work (generation, training)."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable, Optional

from .errors import Cancelled


@dataclass(frozen=True)
class Progress:
    """Where generation stands: diffusion `step` of `n_steps` in `clip` of `n_clips` (0-based)."""

    clip: int
    n_clips: int
    step: int
    n_steps: int

    @property
    def fraction(self) -> float:
        """Overall completion in [0, 1]."""
        if self.n_clips == 0 or self.n_steps == 0:
            return 1.0
        return (self.clip + (self.step + 1) / self.n_steps) / self.n_clips


ProgressCallback = Callable[[Progress], None]


def check_cancel(cancel: Optional[threading.Event]) -> None:
    """Raise `Cancelled` if the caller has set `cancel`."""
    if cancel is not None and cancel.is_set():
        raise Cancelled("generation cancelled")
