"""What a dataset reader finds on disk before reading anything: one `TakeSource` per take."""

from __future__ import annotations

import csv
import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path

from ...errors import DiffshegError

SPLITS = ("train", "val", "test")


@dataclass
class TakeSource:
    """The files of one take (role -> path), its style class, its split (None: the dataset
    has no split file) and the expected files that are not there."""

    name: str
    files: dict[str, Path]
    style: int
    split: str | None
    missing: list[str] = field(default_factory=list)

    @property
    def paths(self) -> list[Path]:
        return [self.files[k] for k in sorted(self.files)]


def speaker_style(name: str) -> int:
    """BEAT / BEAT2 take names start with the speaker number (1-based): '2_scott_0_1_1' -> 1."""
    m = re.match(r"(\d+)_", name)
    if not m or int(m.group(1)) < 1:
        raise DiffshegError(
            f"take '{name}' does not start with a speaker number ('<speaker>_<name>_...'), "
            "as BEAT names do; rename it or use the folder dataset")
    return int(m.group(1)) - 1


def read_split_csv(path: Path) -> dict[str, str]:
    """BEAT2's train_test_split.csv: columns `id` and `type` (train / val / test / additional)."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise DiffshegError(f"{path}: cannot read the split file ({exc})") from exc
    if not rows or not {"id", "type"} <= set(rows[0]):
        raise DiffshegError(f"{path}: expected a CSV with columns 'id' and 'type' "
                            "(train / val / test), as BEAT2's train_test_split.csv")
    return {r["id"].strip(): r["type"].strip().lower() for r in rows}


def hashed_split(name: str, val_fraction: float) -> str:
    """A stable train / val assignment by name, for datasets without a split file."""
    bucket = int(hashlib.sha256(name.encode()).hexdigest()[:8], 16) / 0xFFFFFFFF
    return "val" if bucket < val_fraction else "train"
