"""HuBERT speech features, the second speech input of the official DiffSHEG models:
`load_hubert` loads facebook/hubert-large-ls960-ft (with the `transformers` package, from a
local folder or the Hugging Face cache, never downloading), `hubert_features` computes
(n_frames, 1024) features on the motion frames. What needs neither torch nor transformers
(the constants; `audio.hubert_status` and `audio.require_hubert`, which say whether HuBERT
can run) is in `audio`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..audio import (HUBERT_CHUNK, HUBERT_HOW_TO, HUBERT_KERNEL, HUBERT_RATE, HUBERT_STRIDE, LOAD_RATE, Audio,
                     cached_hubert_folder, require_hubert, resample)
from ..errors import AudioError, DiffshegError
from .devices import resolve_device


@dataclass
class HubertEncoder:
    """A loaded HuBERT model and its feature extractor; load once with `load_hubert`, reuse."""

    model: Any
    feature_extractor: Any
    device: Any


def load_hubert(model_path: str | os.PathLike | None = None, device: str = "cpu") -> HubertEncoder:
    """Load HuBERT from `model_path` (a folder) or the Hugging Face cache; never downloads."""
    require_hubert(model_path)
    torch_device = _torch_device(device)
    from transformers import HubertModel, Wav2Vec2FeatureExtractor

    folder = Path(model_path) if model_path is not None else cached_hubert_folder()
    try:
        model = HubertModel.from_pretrained(folder, local_files_only=True)
        if (folder / "preprocessor_config.json").is_file():
            extractor = Wav2Vec2FeatureExtractor.from_pretrained(folder, local_files_only=True)
        else:
            extractor = Wav2Vec2FeatureExtractor(
                feature_size=1, sampling_rate=HUBERT_RATE, padding_value=0.0, do_normalize=True)
    except (OSError, ValueError) as error:
        raise AudioError(f"HuBERT model in '{folder}' cannot be loaded ({error}). {HUBERT_HOW_TO}") from None
    return HubertEncoder(model.eval().to(torch_device), extractor, torch_device)


def _torch_device(device: str) -> torch.device:
    """torch.device for 'auto' (CUDA when present), 'cpu', 'cuda' or 'cuda:N'."""
    try:
        return resolve_device(device)
    except DiffshegError as exc:
        raise AudioError(f"HuBERT: {exc}") from None


def hubert_features(
    audio: Audio,
    n_frames: int,
    model_path: str | os.PathLike | None = None,
    device: str = "cpu",
    official_quirk: bool = False,
    encoder: HubertEncoder | None = None,
) -> np.ndarray:
    """(n_frames, 1024) float32 HuBERT last hidden states, resampled to the motion frames.

    HuBERT runs on 16 kHz audio. `official_quirk=True` instead feeds the 22050 Hz
    audio as if it were 16 kHz, as the official DiffSHEG inference code does (it
    passes librosa.load's output straight to HuBERT). The 50 Hz states are
    interpolated linearly with align_corners=True (first and last states land on the
    first and last motion frames), as the official checkpoints were trained; each
    motion frame then reads HuBERT from 12 to 75 ms after its own time, at any length.
    `encoder` (from `load_hubert`) avoids reloading the model; otherwise it is
    loaded from `model_path` or the Hugging Face cache onto `device`.
    """
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise AudioError(f"n_frames must be a positive whole number of motion frames, got {n_frames!r}")
    encoder = encoder if encoder is not None else load_hubert(model_path, device)
    speech = resample(audio, LOAD_RATE if official_quirk else HUBERT_RATE)
    states = _hubert_states(encoder, speech)
    resized = F.interpolate(states.T[None], size=int(n_frames), mode="linear", align_corners=True)
    return np.ascontiguousarray(resized[0].T.numpy(), dtype=np.float32)


def _hubert_states(encoder: HubertEncoder, speech: Audio) -> torch.Tensor:
    """(frames, 1024) float32 CPU tensor: one state per 320 input samples, in 1000-frame chunks."""
    values = encoder.feature_extractor(
        speech.samples, sampling_rate=HUBERT_RATE, return_tensors="pt").input_values
    n = values.shape[1]
    expected = (n - (HUBERT_KERNEL - HUBERT_STRIDE)) // HUBERT_STRIDE
    if expected < 1:
        raise AudioError(f"{speech.name} is too short for HuBERT (needs {HUBERT_KERNEL} samples at 16 kHz)")
    chunk_len = HUBERT_CHUNK + HUBERT_KERNEL - HUBERT_STRIDE
    chunks = [values[:, start:start + chunk_len] for start in range(0, n, HUBERT_CHUNK)]
    with torch.inference_mode():
        states = torch.cat([
            encoder.model(chunk.to(encoder.device)).last_hidden_state[0].float().cpu()
            for chunk in chunks if chunk.shape[1] >= HUBERT_KERNEL])
    if len(states) < expected:  # a tail shorter than one receptive field: repeat the last state
        states = torch.cat([states, states[-1:].expand(expected - len(states), -1)])
    return states[:expected]
