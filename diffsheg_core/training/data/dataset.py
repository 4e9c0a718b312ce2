"""Datasets for training and evaluation: configuration, reading every take of a split
(through the BEAT, BEAT2, folder, corpus or FACEGOOD reader) with broken takes reported
and skipped, and the normalisation statistics."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

from tqdm import tqdm

from ...audio import SpeechEncoding, load_audio
from ...errors import DiffshegError
from ...rigs import BEAT_BODY, Layout
from . import beat, beat2, corpus, facegood, folder
from .cache import cached_take
from .normalise import NormStats, compute_stats, official_stats
from .sources import SPLITS, TakeSource, hashed_split
from .take import MAX_LENGTH_MISMATCH_S, Take

log = logging.getLogger(__name__)

READERS: dict[str, ModuleType] = {"beat": beat, "beat2": beat2, "folder": folder, "corpus": corpus,
                                  "facegood": facegood}


@dataclass
class DataConfig:
    """Where the data is and how it is cut into clips.

    kind: 'beat', 'beat2', 'folder', 'corpus' (the project's synthetic speech corpus) or
    'facegood' (real speech with a captured face and no body: training/data/facegood.py).
    stats: 'train' computes normalisation statistics from the training split; otherwise a
    folder with the official statistics files. style: the style class of every take of a
    'folder' or 'corpus' dataset (BEAT names carry theirs). whole_body: a corpus's hips,
    legs and hips' translation too (layout `beat_body`; teacher v4 and later makes them); a
    face-only dataset ('facegood') fits that layout too, its body masked out. pause
    ('facegood'): silences longer than this many seconds are cut to it, audio and face
    together, so words read one by one follow one another as in running speech (0: as
    recorded). face: 'data' (the takes' face is in the loss) or 'source' (left out of it, so
    with the run's keep_unsaid its channels learn the model fine-tuned from's prediction on
    this speech: rehearsal that keeps the face as it was while another dataset teaches it).
    """

    kind: str = "beat"
    root: str = ""
    fps: float = 15.0
    clip_len: int = 34
    stride: int = 10
    cache_dir: str | None = None
    stats: str = "train"
    val_fraction: float = 0.1
    style: int = 0
    max_length_mismatch: float = MAX_LENGTH_MISMATCH_S
    whole_body: bool = False
    pause: float = 0.0
    face: str = "data"

    def reader(self) -> ModuleType:
        if self.kind not in READERS:
            raise DiffshegError(f"unknown dataset kind '{self.kind}': choose one of {', '.join(READERS)}")
        return READERS[self.kind]

    @property
    def layout(self) -> Layout:
        if not self.whole_body:
            return self.reader().LAYOUT
        if not self.reader().WHOLE_BODY:
            raise DiffshegError(f"whole_body needs the project's corpus (kind = \"corpus\"): a '{self.kind}' "
                                "dataset holds no lower body in the beat layout")
        return BEAT_BODY


@dataclass
class TakeSet:
    """The usable takes of one split, and (name, reason) for every take that was skipped."""

    layout: Layout
    takes: list[Take]
    skipped: list[tuple[str, str]] = field(default_factory=list)


def find_sources(config: DataConfig, split: str) -> list[TakeSource]:
    if split not in SPLITS:
        raise DiffshegError(f"unknown split '{split}': choose one of {', '.join(SPLITS)}")
    root = Path(config.root)
    if not root.is_dir():
        raise DiffshegError(f"dataset folder '{root}' does not exist: check 'root' in the data configuration")
    sources = config.reader().find_takes(root)
    for s in sources:
        if s.split is None:
            s.split = hashed_split(s.name, config.val_fraction)
    return [s for s in sources if s.split == split]


def load_takes(config: DataConfig, split: str = "train", speech: SpeechEncoding | None = None) -> TakeSet:
    """Read (or take from the cache) every take of `split`; broken takes are logged and
    skipped. `speech`: the model's second speech input, computed for every take."""
    reader = config.reader()
    result = TakeSet(config.layout, [])
    settings = f"{config.kind}|{config.fps}|{config.style}|{config.max_length_mismatch}|{config.layout.name}"
    if speech is not None:
        settings += f"|{speech.key}"
    if config.pause:
        settings += f"|pause {config.pause}"
    for source in tqdm(find_sources(config, split), desc=f"reading {split} takes", unit="take",
                       disable=None, leave=False):
        try:
            if source.missing:
                raise DiffshegError(f"{source.name}: missing {', '.join(source.missing)}")
            take = cached_take(config.cache_dir, source.paths, settings,
                               lambda: with_speech(reader.read_take(source, config), source, speech))
        except DiffshegError as exc:
            result.skipped.append((source.name, str(exc)))
            log.warning("skipped take %s", exc)
            continue
        result.takes.append(take)
    return result


def with_speech(take: Take, source: TakeSource, speech: SpeechEncoding | None) -> Take:
    """`take` with its second speech input, computed from the take's audio (every reader
    aligns frame i of the take with time i / fps of its audio file)."""
    if speech is not None:
        take.extra = speech.encode(load_audio(source.files["audio"]), take.n_frames)
    return take


def normalisation(config: DataConfig, train: TakeSet) -> NormStats:
    """Statistics from the training takes, or the official ones from `config.stats`."""
    if config.stats == "train":
        return compute_stats(train.takes)
    return official_stats(train.layout, config.stats)
