"""The torch backend of `runtime.backends`: a model's networks as torch modules, numpy in,
numpy out, behind the same calls as the onnx backend's `OnnxNetwork`.
`runtime.backends.open_network` imports this module only when the torch backend is chosen.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..checkpoints import ModelBundle
from ..errors import DiffshegError
from .devices import resolve_device
from .model import PhoneticEncoder, UniEG, load_state_strict


class TorchNetwork:
    """A model's networks as torch modules, on the CPU or a CUDA GPU."""

    name = "torch"

    def __init__(self, bundle: ModelBundle, device: str, precision: str, threads: Optional[int] = None):
        if threads is not None:  # CPU threads, as `runtime.backends.open_network` asks
            torch.set_num_threads(threads)
        self.device = resolve_device(device)
        self.autocast = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}[precision]
        if self.autocast is not None and self.device.type != "cuda":
            raise DiffshegError(f"precision '{precision}' is not available on {self.device.type}: "
                                "use fp32 (or bf16/fp16 on a CUDA GPU)")
        self.model = UniEG(bundle.config)
        load_state_strict(self.model, bundle.weights, bundle.source)
        self.model.to(self.device).eval()
        self.phonetic = None
        if bundle.phonetic is not None:
            self.phonetic = PhoneticEncoder(bundle.phonetic)
            load_state_strict(self.phonetic, bundle.phonetic_weights, f"{bundle.source} (phonetic encoder)")
            self.phonetic.to(self.device).eval()

    def _in(self, value: Optional[np.ndarray]):
        return None if value is None else torch.from_numpy(np.ascontiguousarray(value)).to(self.device)

    def _out(self, value) -> np.ndarray:
        return value.float().cpu().numpy()

    def _call(self, fn, *args):
        with torch.inference_mode(), torch.autocast(self.device.type, dtype=self.autocast,
                                                    enabled=self.autocast is not None):
            return fn(*(self._in(a) for a in args))

    def expression(self, expression, timesteps, mel, speech, style, null):
        eps, audio = self._call(self.model.expression, expression, timesteps, mel, speech, style, null)
        return self._out(eps), self._out(audio)

    def gesture(self, gesture, timesteps, audio, speech, expression_x0, style, null, attend):
        return self._out(self._call(self.model.gesture, gesture, timesteps, audio, speech, expression_x0,
                                    style, null, attend))

    def phone_posteriors(self, mel: np.ndarray) -> np.ndarray:
        logits = self._call(self.phonetic, mel[None])
        return self._out(logits[0].float().softmax(0).T)
