"""Evaluation metrics: DiffSHEG appendix E (FGD / FED / FMD, BA, Div, PCM, SRGR) and the
ones animators see (jitter, clip-seam smoothness, lip-sync, blinks)."""

from .accuracy import pcm, srgr
from .alignment import audio_beats, beat_alignment, motion_beats
from .blinks import blink_stats, detect_blinks
from .channels import blink_signal, face_channel, layout_array, mouth_opening
from .frechet import diversity, frechet_distance
from .lipsync import envelope_correlation, phoneme_contrast, reference_correlation
from .semantic import SemanticSpan, find_semantic, read_semantic, semantic_weights
from .smoothness import foppas_seams, mean_jerk, motion_curves, seam_smoothness, speed
from .textgrid import Interval, phone_tier, read_textgrid

__all__ = [
    "Interval", "SemanticSpan", "audio_beats", "beat_alignment", "blink_signal", "blink_stats",
    "detect_blinks", "diversity", "envelope_correlation", "face_channel", "find_semantic",
    "foppas_seams", "frechet_distance", "layout_array", "mean_jerk", "motion_beats",
    "motion_curves", "mouth_opening", "pcm", "phone_tier", "phoneme_contrast", "read_semantic",
    "read_textgrid", "reference_correlation", "seam_smoothness", "semantic_weights", "speed",
    "srgr",
]
