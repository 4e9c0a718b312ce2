"""The phonetic speech encoder's front end: the phone set, the log-mel it hears and how its
phone posteriors become a model's second speech input. The network itself is
`torch_layer.model.PhoneticEncoder` (torch, trained by `training.train_phonetic`); at generation
time it runs on either backend (`runtime.backends`), from the copy stored in the model file.

Why: the official mel (one 114 ms window per 1/15 s frame) tells loud from quiet but not
*which* consonant is spoken, and the lips need exactly that (closed for p/b/m, open for
t/d/n). Where the official models take HuBERT features, the bundled default model takes
this encoder's phone posteriors instead: four recogniser frames per motion frame, stacked.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields
from typing import Callable

import numpy as np

from .audio import MEL_RATE, Audio, SpeechEncoding, mel_hop, mel_spectrogram, resample, resampled_length
from .errors import CheckpointError, DiffshegError

# One phone alphabet for the whole project: ARPAbet without stress digits, SIL for pauses.
SILENCE = "SIL"
VOWELS = frozenset({
    "AA", "AE", "AH", "AO", "AW", "AY", "EH", "ER", "EY", "IH", "IY", "OW", "OY", "UH", "UW",
})
CONSONANTS = frozenset({
    "B", "CH", "D", "DH", "F", "G", "HH", "JH", "K", "L", "M", "N", "NG", "P", "R", "S", "SH",
    "T", "TH", "V", "W", "Y", "Z", "ZH",
})
ARPABET = VOWELS | CONSONANTS | {SILENCE}
PHONES: tuple[str, ...] = (SILENCE,) + tuple(sorted(ARPABET - {SILENCE}))
BILABIALS = ("P", "B", "M")
NORMALISATIONS = ("utterance", "none")

ENCODER_RATE = 16000
"""The encoder hears speech band-limited to this rate (0-8 kHz), whatever the recording's rate.

Its corpus is 16 kHz (`training.corpus.augment.SAMPLE_RATE`), so in training the mel bands
above 8 kHz (the top two of 64 at 18 kHz) only ever held the 1e-5 floor: the stored input
statistics divide them by a standard deviation of 0.004-0.005. Speech at 22.05 or 44.1 kHz
has energy there, which that scaling turned into inputs hundreds of times too large: the
phone picked per frame agreed with the same speech at 16 kHz on 5 % of frames, and the
bundled model's lips moved against the voice (mouth-voice correlation -0.44 on
fr_css10_1 at 22.05 kHz, 0.52 at 16 kHz). 16 kHz audio and slower are heard as they are."""

Posteriors = Callable[[np.ndarray], np.ndarray]
"""(n_mels, N) log-mel -> (N, len(PHONES)) phone probabilities: the encoder on some backend."""


@dataclass
class PhoneticConfig:
    """Front end and network sizes. The recogniser runs at `subframes` x the motion rate."""

    fps: float = 15.0
    subframes: int = 4
    n_fft: int = 512
    n_mels: int = 64
    channels: int = 128
    kernel: int = 5
    dilations: tuple[int, ...] = (1, 2, 4, 8, 1)
    dropout: float = 0.2
    normalise: str = "utterance"   # mel level: minus its mean over the utterance per band, or as recorded ("none")

    @property
    def hop(self) -> int:
        """Recogniser hop in samples at 18 kHz (300 at 15 fps x 4)."""
        hop, rest = divmod(mel_hop(self.fps), self.subframes)
        if rest:
            raise DiffshegError(f"{self.subframes} subframes do not divide the mel hop at {self.fps:g} fps")
        return hop

    @property
    def dim(self) -> int:
        """Width of the features per motion frame: stacked phone posteriors."""
        return self.subframes * len(PHONES)

    def __post_init__(self):
        if self.normalise not in NORMALISATIONS:
            raise DiffshegError(f"phonetic normalise must be one of {', '.join(NORMALISATIONS)}, "
                                f"got {self.normalise!r}")

    def metadata(self) -> str:
        """The JSON stored with the encoder's weights."""
        return json.dumps({**asdict(self), "phones": list(PHONES)})

    @classmethod
    def from_metadata(cls, metadata: str, source: str) -> "PhoneticConfig":
        try:
            values = json.loads(metadata)
        except ValueError as exc:
            raise CheckpointError(f"{source}: its phonetic encoder settings are not valid JSON ({exc}); "
                                  "export the model again") from None
        if tuple(values.get("phones", ())) != PHONES:
            raise CheckpointError(f"{source}: its phonetic encoder uses another phone set; retrain it "
                                  "with this version (python -m diffsheg_core train-phonetic)")
        known = {f.name for f in fields(cls)}
        values = {k: tuple(v) if k == "dilations" else v for k, v in values.items() if k in known}
        values.setdefault("normalise", "none")  # encoders saved before the option existed
        return cls(**values)


def encoder_speech(audio: Audio) -> Audio:
    """`audio` as the recogniser hears it: taken down to ENCODER_RATE when faster (soxr HQ,
    which band-limits it to the encoder's 8 kHz), then to MEL_RATE. Every path to the encoder
    (whole recordings, pieces of long ones, their level, training) goes through here."""
    return resample(resample(audio, min(audio.sample_rate, ENCODER_RATE)), MEL_RATE)


def recogniser_frames(n_samples: int, sample_rate: int, cfg: PhoneticConfig) -> int:
    """Recogniser frames `raw_log_mel` gives for `n_samples` at `sample_rate` (centred frames)."""
    rate = min(sample_rate, ENCODER_RATE)
    return 1 + resampled_length(resampled_length(n_samples, sample_rate, rate), rate, MEL_RATE) // cfg.hop


def raw_log_mel(audio: Audio, cfg: PhoneticConfig) -> np.ndarray:
    """(n_mels, N) log10 power mel at the recogniser rate, before any level normalisation,
    of `encoder_speech(audio)`."""
    speech = encoder_speech(audio)
    return np.log10(mel_spectrogram(speech.samples, cfg.n_fft, cfg.hop, cfg.n_mels) + 1e-5)


def log_mel(audio: Audio, cfg: PhoneticConfig, level: np.ndarray | None = None) -> np.ndarray:
    """(n_mels, N) log10 power mel at the recogniser rate; frame j is centred at j * hop.

    With `normalise = "utterance"` each band's mean over the recording is taken off
    (cepstral mean normalisation), so most of a microphone's gain and colouring drop out
    (not all: frames at the 1e-5 floor keep their level). On the real take 2_scott_0_1_1
    this raised the bilabial probability at p/b/m from 0.37 to 0.41 (same corpus, same
    network). With the shipped encoder the phone picked per frame stays the same for 89 %
    of frames when the recording is 5 dB louder or quieter (v2's encoder, on raw levels: 85 %).

    `level`: (n_mels, 1) band means to take off instead of `audio`'s own (a piece of a long
    recording takes off the whole recording's)."""
    return normalised(raw_log_mel(audio, cfg), cfg, level)


def normalised(raw: np.ndarray, cfg: PhoneticConfig, level: np.ndarray | None = None) -> np.ndarray:
    """`raw_log_mel`'s (n_mels, N) frames as the encoder takes them (`log_mel`): with
    `normalise = "utterance"` less `level`, or their own band means when None."""
    if cfg.normalise == "utterance":
        raw = raw - (raw.mean(axis=1, keepdims=True) if level is None else level)
    return raw.astype(np.float32)


def receptive_field(cfg: PhoneticConfig) -> int:
    """Recogniser frames the encoder looks at on either side of a frame."""
    return sum(d * (cfg.kernel // 2) for d in cfg.dilations)


def stack_posteriors(post: np.ndarray, n_frames: int, subframes: int, first: int = 0,
                     total: int | None = None, offset: int = 0) -> np.ndarray:
    """(n_frames, subframes * P) features of motion frames first .. first + n_frames - 1:
    motion frame i (at i / fps) gets the recogniser frames centred from 2 subframes before
    it to 1 after (4 subframes), clipped to the recording's `total` recogniser frames.
    `post` holds the recording's recogniser frames from `offset` on (default: all of them)."""
    s = subframes
    total = len(post) if total is None else total
    index = np.arange(first, first + n_frames)[:, None] * s + np.arange(-(s // 2), s - s // 2)[None]
    return post[np.clip(index, 0, total - 1) - offset].reshape(n_frames, -1).astype(np.float32)


def fingerprint(cfg: PhoneticConfig, weights: dict[str, np.ndarray]) -> str:
    """A short hash of the encoder's settings and weights (for feature caches)."""
    h = hashlib.sha256(cfg.metadata().encode())
    for name, value in sorted(weights.items()):
        h.update(name.encode() + np.asarray(value, np.float32).tobytes())
    return h.hexdigest()[:16]


def phonetic_encoding(cfg: PhoneticConfig, posteriors: Posteriors, key: str) -> SpeechEncoding:
    """The encoder as a model's second speech input."""
    return SpeechEncoding(f"phonetic:{key}", lambda audio, n: stack_posteriors(
        posteriors(log_mel(audio, cfg)), n, cfg.subframes))
