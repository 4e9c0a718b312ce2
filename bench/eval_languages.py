"""Lip-sync of the bundled model on real speech in languages other than English (issue 29, item 3;
issue 42).

First, against a real Mandarin face (issue 42): the bundled model (seeds 0 and 1) on the 5
takes of ../shared/data/lang_capture/zh_facegood (read Mandarin, one speaker, the face
solved onto FACEGOOD's 116-blendshape rig at 30 fps, mapped onto ARKit at 15 fps by
diffsheg_core.training.metrics.facegood, whose docstring gives the mapping and how well
it holds), per take:
  jaw r whole / voiced   Pearson correlation of our jawOpen with the captured jaw opening
              (mouth_stretch_c) over the whole clip / over the voiced frames (qc.voiced_frames,
              as the English figure), each the best within +-qc.MAX_LAG; per seed in brackets
  x English   that figure over the same figure of the model's jaw against BEAT2's captured
              SMPL-X jaw of the English take 2_scott_0_1_1 (its last row)
  capture / model follow level   r voiced of the captured jaw / of our jawOpen with the
              voice's level (qc.voiced_level_correlation: the loudness figure below)
  voiced share, items  share of voiced frames; voiced runs (gaps under 0.3 s merged) and
              their median length: the takes are single syllables and words with pauses
each take also joined into running speech (metrics.facegood.joined: silences cut to 0.1 s,
audio and face together, so the words follow one another; its own mean row): the takes hold
no running speech, and this is the closest to it they give. Then a second table of the other
mapped mouth channels' agreement (whole / voiced, means over seeds). 1114_2_05 is the take
the tests and the fine-tunes (weights/default_face_zh.toml, default_face_zh_own.toml) hold out.
Both tables come first with the model's shared face, then again with each language's own face
the model carries (`--language zh`: the bundled model's Mandarin face). --facegood-only stops there.

Then runs the bundled model with its default settings (seeds 0 and 1) on every recording in
../shared/data/audio/lang/ and on the real English recordings of ../shared/data (the take
beat2/2_scott_0_1_1 and audio/2_scott_0_3_3, 2_scott_0_4_4, 12_zhao_2_3_3,
2_scott_0_103_103_28s; Forrest_tts is synthetic and left out), and prints per file and per
language (means over seeds, then over files):
  r whole     mouth-to-voice correlation over the whole clip (diffsheg_core.qc)
  r voiced    the same over voiced frames only (qc.voiced_mouth_voice_correlation)
  x English   r voiced against English's (the issue's goal: at least 0.9); for a language's
              mean, ± its standard error over the language's recordings
  closures/s  lips shutting during speech per second of voiced speech (qc.lip_closures), a
              proxy for closing on p/b/m that needs no phone timings
  per p/b/m   those closures per p, b or m of the recording's phones
  jaw v/b     mouth opening at open vowels over at p/b/m (the model card's jaw contrast)
  follows     correlation over voiced frames of the mouth opening with the jaw the teacher's
              visemes give the recording's phones (lipsync.viseme_jaw): how closely the
              mouth follows what is said, whatever the loudness
  teacher r   r voiced of that viseme jaw itself: what lip-sync that follows the phones
              exactly scores on the loudness figure in that language (its ceiling, unless
              the mouth also follows the voice's level)
The phones are the take's TextGrid, elsewhere the transcript spoken by espeak-ng and warped
onto the recording (training.metrics.transcript_phones: approximate; on the take it gives
2.34 where the TextGrid gives 2.43); none where espeak-ng cannot read the script (Chinese
characters and pinyin) or there is no transcript; Japanese kanji are read as kana through UniDic
(fugashi)
and, for the English take, the phone-timed lip-sync of the model card (jaw open at open
vowels over bilabials, mouthClose at bilabials minus at open vowels), and the take's own
motion capture as the reference for the loudness figure: what a real face scores on it
(the BEAT2 SMPL-X jaw) and how closely the model's jaw and the exact visemes' agree with
that captured jaw over voiced frames.

--linear-probe prints how much of the captured Mandarin jaw the speech features the network is
fed already hold: a ridge regression from them (its log-mel and the phonetic encoder's
posteriors, +-2 frames about each) to the captured jaw of the four training takes, as read and
joined, its strength chosen by leave-one-take-out over those four; then its agreement with the
held-out take's captured jaw, as read and joined (the same figure as the model's, which it
stands beside). A linear map learnt from 7.4 min of one reader is no animation, but where it
agrees better than the network does, the speech input is not what limits the network.

--loudness-gain K ... measures what the goal would cost if met by making the mouth follow the
voice's level: every jawOpen is scaled by the level's amplitude ratio to the recording's
median voiced level to the power K (6 dB louder opens 2**(K/2) times wider), and the x English
ratios, the take's phone-following, its agreement with the captured jaw and its 99th
percentile jawOpen (1 is a fully open ARKit jaw) are printed for each K.

    python bench/eval_languages.py [--seeds 0 1] [--steps N] [--model FILE] [--loudness-gain K ...]
                                   [--facegood-only] [--linear-probe]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np

from diffsheg_core.audio import load_audio
from diffsheg_core.checkpoints import load_model
from diffsheg_core.motion import Motion
from diffsheg_core.pipeline import generate
from diffsheg_core.qc import (lip_closures, mouth_voice_correlation, speech_level,
                              voiced_frames, voiced_level_correlation, voiced_mouth_voice_correlation)
from diffsheg_core.training.evaluate import load_reference
from diffsheg_core.training.metrics import face_channel, mouth_opening, phone_tier, phoneme_contrast, read_textgrid
from diffsheg_core.training.metrics.facegood import (ARKIT_FROM_RIG, HELD_OUT, FacegoodTake, agreement,
                                                     arkit_curves, joined, measure_take, read_names, read_take,
                                                     take_names)
from diffsheg_core.training.metrics.lipsync import (BILABIALS, OPEN_VOWELS, base_phone, phone_following,
                                                     phone_middles, values_at, viseme_jaw,
                                                     voiced_reference_correlation)
from diffsheg_core.training.metrics.transcript_phones import transcript_phones

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
LANG = DATA / "audio" / "lang"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
TAKE_TEXTGRID = DATA / "beat2" / "2_scott_0_1_1.TextGrid"
TAKE_CAPTURE = DATA / "beat2" / "2_scott_0_1_1.npz"
FACEGOOD = DATA / "lang_capture" / "zh_facegood"
ENGLISH = (TAKE_WAV, *(DATA / "audio" / name for name in (
    "2_scott_0_3_3.wav", "2_scott_0_4_4.wav", "12_zhao_2_3_3.wav", "2_scott_0_103_103_28s.wav")))
ESPEAK_VOICES = {"de": "de", "es": "es", "fr": "fr", "hi": "hi", "ja": "ja", "ru": "ru", "sv": "sv"}
"""Languages whose transcripts espeak-ng reads (its zh voice cannot read pinyin or characters;
Japanese goes through transcript_phones' kana reading)."""


def language(path: Path) -> str:
    return "en" if path.parent != LANG else path.name.split("_", 1)[0]


def timed_phones(path: Path, audio) -> Optional[list]:
    """Phone timings of a recording: the take's TextGrid, else its transcript spoken by
    espeak-ng and warped onto it (training.metrics.transcript_phones, approximate); None
    where there is no transcript espeak-ng can read."""
    if path == TAKE_WAV:
        return phone_tier(read_textgrid(TAKE_TEXTGRID))
    sidecar = path.with_suffix(".txt")
    voice = ESPEAK_VOICES.get(language(path))
    if voice is None or not sidecar.is_file():
        return None
    return transcript_phones(audio.samples, audio.sample_rate, sidecar.read_text(encoding="utf-8"), voice)


@dataclass
class Row:
    language: str
    file: str
    seconds: float
    whole: float
    voiced: float
    closures_per_s: float
    per_bilabial: Optional[float]
    jaw_open: list[float]
    jaw_bilabial: list[float]
    follows: Optional[float] = None
    teacher: Optional[float] = None


def measure(path: Path, motions: list[Motion]) -> Row:
    """Figures of one recording, means over its motions (one per seed)."""
    audio = load_audio(path)
    whole, voiced, rate, closures = [], [], [], []
    phones = timed_phones(path, audio)
    jaw_open, jaw_bilabial, follows = [], [], []
    for m in motions:
        whole.append(mouth_voice_correlation(m, audio.samples, audio.sample_rate))
        voiced.append(voiced_mouth_voice_correlation(m, audio.samples, audio.sample_rate))
        shut = len(lip_closures(m, audio.samples, audio.sample_rate))
        voiced_seconds = voiced_frames(audio.samples, audio.sample_rate, m.fps, m.n_frames).sum() / m.fps
        rate.append(shut / voiced_seconds if voiced_seconds else float("nan"))  # no voiced frame: no rate
        closures.append(shut)
        if phones:
            mouth = mouth_opening(m)
            jaw_open += list(values_at(mouth, m.fps, phone_middles(phones, OPEN_VOWELS, m.n_frames / m.fps)))
            jaw_bilabial += list(values_at(mouth, m.fps, phone_middles(phones, BILABIALS, m.n_frames / m.fps)))
            follows.append(phone_following(mouth, m.fps, phones, audio.samples, audio.sample_rate))
    bilabials = sum(base_phone(p.label) in BILABIALS for p in phones) if phones else 0
    return Row(language(path), path.stem, audio.duration, float(np.mean(whole)), float(np.mean(voiced)),
               float(np.mean(rate)), float(np.mean(closures)) / bilabials if bilabials else None,
               jaw_open, jaw_bilabial, float(np.mean(follows)) if follows else None,
               voiced_level_correlation(viseme_jaw(phones, motions[0].n_frames, motions[0].fps), motions[0].fps,
                                        audio.samples, audio.sample_rate) if phones else None)


def _jaw_ratio(rows: list[Row]) -> Optional[float]:
    """Mouth opening at open vowels over at p/b/m, pooled over the rows' phones."""
    opened = [x for r in rows for x in r.jaw_open]
    shut = [x for r in rows for x in r.jaw_bilabial]
    return float(np.mean(opened) / np.mean(shut)) if opened and shut and np.mean(shut) > 0 else None


def take_contrast(motions: list[Motion]) -> str:
    grid = read_textgrid(TAKE_TEXTGRID)
    phones = phone_tier(grid)
    jaw = [phoneme_contrast(mouth_opening(m), m.fps, phones)["ratio"] for m in motions]
    close = [phoneme_contrast(face_channel(m, "mouthClose"), m.fps, phones) for m in motions]
    shut = [c["bilabial"] - c["open"] for c in close]
    audio = load_audio(TAKE_WAV)
    words = " ".join(w.label for w in grid["words"] if w.label.strip())
    approximate = transcript_phones(audio.samples, audio.sample_rate, words, "en-us")
    follows = [phone_following(mouth_opening(m), m.fps, approximate, audio.samples, audio.sample_rate)
               for m in motions]
    return (f"English take 2_scott_0_1_1 with its phone timings: jaw open at open vowels / at p,b,m "
            f"{np.mean(jaw):.2f} (seeds {', '.join(f'{x:.2f}' for x in jaw)}); mouthClose at p,b,m minus "
            f"at open vowels {np.mean(shut):.2f}; follows the phones of its words spoken by espeak-ng and "
            f"warped onto it, as the other languages' are timed, at {np.mean(follows):.2f}")


def captured_jaw(fps: float) -> np.ndarray:
    """The take's real jaw opening: the BEAT2 SMPL-X capture's jaw rotation angle."""
    return mouth_opening(load_reference(TAKE_CAPTURE, fps=fps))


def agrees(curve: np.ndarray, real: np.ndarray, fps: float, audio) -> float:
    """Correlation of a mouth curve of the take with its captured jaw over voiced frames."""
    return voiced_reference_correlation(curve, real, fps, audio.samples, audio.sample_rate)


def captured_face(motions: list[Motion]) -> str:
    """The take's motion capture as the reference for the loudness figure."""
    audio, fps, n = load_audio(TAKE_WAV), motions[0].fps, motions[0].n_frames
    real = captured_jaw(fps)
    visemes = viseme_jaw(phone_tier(read_textgrid(TAKE_TEXTGRID)), n, fps)
    model = [agrees(mouth_opening(m), real, fps, audio) for m in motions]
    exact = agrees(visemes, real, fps, audio)
    return (f"English take's motion capture (BEAT2 SMPL-X jaw, {fps:g} fps): r voiced "
            f"{voiced_level_correlation(real, fps, audio.samples, audio.sample_rate):.2f}; agreement with "
            f"that captured jaw over voiced frames: the model {np.mean(model):.2f} "
            f"(seeds {', '.join(f'{x:.2f}' for x in model)}), the exact visemes {exact:.2f}")


def voiced_runs(voiced: np.ndarray, fps: float, gap: float = 0.3) -> list[float]:
    """Seconds of each run of voiced frames, runs under `gap` s apart merged: the items spoken."""
    frames = np.flatnonzero(voiced)
    if not len(frames):
        return []
    breaks = np.flatnonzero(np.diff(frames) > gap * fps + 1)
    starts, ends = frames[np.r_[0, breaks + 1]], frames[np.r_[breaks, len(frames) - 1]]
    return list((ends - starts + 1) / fps)


def _seeds(values: list[float]) -> str:
    return f"{np.mean(values):.2f} ({', '.join(f'{x:.2f}' for x in values)})"


JOIN_PAUSE = 0.1
"""Seconds the joined takes' silences are cut to (metrics.facegood.joined)."""


def facegood_tables(takes: dict[str, tuple[FacegoodTake, list[Motion]]], english: list[Motion]) -> str:
    """The captured-face figures of the FACEGOOD Mandarin takes against English's (issue 42):
    label -> (take, the model's motions on its audio); labels ending in 'joined' are the
    takes with their pauses cut (a mean row each for the takes as read and as joined)."""
    audio = load_audio(TAKE_WAV)
    real = captured_jaw(english[0].fps)
    en = [agreement(mouth_opening(m), real, m.fps, audio) for m in english]
    en_whole, en_voiced = float(np.mean([w for w, _ in en])), float(np.mean([v for _, v in en]))
    head = ["take", "seconds", "voiced share", "items (median s)", "jaw r whole", "x English", "jaw r voiced",
            "x English", "capture follows level", "model follows level"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    others = [name for name in ARKIT_FROM_RIG if name != "jawOpen"]
    head2 = ["take", *others]
    lines2 = ["| " + " | ".join(head2) + " |", "|" + "---|" * len(head2)]
    for group in ("read", "joined"):
        whole_all, voiced_all, shares, items, per_channel = [], [], [], [], {n: [] for n in others}
        chosen = {label: v for label, v in takes.items() if label.endswith("joined") == (group == "joined")}
        for label, (take, motions) in chosen.items():
            a, fps, n = take.audio, motions[0].fps, motions[0].n_frames
            figures = [measure_take(m, take) for m in motions]
            whole = [f["jawOpen"][0] for f in figures]
            voiced = [f["jawOpen"][1] for f in figures]
            whole_all.append(np.mean(whole))
            voiced_all.append(np.mean(voiced))
            marks = voiced_frames(a.samples, a.sample_rate, fps, n)
            runs = voiced_runs(marks, fps)
            shares.append(marks.mean())
            items.extend(runs)
            jaw = arkit_curves(take, fps, n)["jawOpen"]
            label = f"{label} (held out)" if label.startswith(HELD_OUT) else label
            lines.append(
                f"| {label} | {a.duration:.1f} | {marks.mean():.2f} | {len(runs)} ({np.median(runs):.2f}) | "
                f"{_seeds(whole)} | {np.mean(whole) / en_whole:.2f} | {_seeds(voiced)} | "
                f"{np.mean(voiced) / en_voiced:.2f} | "
                f"{voiced_level_correlation(jaw, fps, a.samples, a.sample_rate):.2f} | "
                f"{np.mean([voiced_mouth_voice_correlation(m, a.samples, a.sample_rate) for m in motions]):.2f} |")
            cells = []
            for channel in others:
                pair = np.array([f[channel] for f in figures])
                per_channel[channel].append(pair.mean(0))
                still = np.isnan(pair).all()  # the take never uses the channel's rig shapes
                cells.append("n/a (still)" if still else f"{pair[:, 0].mean():.2f} / {pair[:, 1].mean():.2f}")
            lines2.append(f"| {label} | " + " | ".join(cells) + " |")
        if not chosen:
            continue
        whole_mean, voiced_mean = float(np.mean(whole_all)), float(np.mean(voiced_all))
        lines.append(f"| **zh mean of {len(chosen)} {group}** | | {np.mean(shares):.2f} | {len(items)} "
                     f"({np.median(items):.2f}) | **{whole_mean:.2f}** | **{whole_mean / en_whole:.2f}** | "
                     f"**{voiced_mean:.2f}** | **{voiced_mean / en_voiced:.2f}** | | |")
        means = [np.nanmean(per_channel[c], 0) for c in others]
        lines2.append(f"| **zh mean of {len(chosen)} {group}** | "
                      + " | ".join(f"**{w:.2f} / {v:.2f}**" for w, v in means) + " |")
    fps = english[0].fps
    en_marks = voiced_frames(audio.samples, audio.sample_rate, fps, english[0].n_frames)
    en_runs = voiced_runs(en_marks, fps)
    lines.append(
        f"| en {TAKE_WAV.stem} (BEAT2 SMPL-X jaw) | {audio.duration:.1f} | {en_marks.mean():.2f} | "
        f"{len(en_runs)} ({np.median(en_runs):.2f}) | {_seeds([w for w, _ in en])} | 1 | "
        f"{_seeds([v for _, v in en])} | 1 | "
        f"{voiced_level_correlation(real, fps, audio.samples, audio.sample_rate):.2f} | "
        f"{np.mean([voiced_mouth_voice_correlation(m, audio.samples, audio.sample_rate) for m in english]):.2f} |")
    return ("Captured Mandarin face (FACEGOOD zh_facegood, mapped onto ARKit), jawOpen against the captured jaw "
            f"(as read, and joined: silences cut to {JOIN_PAUSE:g} s, words following one another):\n"
            + "\n".join(lines) + "\n\nThe other mapped mouth channels, r whole / r voiced (means over seeds):\n"
            + "\n".join(lines2))


def facegood_takes(model, seeds: list[int], options: dict) -> dict[str, tuple[FacegoodTake, list[Motion]]]:
    """Every FACEGOOD take as read and joined, with the model's motions on its audio."""
    names = read_names(FACEGOOD / "bs_names.json")
    found = {}
    for name in take_names(FACEGOOD):
        take = read_take(FACEGOOD, name, names)
        for label, version in ((name, take), (f"{name} joined", joined(take, JOIN_PAUSE))):
            found[label] = (version, [generate(version.audio, model=model, seed=s, **options) for s in seeds])
    return found


PROBE_CONTEXT = 2
"""Frames either side of each frame the linear probe reads."""
PROBE_STRENGTHS = (1e2, 1e3, 1e4, 1e5)
"""Ridge strengths the linear probe chooses from (leave-one-take-out on the training takes)."""


def probe_features(bundle, network, audio) -> np.ndarray:
    """(frames, features) the network's speech input at each frame and PROBE_CONTEXT either side."""
    from diffsheg_core.speech_features import speech_features

    f = speech_features(bundle, network, audio)
    mel = np.log10(f.mel + 1e-5) if bundle.config.log_mel else f.mel
    x = mel if f.speech is None else np.concatenate([mel, f.speech], 1)
    k = PROBE_CONTEXT
    padded = np.concatenate([np.repeat(x[:1], k, 0), x, np.repeat(x[-1:], k, 0)])
    return np.concatenate([padded[i:i + len(x)] for i in range(2 * k + 1)], 1).astype(np.float64)


def _ridge_fits(x: np.ndarray, y: np.ndarray, strengths) -> dict:
    """strength -> predict(features): ridge regressions of `y` on the standardised `x`, one per
    strength, sharing one standardisation and one Gram matrix."""
    mean, spread = x.mean(0), x.std(0) + 1e-6
    a = (x - mean) / spread
    gram, target = a.T @ a, a.T @ (y - y.mean())

    def fit(strength):
        w = np.linalg.solve(gram + strength * np.eye(len(gram)), target)
        return lambda z: ((z - mean) / spread) @ w
    return {strength: fit(strength) for strength in strengths}


def linear_probe(bundle) -> str:
    """The --linear-probe line (see the module docstring)."""
    from diffsheg_core.runtime.backends import open_network

    network = open_network(bundle)
    names = read_names(FACEGOOD / "bs_names.json")
    train, held = {}, {}
    for name in take_names(FACEGOOD):
        take = read_take(FACEGOOD, name, names)
        for version in (take, joined(take, JOIN_PAUSE)):
            x = probe_features(bundle, network, version.audio)
            entry = (version, x, arkit_curves(version, bundle.config.fps, len(x))["jawOpen"])
            (held if name == HELD_OUT else train.setdefault(name, {}))[version.name] = entry

    def fits(names_used, strengths):
        parts = [e for n in names_used for e in train[n].values()]
        return _ridge_fits(np.concatenate([x for _, x, _ in parts]), np.concatenate([y for _, _, y in parts]),
                           strengths)

    def scores(predict, entries):
        return [agreement(predict(x), y, bundle.config.fps, v.audio)[1] for v, x, y in entries]

    left_out = {strength: [] for strength in PROBE_STRENGTHS}  # each training take scored by the others' fit
    for n in train:
        for strength, predict in fits([m for m in train if m != n], PROBE_STRENGTHS).items():
            left_out[strength].append(np.mean(scores(predict, train[n].values())))
    chosen = {strength: float(np.mean(found)) for strength, found in left_out.items()}
    strength = max(chosen, key=chosen.get)
    figures = dict(zip(held, scores(fits(list(train), [strength])[strength], held.values())))
    return (f"Linear probe (ridge {strength:g} on the speech features, +-{PROBE_CONTEXT} frames, fitted to the "
            f"captured jaw of the {len(train)} training takes): r voiced on the held-out {HELD_OUT} as read "
            f"{figures[HELD_OUT]:.2f}, joined {figures[HELD_OUT + '-joined']:.2f}; leave-one-take-out over the "
            f"training takes {chosen[strength]:.2f}")


def with_loudness_gain(motion: Motion, audio, k: float) -> Motion:
    """`motion` with jawOpen times (level's amplitude / the median voiced level's) ** k,
    the level within +-12 dB of that median."""
    level = speech_level(audio.samples, audio.sample_rate, motion.fps, motion.n_frames)
    voiced = voiced_frames(audio.samples, audio.sample_rate, motion.fps, motion.n_frames)
    median = np.median(level[voiced]) if voiced.any() else level.max()
    face = motion.face.copy()
    face[:, motion.face_names.index("jawOpen")] *= 10 ** (k * np.clip(level - median, -12, 12) / 20)
    return replace(motion, face=face)


def loudness_gain_table(generated: dict[Path, list[Motion]], gains: list[float]) -> str:
    """What meeting the goal through the voice's level costs, for each gain (see --loudness-gain)."""
    audios = {path: load_audio(path) for path in generated}
    languages = list(dict.fromkeys(language(p) for p in generated if language(p) != "en"))
    take, audio = generated[TAKE_WAV], audios[TAKE_WAV]
    real, phones = captured_jaw(take[0].fps), phone_tier(read_textgrid(TAKE_TEXTGRID))
    head = ["gain K", "English r voiced", *languages, "take follows", "agrees w/ capture", "jawOpen p99"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k in gains:
        voiced: dict[str, list[float]] = {}
        for path, motions in generated.items():
            a = audios[path]
            voiced.setdefault(language(path), []).append(np.mean([voiced_mouth_voice_correlation(
                with_loudness_gain(m, a, k), a.samples, a.sample_rate) for m in motions]))
        english = np.mean(voiced["en"])
        mouths = [(mouth_opening(with_loudness_gain(m, audio, k)), m.fps) for m in take]
        follows = np.mean([phone_following(c, fps, phones, audio.samples, audio.sample_rate) for c, fps in mouths])
        agree = np.mean([agrees(c, real, fps, audio) for c, fps in mouths])
        p99 = np.mean([np.percentile(c, 99) for c, _ in mouths])
        ratios = " | ".join(f"{np.mean(voiced[lang]) / english:.2f}" for lang in languages)
        lines.append(f"| {k:g} | {english:.2f} | {ratios} | {follows:.2f} | {agree:.2f} | {p99:.2f} |")
    return "\n".join(lines)


def _mean_of(values) -> Optional[float]:
    known = [v for v in values if v is not None]
    return float(np.mean(known)) if known else None


def _cell(x: Optional[float], digits: int = 2) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def table(rows: list[Row]) -> str:
    english = float(np.mean([r.voiced for r in rows if r.language == "en"]))
    head = ["language", "file", "seconds", "r whole", "r voiced", "x English", "closures/s", "per p/b/m",
            "jaw v/b", "follows", "teacher r"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for lang in dict.fromkeys(r.language for r in rows):
        group = [r for r in rows if r.language == lang]
        for r in group:
            lines.append(f"| {lang} | {r.file} | {r.seconds:.1f} | {r.whole:.2f} | {r.voiced:.2f} | "
                         f"{r.voiced / english:.2f} | {r.closures_per_s:.2f} | {_cell(r.per_bilabial)} | "
                         f"{_cell(_jaw_ratio([r]))} | {_cell(r.follows)} | {_cell(r.teacher)} |")
        known = [r.per_bilabial for r in group if r.per_bilabial is not None]
        voiced = float(np.mean([r.voiced for r in group]))
        spread = (f" ± {np.std([r.voiced for r in group], ddof=1) / np.sqrt(len(group)) / english:.2f}"
                  if len(group) > 1 else "")
        lines.append(f"| **{lang}** | mean of {len(group)} | {sum(r.seconds for r in group):.1f} | "
                     f"{np.mean([r.whole for r in group]):.2f} | **{voiced:.2f}** | **{voiced / english:.2f}**{spread} | "
                     f"{np.mean([r.closures_per_s for r in group]):.2f} | "
                     f"{_cell(float(np.mean(known)) if known else None)} | **{_cell(_jaw_ratio(group))}** | "
                     f"{_cell(_mean_of(r.follows for r in group))} | {_cell(_mean_of(r.teacher for r in group))} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=None, help="sampling steps (default: the model's)")
    parser.add_argument("--model", default=None, help="model file (default: the bundled model)")
    parser.add_argument("--loudness-gain", type=float, nargs="+", default=None, metavar="K",
                        help="also measure the mouth made to follow the voice's level by these gains (0: as made)")
    parser.add_argument("--linear-probe", action="store_true",
                        help="also how much of the captured Mandarin jaw a linear map of the speech input gets")
    parser.add_argument("--facegood-only", action="store_true",
                        help="only the captured Mandarin face's figures (issue 42)")
    args = parser.parse_args()
    bundle = load_model(args.model)
    options = {} if args.steps is None else {"steps": args.steps}
    started = time.perf_counter()
    generated = {TAKE_WAV: [generate(TAKE_WAV, model=bundle, seed=s, **options) for s in args.seeds]}
    measured_takes = 0
    for language in [None, *sorted(bundle.faces)]:  # the shared face, then each language's own (issue 42)
        takes = facegood_takes(bundle, args.seeds, {**options, "language": language})
        measured_takes += len(takes)
        print("The shared face (no --language):" if language is None else
              f"The model's own face for {language} (--language {language}); English as above, with the shared face:")
        print(facegood_tables(takes, generated[TAKE_WAV]))
        print()
    if args.linear_probe:
        print(linear_probe(bundle))
        print()
    if args.facegood_only:
        print(f"{measured_takes} takes, seeds {args.seeds}: {time.perf_counter() - started:.0f} s")
        return
    for path in (*ENGLISH, *sorted(LANG.glob("*.wav"))):
        if path not in generated:
            generated[path] = [generate(path, model=bundle, seed=s, **options) for s in args.seeds]
    rows = [measure(path, motions) for path, motions in generated.items()]
    print(table(rows))
    print()
    print(take_contrast(generated[TAKE_WAV]))
    print(captured_face(generated[TAKE_WAV]))
    if args.loudness_gain:
        print()
        print(loudness_gain_table(generated, args.loudness_gain))
    print(f"{len(rows)} recordings, seeds {args.seeds}: {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
