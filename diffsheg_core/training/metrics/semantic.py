"""BEAT's semantic relevance annotations, as per-frame weights for SRGR.

One file per take: `<take>.txt` beside the take's .bvh in the BEAT release, `sem/<take>.txt`
in the BEAT / BEAT2 training layouts. Each line is one annotated gesture, tab separated,
no header: name, start (s), end (s), duration (s), score, keywords. BEAT's evaluation gives
the frame at time i / fps the score of the first span with start <= t <= end, and 0 to
frames outside every span.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import DiffshegError

COLUMNS = ("name", "start", "end", "duration", "score", "keywords")


@dataclass(frozen=True)
class SemanticSpan:
    name: str
    start: float
    end: float
    score: float
    keywords: str = ""


def read_semantic(path: str | Path) -> list[SemanticSpan]:
    """The annotated spans of one take, in file order."""
    path = Path(path)
    if not path.is_file():
        raise DiffshegError(f"{path}: semantic annotation file not found; give the take's BEAT "
                            "sem/<take>.txt file")
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    return [_parse_line(path, number, line) for number, line in enumerate(lines, 1) if line.strip()]


def _parse_line(path: Path, number: int, line: str) -> SemanticSpan:
    fields = line.split("\t")
    where = f"{path}, line {number}"
    if len(fields) not in (len(COLUMNS) - 1, len(COLUMNS)):
        raise DiffshegError(
            f"{where}: expected {len(COLUMNS)} tab-separated columns ({', '.join(COLUMNS)}; the "
            f"keywords may be left out), got {len(fields)}; fix the line or use the file as BEAT publishes it")
    try:
        start, end, _duration, score = (float(f) for f in fields[1:5])
    except ValueError:
        raise DiffshegError(f"{where}: start, end, duration and score must be numbers (seconds, "
                            f"score), got {fields[1:5]}; fix the line") from None
    if end < start or score < 0:
        raise DiffshegError(f"{where}: a span needs end >= start and a score >= 0, got start {start}, "
                            f"end {end}, score {score}; fix the line")
    return SemanticSpan(fields[0].strip(), start, end, score, fields[5].strip() if len(fields) > 5 else "")


def semantic_weights(spans: list[SemanticSpan], n_frames: int, fps: float) -> np.ndarray:
    """(n_frames,) SRGR weights: each frame takes the score of the first span covering
    its time, 0 outside every span."""
    t = np.arange(n_frames) / fps
    weights = np.zeros(n_frames)
    for span in reversed(spans):  # earlier spans overwrite later ones: the first match wins
        weights[(t >= span.start) & (t <= span.end)] = span.score
    return weights


def find_semantic(motion_path: str | Path) -> Path | None:
    """The annotation of a BEAT take stored next to its motion, if any: `<take>.txt` beside a
    .bvh (the BEAT release) or `sem/<take>.txt` beside the motion's folder (training layouts)."""
    path = Path(motion_path)
    candidates = [path.parent.parent / "sem" / f"{path.stem}.txt"]
    if path.suffix.lower() == ".bvh":
        candidates.insert(0, path.with_suffix(".txt"))
    return next((c for c in candidates if c.is_file()), None)
