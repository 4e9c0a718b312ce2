"""`ModelConfig`: the sizes and switches of a UniEG network, apart from the network itself,
so the torch-free runtime (onnxruntime) reads a model file without importing torch."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Optional

SPEECH_ENCODERS = ("hubert", "phonetic")

# names used by model files and training settings written before the second speech input
# was named after what it is
_RENAMED = {"hubert_dim": "speech_dim", "hubert_latent": "speech_latent"}


@dataclass
class ModelConfig:
    """Sizes and switches of a UniEG network (defaults: the official BEAT model)."""

    gesture_dim: int = 141
    expression_dim: int = 51
    style_dim: int = 30           # one-hot speaker / style classes
    mel_dim: int = 128            # mel bands per motion frame
    audio_latent: int = 256       # width of the projected [mel | encoded mel] feature
    # The second speech input beside the mel, encoded per branch to speech_latent:
    # hubert (official, 1024-d), phonetic (the project's phone recogniser, stored in the
    # model file) or None (mel only).
    speech_encoder: Optional[str] = "hubert"
    speech_dim: int = 1024
    speech_latent: int = 128
    latent: int = 512
    layers: int = 8               # per branch
    ff: int = 1024
    heads: int = 8
    dropout: float = 0.0
    pe_period: int = 600          # sinusoidal PE, restarting in every window
    pe_length: int = 1200
    classifier_free: bool = False  # learned null condition for guidance
    # frames of a depthwise convolution over time in every layer of the gesture branch, beside
    # the linear attention (which sees only a window-wide summary, not a frame's neighbours);
    # 0: none (official)
    temporal_kernel: int = 0
    log_mel: bool = False         # feed log10(mel + 1e-5) instead of the raw power mel (official: raw)
    # the last `lower_dim` gesture channels (a whole-body layout's hips, legs and hips'
    # translation) made by a branch of their own, with `lower_layers` layers, fed the other
    # gesture channels' noisy motion and noise prediction as the gesture branch is fed the
    # expression's x0; 0: none (official)
    lower_dim: int = 0
    lower_layers: int = 1
    clip_len: int = 34            # frames per diffusion window (n_poses)
    fps: float = 15.0
    layout: str = "beat"

    def __post_init__(self):
        if self.speech_encoder is not None and self.speech_encoder not in SPEECH_ENCODERS:
            raise ValueError(f"speech_encoder must be one of {', '.join(SPEECH_ENCODERS)} or none, "
                             f"got {self.speech_encoder!r}")
        if not isinstance(self.lower_dim, int) or not 0 <= self.lower_dim < self.gesture_dim:
            raise ValueError(f"lower_dim must be a whole number from 0 to below gesture_dim ({self.gesture_dim}), "
                             f"got {self.lower_dim}")
        k = self.temporal_kernel
        if isinstance(k, bool) or not isinstance(k, int) or k < 0 or (k and k % 2 == 0):
            raise ValueError(f"temporal_kernel must be 0 (none) or an odd number of frames, "
                             f"got {self.temporal_kernel}")

    @property
    def dim(self) -> int:
        return self.gesture_dim + self.expression_dim

    @property
    def upper_dim(self) -> int:
        """The gesture channels the gesture branch makes (all but the lower branch's)."""
        return self.gesture_dim - self.lower_dim

    @property
    def has_speech_input(self) -> bool:
        """The network takes a second speech input beside the mel."""
        return self.speech_encoder is not None

    @property
    def phonetic_input(self) -> bool:
        """The second speech input is the phonetic encoder's (stored with the model)."""
        return self.speech_encoder == "phonetic"

    @property
    def time_embed_dim(self) -> int:
        return 4 * self.latent

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "ModelConfig":
        """From `to_dict` output or training settings; the older `use_hubert` / `hubert_*`
        names are read too."""
        values = {_RENAMED.get(k, k): v for k, v in values.items()}
        if "use_hubert" in values:
            uses = values.pop("use_hubert")
            values["speech_encoder"] = (values.get("speech_encoder") or "hubert") if uses else None
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown model configuration fields: {sorted(unknown)}")
        return cls(**values)

