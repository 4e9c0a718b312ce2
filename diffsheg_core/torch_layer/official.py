"""Reading official DiffSHEG checkpoints, which are torch pickles: `torch.load` with
`weights_only=True`. The rest of loading them (the state dict as numpy, the configuration
inferred from its shapes, the normalisation statistics) is numpy, in `official_checkpoints`;
`checkpoints` imports this module when it meets such a file.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import torch

from ..errors import CheckpointError


def read_official_pickle(path: Path) -> dict:
    """The unpickled contents of an official checkpoint, plain tensors and containers only
    (`weights_only=True`); damaged files and pickles that would run code raise CheckpointError."""
    damaged = (f"{path}: cannot read this torch checkpoint ({{}}); it is truncated, damaged or not a "
               "checkpoint at all: download it again")
    try:
        return torch.load(str(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        if "Unsupported operand" in str(exc):  # torch's word for bytes that are no pickle opcode
            raise CheckpointError(damaged.format("its pickle is damaged")) from None
        raise CheckpointError(
            f"{path}: refused to load: the file needs arbitrary code to unpickle ({exc}). "
            "Only plain tensors and containers are accepted; re-save the checkpoint's state "
            "dict with torch.save({'encoder': model.state_dict()}, path) in a trusted environment."
        ) from exc
    except (RuntimeError, OSError) as exc:  # torch's zip reader, the file system
        raise CheckpointError(damaged.format(exc)) from None
    except Exception:  # a damaged pickle raises many types (IndexError for 3 bytes, EOFError)
        raise CheckpointError(damaged.format("its pickle is damaged or cut short")) from None
