"""Training data: BEAT, BEAT2 and folder-of-recordings readers, sliding-window clips,
a content-keyed feature cache and normalisation statistics."""

from .dataset import DataConfig, TakeSet, find_sources, load_takes, normalisation
from .normalise import NormStats, compute_stats, official_stats
from .take import Take, TakeError
from .windows import ClipDataset, window_starts

__all__ = [
    "ClipDataset", "DataConfig", "NormStats", "Take", "TakeError", "TakeSet",
    "compute_stats", "find_sources", "load_takes", "normalisation", "official_stats", "window_starts",
]
