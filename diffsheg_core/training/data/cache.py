"""Feature cache: one npz per take, keyed by the content of its source files, so an edited
file is re-read and a renamed one is not."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from .take import Take

CACHE_VERSION = "1"
"""Bump when what a reader produces changes, so old cache entries are not reused."""


def content_key(paths: list[Path], settings: str) -> str:
    """SHA-256 over the bytes of `paths` (in order) and a description of the reader settings."""
    h = hashlib.sha256(f"{CACHE_VERSION}|{settings}".encode())
    for path in paths:
        h.update(path.name.encode() + b"\0")
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def _save(path: Path, take: Take) -> None:
    """Write atomically, so that a run killed mid-write leaves no broken entry."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "wb") as fh:
        extra = {} if take.extra is None else {"extra": take.extra}
        np.savez(fh, name=take.name, motion=take.motion, mel=take.mel, style=take.style, mask=take.mask,
                 **extra)
    os.replace(tmp, path)


def _load(path: Path) -> Take | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            return Take(str(z["name"]), z["motion"], z["mel"], int(z["style"]), z["mask"],
                        z["extra"] if "extra" in z.files else None)
    except (OSError, KeyError, ValueError):
        return None


def cached_take(cache_dir: str | Path | None, paths: list[Path], settings: str,
                build: Callable[[], Take]) -> Take:
    """The take from the cache when present, else `build()` (stored for next time)."""
    if cache_dir is None:
        return build()
    entry = Path(cache_dir) / f"{content_key(paths, settings)}.npz"
    take = _load(entry) if entry.is_file() else None
    if take is None:
        take = build()
        _save(entry, take)
    return take
