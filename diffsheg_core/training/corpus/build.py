"""Build the training corpus: synthesise, augment and teach utterances in parallel until
the requested hours of speech exist. Resumable: utterance i is fully determined by the
seed and i, finished utterances are listed in `manifest.jsonl` and skipped on a rerun, and
asking for more hours adds to what is there."""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import soundfile as sf

from ...audio import Audio
from ...errors import DiffshegError
from .augment import SAMPLE_RATE, AugmentSpec, augment, random_augment
from .languages import Language, language_text
from .synthesis import ENGINES, VoiceSpec, engine_available, espeak_voice, random_voice, synthesize
from .teacher import TEACHER_VERSION, save_utterance, teach
from .texts import load_texts

MANIFEST = "manifest.jsonl"
SUMMARY = "corpus.json"


@dataclass(frozen=True)
class BuildConfig:
    """What to build: `hours` of English speech and `language_hours` of speech in the
    other `languages` into `out`, with `jobs` worker processes."""

    out: Path
    hours: float
    jobs: int = 2
    seed: int = 0
    engines: tuple[str, ...] = ENGINES
    text_files: tuple[Path, ...] | None = None
    mocap: Path | None = None
    languages: tuple[Language, ...] = ()
    language_hours: float = 0.0


@dataclass(frozen=True)
class UtteranceSpec:
    """Everything that decides utterance `index`."""

    index: int
    text: str
    voice: VoiceSpec
    augment: AugmentSpec
    teacher_seed: int

    @property
    def name(self) -> str:
        return f"{self.index:06d}"

    @property
    def language(self) -> str:
        """'en' for every English voice and accent, else the voice's language."""
        return "en" if self.voice.language.startswith("en") else self.voice.language

    @property
    def folder(self) -> str:
        return f"utt/{self.index // 1000:03d}"


def utterance_specs(texts: list[str], seed: int, engines: tuple[str, ...],
                    start: int = 0) -> Iterator[UtteranceSpec]:
    """Utterances start, start + 1, ...: texts in a seeded order (repeating with other
    voices after the whole text source is used), voice, augmentation and teacher seed
    drawn from (seed, index)."""
    order = np.random.default_rng(seed).permutation(len(texts))
    index = start
    while True:
        rng = np.random.default_rng([seed, index])
        yield UtteranceSpec(index, texts[order[index % len(texts)]], random_voice(rng, engines),
                            random_augment(rng), int(rng.integers(2**31)))
        index += 1


LANGUAGE_INDEX_START = 500_000
"""Utterances in other languages are numbered from here, apart from the English ones, so
that asking for more of either leaves every utterance made as it was."""


def language_specs(languages: tuple[Language, ...], seed: int) -> Iterator[UtteranceSpec]:
    """Utterances LANGUAGE_INDEX_START, ...: language, words, espeak-ng voice, augmentation
    and teacher seed drawn from (seed, index)."""
    index = LANGUAGE_INDEX_START
    while True:
        rng = np.random.default_rng([seed, index])
        language = languages[int(rng.integers(len(languages)))]
        yield UtteranceSpec(index, language_text(language, rng), espeak_voice(rng, language.code),
                            random_augment(rng), int(rng.integers(2**31)))
        index += 1


def make_utterance(spec: UtteranceSpec, out: Path, mocap: Path | None = None) -> dict:
    """Synthesise, augment, teach and write one utterance; its manifest record."""
    from .gestures import load_library

    speech = synthesize(spec.text, spec.voice)
    rng = np.random.default_rng(spec.teacher_seed)
    samples, phones = augment(speech.samples, speech.sample_rate, speech.phones, spec.augment, rng)
    folder = out / spec.folder
    folder.mkdir(parents=True, exist_ok=True)
    wav = folder / f"{spec.name}.wav"
    motion = teach(Audio(samples, SAMPLE_RATE, str(wav.relative_to(out))), phones, seed=spec.teacher_seed,
                   library=load_library(str(mocap) if mocap else None))
    info = {"index": spec.index, "text": spec.text, "voice": asdict(spec.voice),
            "language": spec.language, "augment": spec.augment.to_dict(), "teacher_seed": spec.teacher_seed,
            "teacher_version": TEACHER_VERSION, "style": motion.meta["style"]["name"]}
    npz = save_utterance(folder / f"{spec.name}.npz", motion, phones, info)
    part = wav.with_name(wav.name + ".part")
    sf.write(part, samples, SAMPLE_RATE, subtype="PCM_16", format="WAV")
    part.replace(wav)
    return info | {"wav": str(wav.relative_to(out)), "npz": str(npz.relative_to(out)),
                   "duration": len(samples) / SAMPLE_RATE, "frames": motion.n_frames}


def _safe_make(spec: UtteranceSpec, out: Path, mocap: Path | None) -> dict:
    """make_utterance, with a failure (odd text the synthesiser rejects) as a record."""
    try:
        return make_utterance(spec, out, mocap)
    except DiffshegError as exc:
        return {"index": spec.index, "error": str(exc)}


def read_manifest(out: Path) -> dict[int, dict]:
    """Finished (or failed) utterances by index; records whose files are gone are dropped."""
    path = out / MANIFEST
    records: dict[int, dict] = {}
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut short by an interrupted build
            if "error" in rec or ((out / rec["wav"]).is_file() and (out / rec["npz"]).is_file()):
                records[int(rec["index"])] = rec
    return records


def _engines(config: BuildConfig) -> tuple[str, ...]:
    unknown = [e for e in config.engines if e not in ENGINES]
    if unknown:
        raise DiffshegError(f"unknown speech engine {', '.join(unknown)}: use some of {', '.join(ENGINES)}")
    if not config.engines:
        raise DiffshegError(f"no speech engine named: use some of {', '.join(ENGINES)}")
    missing = [e for e in config.engines if not engine_available(e)]
    if missing:
        present = [e for e in config.engines if e not in missing]
        leave_out = f", or build without them: --engines {','.join(present)}" if present else ""
        raise DiffshegError(f"speech engine {', '.join(missing)} is not installed: run `bash "
                            f"tools/install_system_packages.sh --corpus`{leave_out}")
    return tuple(config.engines)


def _size_bytes(out: Path) -> int:
    return sum(p.stat().st_size for p in (out / "utt").rglob("*") if p.is_file())


MAX_FAILURES_IN_A_ROW = 20


def _make(pool: ProcessPoolExecutor, manifest, config: BuildConfig, specs: Iterator[UtteranceSpec],
          indices: range, target: float, done: dict[int, dict], bar) -> float:
    """Make utterances from `specs` (skipping finished ones) until `target` seconds of
    utterances numbered in `indices` exist; the seconds made."""
    specs = (s for s in specs if s.index not in done)
    have = sum(r.get("duration", 0.0) for i, r in done.items() if i in indices)
    bar.update(round(min(have, target)))
    made, failed_in_a_row = 0.0, 0
    pending: set[Future] = set()
    while have < target or pending:
        while have < target and len(pending) < 2 * config.jobs:
            pending.add(pool.submit(_safe_make, next(specs), config.out, config.mocap))
        finished, pending = wait(pending, return_when=FIRST_COMPLETED)
        for fut in finished:
            if fut.cancelled():
                continue
            rec = fut.result()
            manifest.write(json.dumps(rec) + "\n")
            manifest.flush()
            done[rec["index"]] = rec
            failed_in_a_row = failed_in_a_row + 1 if "error" in rec else 0
            if failed_in_a_row >= MAX_FAILURES_IN_A_ROW:  # a setup problem, not odd texts
                for other in pending:
                    other.cancel()
                raise DiffshegError(f"the last {failed_in_a_row} utterances all failed, the last "
                                    f"with: {rec['error']}")
            if "error" not in rec:
                have += rec["duration"]
                made += rec["duration"]
                bar.update(round(have) - round(have - rec["duration"]))
        if have >= target:
            for fut in pending:
                fut.cancel()
            pending = {f for f in pending if not f.cancelled()}
    return made


def build(config: BuildConfig, progress: bool = True) -> dict:
    """Build (or extend) the corpus; returns the summary also written to corpus.json."""
    from tqdm import tqdm

    if config.hours <= 0:
        raise DiffshegError(f"--hours must be positive, got {config.hours}")
    if config.language_hours < 0 or (config.language_hours > 0) != bool(config.languages):
        raise DiffshegError("--language-hours and --languages go together: name the languages and "
                            "the hours of speech wanted in them")
    if config.jobs < 1:
        raise DiffshegError(f"--jobs must be at least 1, got {config.jobs}")
    engines = _engines(config)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    texts = load_texts(list(config.text_files) if config.text_files else None)
    done = read_manifest(out)
    started = time.time()
    bar = tqdm(total=round(3600 * (config.hours + config.language_hours)), unit="s", desc="speech",
               disable=not progress)
    with open(out / MANIFEST, "a", encoding="utf-8") as manifest, \
            ProcessPoolExecutor(max_workers=config.jobs) as pool:
        bar.set_description("speech, English" if config.languages else "speech")
        made = _make(pool, manifest, config, utterance_specs(texts, config.seed, engines),
                     range(LANGUAGE_INDEX_START), config.hours * 3600.0, done, bar)
        if config.languages:
            bar.set_description("speech, other languages")  # one bar over both targets, phase by phase
            made += _make(pool, manifest, config, language_specs(config.languages, config.seed),
                          range(LANGUAGE_INDEX_START, 2**31), config.language_hours * 3600.0, done, bar)
    bar.close()
    elapsed = time.time() - started
    ok = [r for r in done.values() if "error" not in r]
    summary = {
        "utterances": len(ok), "failed": len(done) - len(ok),
        "hours": sum(r["duration"] for r in ok) / 3600.0, "size_bytes": _size_bytes(out),
        "seconds_this_run": elapsed, "speech_seconds_this_run": made,
        "speech_seconds_per_second": made / elapsed if elapsed > 0 else 0.0,
        "config": {k: str(v) for k, v in asdict(config).items()}, "engines": list(engines),
        "languages": {lang: round(sum(r["duration"] for r in ok if r.get("language", "en") == lang) / 3600, 3)
                      for lang in sorted({r.get("language", "en") for r in ok})},
        "teacher_version": TEACHER_VERSION, "cpu_count": os.cpu_count(),
    }
    (out / SUMMARY).write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
    return summary
