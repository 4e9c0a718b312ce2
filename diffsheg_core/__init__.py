"""diffsheg_core: speech in, holistic motion (body, hands, head, face) out.

The public entry point is `generate(...) -> Motion`. No Blender import anywhere here.
"""

from .errors import AudioError, Cancelled, CheckpointError, DiffshegError
from .motion import Motion
from .progress import Progress

__version__ = "0.1.0"

__all__ = [
    "AudioError", "Cancelled", "CheckpointError", "DiffshegError",
    "Motion", "Progress", "generate", "regenerate", "__version__",
]


def generate(*args, **kwargs) -> Motion:
    """Generate motion from speech; see `diffsheg_core.pipeline.generate`."""
    from .pipeline import generate as _generate

    return _generate(*args, **kwargs)


def regenerate(*args, **kwargs) -> Motion:
    """Generate a range of a motion anew; see `diffsheg_core.pipeline.regenerate`."""
    from .pipeline import regenerate as _regenerate

    return _regenerate(*args, **kwargs)
