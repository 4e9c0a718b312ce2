"""Speech synthesis with timed phones: the voices the corpus draws from and one entry
point, `synthesize`, over the espeak-ng, festival and flite back ends."""

from __future__ import annotations

import ctypes.util
import shutil
from dataclasses import dataclass

import numpy as np

from ...errors import DiffshegError
from .phones import Phone

ESPEAK_ACCENTS = (
    "en-us", "en-us", "en-us", "en", "en-gb-x-rp", "en-gb-scotland", "en-029", "en-us-nyc",
    "en-gb-x-gbclan", "en-gb-x-gbcwmd",
)
"""espeak-ng English voices by the names its library accepts ("en" is British English; en-us
weighted up: the product's users speak mostly US English)."""

ESPEAK_VARIANTS = (
    "", "m1", "m2", "m3", "m4", "m5", "m6", "m7", "m8", "f1", "f2", "f3", "f4", "f5",
    "klatt", "klatt2", "klatt3", "klatt4", "Alex", "Alicia", "Andy", "Annie", "aunty", "belinda",
    "benjamin", "caleb", "david", "ed", "edward", "Gene", "john", "linda", "max", "Michael",
    "paul", "quincy", "rob", "robert", "steph", "travis", "victor", "zac", "norbert", "shelby",
    "grandpa", "grandma", "Lee", "Mike", "adam", "Andrea",
)
"""Human-sounding voice variants (whisper, robot and effect variants left out)."""

FESTIVAL_VOICES = ("kal_diphone", "ked_diphone", "cmu_us_slt_arctic_hts")
"""US English festival voices from Debian (festvox-kallpc16k, festvox-kdlpc16k, festvox-us-slt-hts)."""


@dataclass(frozen=True)
class VoiceSpec:
    """A voice and its speaking style. `rate` (words per minute), `pitch` and
    `pitch_range` (0-100) and `word_gap` (10 ms units) are espeak-ng parameters;
    festival and flite voices use `stretch` (duration factor) instead, flite also
    `f0_shift` (pitch factor)."""

    engine: str
    name: str
    rate: int = 175
    pitch: int = 50
    pitch_range: int = 50
    word_gap: int = 0
    stretch: float = 1.0
    f0_shift: float = 1.0

    @property
    def language(self) -> str:
        """The language it speaks: an espeak-ng voice's language code ('en-us', 'de',
        'cmn'); festival's and flite's voices are English."""
        return self.name.split("+")[0] if self.engine == "espeak" else "en"


@dataclass
class Synthesis:
    """Synthesised speech: float32 mono samples and the phones timed on them."""

    samples: np.ndarray
    sample_rate: int
    phones: list[Phone]
    voice: VoiceSpec

    @property
    def duration(self) -> float:
        return len(self.samples) / self.sample_rate


FLITE_VOICES = ("cmu_us_rms", "cmu_us_slt", "cmu_us_awb")
"""Flite's clustergen voices in Debian's flite package: US male, US female, Scottish male."""

ENGINES = ("espeak", "festival", "flite")

_ENGINE_WEIGHTS = {"espeak": 0.4, "festival": 0.25, "flite": 0.35}
"""How often each engine speaks when all are allowed: espeak-ng brings the most voices and
accents, festival and flite (statistical parametric voices) sound nearer a human voice."""


def engine_available(engine: str) -> bool:
    """Whether a synthesiser's program or library is installed (espeak-ng is checked when
    it first speaks: it is always installed with the project's system packages)."""
    if engine == "festival":
        return shutil.which("festival") is not None
    if engine == "flite":
        return ctypes.util.find_library("flite") is not None
    return engine == "espeak"


def random_voice(rng: np.random.Generator, engines: tuple[str, ...] = ENGINES) -> VoiceSpec:
    """Draw an engine (by `_ENGINE_WEIGHTS` among `engines`), a voice and a speaking style."""
    weights = np.array([_ENGINE_WEIGHTS[e] for e in engines])
    engine = engines[int(rng.choice(len(engines), p=weights / weights.sum()))]
    if engine == "festival":
        return VoiceSpec("festival", str(rng.choice(FESTIVAL_VOICES, p=[0.25, 0.25, 0.5])),
                         stretch=float(rng.uniform(0.85, 1.25)))
    if engine == "flite":
        return VoiceSpec("flite", str(rng.choice(FLITE_VOICES)), stretch=float(rng.uniform(0.85, 1.25)),
                         f0_shift=float(rng.uniform(0.85, 1.2)))
    return espeak_voice(rng, str(rng.choice(ESPEAK_ACCENTS)))


def espeak_voice(rng: np.random.Generator, language: str) -> VoiceSpec:
    """An espeak-ng voice of `language` (a voice name such as 'en-us' or 'de') with a drawn
    variant and speaking style."""
    variant = str(rng.choice(ESPEAK_VARIANTS))
    return VoiceSpec(
        "espeak", f"{language}+{variant}" if variant else language,
        rate=int(rng.integers(130, 215)), pitch=int(rng.integers(25, 80)),
        pitch_range=int(rng.integers(30, 95)), word_gap=int(rng.choice([0, 0, 0, 1, 2])),
    )


def synthesize(text: str, voice: VoiceSpec) -> Synthesis:
    """Speak `text`; the phones are timed exactly as the synthesiser placed them."""
    if not text.strip():
        raise DiffshegError("cannot synthesise empty text")
    if voice.engine == "espeak":
        from .espeak import synthesize as speak
    elif voice.engine == "festival":
        from .festival import synthesize as speak
    elif voice.engine == "flite":
        from .flite import synthesize as speak
    else:
        raise DiffshegError(f"unknown speech engine {voice.engine!r}: use one of {', '.join(ENGINES)}")
    return speak(text, voice)
