"""Which torch device work runs on."""

from __future__ import annotations

import torch

from ..errors import DiffshegError


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """'auto' picks CUDA when present, else the CPU; asking for an absent GPU is an error."""
    name = str(device)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise DiffshegError("device 'cuda' was requested but no CUDA GPU is available to torch: "
                            "use device 'auto' or 'cpu', or install a CUDA build of torch (README)")
    if name not in ("cpu",) and not name.startswith("cuda"):
        raise DiffshegError(f"unknown device '{name}': use auto, cpu or cuda")
    try:
        return torch.device(name)
    except RuntimeError:
        raise DiffshegError(f"unknown device '{name}': use auto, cpu or cuda") from None
