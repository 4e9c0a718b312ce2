"""diffsheg_core: speech in, holistic motion (body, hands, head, face) out.

The public entry point is `generate(...) -> Motion`. No Blender import anywhere here.
Importing the package needs the standard library alone (numpy comes with `Motion` and
`generate`), so the Blender add-on registers in a Blender whose Python lacks numpy and
offers to install it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .errors import AudioError, Cancelled, CheckpointError, DiffshegError
from .progress import Progress

if TYPE_CHECKING:
    from .motion import Motion

__version__ = "0.1.0"

__all__ = [
    "AudioError", "Cancelled", "CheckpointError", "DiffshegError",
    "Motion", "Progress", "generate", "regenerate", "__version__",
]


def __getattr__(name: str):
    if name == "Motion":
        from .motion import Motion

        return Motion
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def generate(*args, **kwargs) -> Motion:
    """Generate motion from speech; see `diffsheg_core.pipeline.generate`."""
    from .pipeline import generate as _generate

    return _generate(*args, **kwargs)


def regenerate(*args, **kwargs) -> Motion:
    """Generate a range of a motion anew; see `diffsheg_core.pipeline.regenerate`."""
    from .pipeline import regenerate as _regenerate

    return _regenerate(*args, **kwargs)
