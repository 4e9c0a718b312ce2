"""`generate`: speech in, `Motion` out. The one entry point clients use."""

from __future__ import annotations

import threading
from functools import lru_cache
from pathlib import Path
from typing import Callable, Optional, Union

import numpy as np
import torch

from . import __version__
from .audio import Audio, SpeechEncoding, hubert_features, load_audio, load_hubert, mel_features
from .checkpoints import ModelBundle, load_model
from .diffusion import Schedule
from .devices import resolve_device
from .errors import DiffshegError
from .foppas import EpsFn, Foppas, FoppasConfig, FoppasStream, sample_long, with_overrides
from .model import ModelConfig
from .motion import Motion
from .phonetic import PhoneticEncoder, fingerprint
from .progress import ProgressCallback

AudioInput = Union[str, Path, np.ndarray, Audio]

_hubert_encoder = lru_cache(maxsize=1)(load_hubert)  # the 1.2 GB model is loaded once per process


def style_onehot(bundle: ModelBundle, style: int) -> torch.Tensor:
    n = bundle.config.style_dim
    if isinstance(style, bool) or not isinstance(style, (int, np.integer)) or not 0 <= style < n:
        raise DiffshegError(f"style must be a whole number from 0 to {n - 1} for this model, got {style!r}")
    onehot = torch.zeros(1, n)
    onehot[0, int(style)] = 1.0
    return onehot


def resolve_guidance(bundle: ModelBundle, guidance: Optional[float]) -> Optional[float]:
    if not bundle.config.classifier_free:
        if guidance not in (None, 1.0):
            raise DiffshegError(f"model {bundle.model_id} was trained without classifier-free guidance: "
                                "leave the guidance scale at 1")
        return None
    scale = bundle.guidance if guidance is None else float(guidance)
    if scale is not None and not 0.0 <= scale <= 10.0:
        raise DiffshegError(f"guidance scale must be between 0 and 10, got {scale}")
    return scale


def check_skip_guidance(scale: float) -> float:
    if not 0.0 <= scale <= 1.0:
        raise DiffshegError(f"skip guidance scale must be between 0 and 1, got {scale}")
    return float(scale)


def resolve_skip_guidance(bundle: ModelBundle, skip_guidance: Optional[float]) -> Optional[float]:
    """The gesture skip-guidance scale to sample with: the model's default for None, off for 0."""
    scale = bundle.skip_guidance if skip_guidance is None else skip_guidance
    if scale is None:
        return None
    return check_skip_guidance(scale) or None  # 0 turns it off


def speech_encoding(config: ModelConfig, phonetic: Optional[PhoneticEncoder] = None,
                    hubert_path: Optional[str] = None, hubert_quirk: bool = False,
                    device: str = "cpu") -> Optional[SpeechEncoding]:
    """The model's second speech input beside the mel (None for mel-only models): HuBERT,
    loaded once per process, or the phonetic encoder stored with the model."""
    if not config.use_hubert:
        return None
    if config.phonetic_input:
        if phonetic is None:
            raise DiffshegError("this model takes phonetic features, but no phonetic encoder came with "
                                "it: export the model again from its training run")
        return SpeechEncoding(f"phonetic:{fingerprint(phonetic)}", phonetic.features)
    encoder = _hubert_encoder(hubert_path, device)
    return SpeechEncoding(f"hubert:{hubert_path or 'cache'}:{hubert_quirk}",
                          lambda audio, n: hubert_features(audio, n, official_quirk=hubert_quirk,
                                                           encoder=encoder))


def speech_features(bundle: ModelBundle, audio: Audio, hubert_path: Optional[str] = None,
                    hubert_quirk: bool = False, device: str = "cpu") -> torch.Tensor:
    """(T, F) conditioning frames: mel, then the second speech input when the model has one."""
    mel = mel_features(audio, fps=bundle.config.fps)
    parts = [mel]
    encoding = speech_encoding(bundle.config, bundle.phonetic, hubert_path, hubert_quirk, device)
    if encoding is not None:
        parts.append(encoding.encode(audio, len(mel)))
    return torch.from_numpy(np.concatenate(parts, axis=1).astype(np.float32))


def uses_prior(bundle: ModelBundle, config: FoppasConfig) -> bool:
    """Whether later windows start from the model's gesture prior (it has one and `config` asks)."""
    return bundle.prior is not None and config.prior_start


def build_sampling(bundle: ModelBundle, config: FoppasConfig, style: int = 0,
                   guidance: Optional[float] = None, autocast: Optional[torch.dtype] = None,
                   skip_guidance: Optional[float] = None
                   ) -> tuple[Foppas, Callable[[torch.Tensor], EpsFn]]:
    """The FOPPAS sampler for `bundle` with `config`, and the factory that binds the model,
    style and guidance scales to one window's speech features. Bad settings raise DiffshegError."""
    try:
        sampler = Foppas(Schedule.linear(), config, bundle.config.clip_len, bundle.config.dim,
                         proposal=bundle.prior.propose if uses_prior(bundle, config) else None)
    except ValueError as exc:
        raise DiffshegError(str(exc)) from None
    make = make_eps_fn_factory(bundle, sampler, style_onehot(bundle, style),
                               resolve_guidance(bundle, guidance), autocast,
                               resolve_skip_guidance(bundle, skip_guidance))
    return sampler, make


def make_eps_fn_factory(bundle: ModelBundle, sampler: Foppas, style: torch.Tensor,
                        guidance: Optional[float], autocast: Optional[torch.dtype],
                        skip_guidance: Optional[float] = None) -> Callable[[torch.Tensor], EpsFn]:
    """Bind model, style and guidance scales; the result binds one window's speech features."""
    cfg, sched, device = bundle.config, sampler.schedule, bundle.device
    style = style.to(device)
    if guidance == 1.0:  # uncond + 1 * (cond - uncond) is the conditioned pass alone: skip the null pass
        guidance = None

    def make(cond: torch.Tensor) -> EpsFn:
        mel = cond[..., : cfg.mel_dim]
        hubert = cond[..., cfg.mel_dim:] if cfg.use_hubert else None

        @torch.inference_mode()
        def eps_fn(x: torch.Tensor, index: int) -> torch.Tensor:
            idx = torch.tensor([index], device=device)
            with torch.autocast(device.type, dtype=autocast, enabled=autocast is not None):
                eps = bundle.model(x, sched.model_timesteps(idx), mel, hubert, style,
                                   sched.x0_coefs(idx, x), guidance, skip_guidance=skip_guidance)
            return eps.float()

        return eps_fn

    return make


def generate(audio: AudioInput, sample_rate: Optional[int] = None, *,
             model: Union[None, str, Path, ModelBundle] = None, seed: int = 0,
             overlap: Optional[int] = None, steps: Optional[int] = None, style: int = 0,
             guidance: Optional[float] = None, skip_guidance: Optional[float] = None,
             sampling: Optional[FoppasConfig] = None, device: str = "auto", precision: str = "fp32",
             hubert_path: Optional[str] = None, hubert_quirk: bool = False,
             progress: Optional[ProgressCallback] = None,
             cancel: Optional[threading.Event] = None) -> Motion:
    """Generate body, hand, head and face motion for a speech recording.

    audio: a file path, an array (with `sample_rate`) or a loaded `Audio`.
    model: None for the bundled default, a checkpoint path, or a loaded `ModelBundle`.
    guidance / skip_guidance: classifier-free and gesture skip-guidance scales (None: the
    model's defaults; 1 and 0 turn them off).
    sampling: FOPPAS settings (default: the model's); `steps` / `overlap` override them.
    precision: 'fp32', or 'bf16' / 'fp16' autocast on CUDA.
    progress: called after every diffusion step; cancel: checked before every step.
    The result has one frame per 1/fps s of audio (fps of the model, 15 for BEAT).
    """
    torch_device = resolve_device(device)
    bundle = model if isinstance(model, ModelBundle) else load_model(model, device=torch_device)
    if bundle.device != torch_device:
        bundle.model.to(torch_device)
    speech = audio if isinstance(audio, Audio) else load_audio(audio, sample_rate)
    config = with_overrides(sampling or bundle.sampling, steps=steps, overlap=overlap)
    autocast = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}.get(precision, "bad")
    if autocast == "bad" or (autocast is not None and torch_device.type != "cuda"):
        raise DiffshegError(f"precision '{precision}' is not available on {torch_device.type}: "
                            "use fp32 (or bf16/fp16 on a CUDA GPU)")
    sampler, make_eps_fn = build_sampling(bundle, config, style, guidance, autocast, skip_guidance)

    cond = speech_features(bundle, speech, hubert_path, hubert_quirk, str(torch_device))
    generator = torch.Generator().manual_seed(int(seed))
    normalised = sample_long(sampler, make_eps_fn, cond, generator, torch_device, progress, cancel)
    return to_motion(bundle, normalised.cpu().numpy(), meta={
        "model_id": bundle.model_id, "trained": bundle.trained, "seed": int(seed),
        "audio_file": speech.path, "sample_rate": speech.sample_rate, "style": int(style),
        "guidance": resolve_guidance(bundle, guidance),
        "skip_guidance": resolve_skip_guidance(bundle, skip_guidance),
        "steps": config.steps, "overlap": config.overlap, "prior_start": uses_prior(bundle, config),
        "clip_len": bundle.config.clip_len,
        "device": str(torch_device), "software": f"diffsheg_core {__version__}",
    })


def to_motion(bundle: ModelBundle, normalised: np.ndarray, meta: dict) -> Motion:
    """Denormalise (T, D) model output and split it into named rotations and face weights."""
    layout = bundle.layout
    rotations, face = layout.split(bundle.denormalise(normalised).astype(np.float32))
    if layout.name == "beat":
        face = np.clip(face, 0.0, 1.0)  # ARKit weights are defined on [0, 1]
    return Motion(fps=bundle.config.fps, rig=layout.name, joint_names=list(layout.joint_names),
                  rotations=rotations, face_names=list(layout.face_names), face=face, meta=meta)


def open_stream(bundle: ModelBundle, *, seed: int = 0, style: int = 0,
                guidance: Optional[float] = None, skip_guidance: Optional[float] = None,
                sampling: Optional[FoppasConfig] = None, device: str = "auto") -> FoppasStream:
    """A `FoppasStream` for live use: push (n, F) speech features from `speech_features`
    (computed on audio chunks whose lengths are multiples of 1/fps s), get normalised
    motion frames back; `to_motion` turns them into a Motion. For a model with the phonetic
    encoder, compute the features over a buffer of the last few seconds and push its newest
    frames: the encoder looks 0.53 s either side and takes off the level of what it is given."""
    torch_device = resolve_device(device)
    bundle.model.to(torch_device)
    sampler, make = build_sampling(bundle, sampling or bundle.sampling, style, guidance,
                                   skip_guidance=skip_guidance)
    return FoppasStream(sampler, make, torch.Generator().manual_seed(int(seed)), torch_device)
