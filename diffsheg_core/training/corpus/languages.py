"""The corpus's speech in languages other than English: espeak-ng reads words of each
language that Faker's locale data holds (its lorem word lists, or its names and places
where a locale has none), so that the phonetic encoder and the model hear other
languages' sounds. Their phones are mapped onto the one ARPAbet set the teacher's visemes
use (`phones.from_espeak`)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ...errors import DiffshegError


@dataclass(frozen=True)
class Language:
    """`code`: espeak-ng's voice name for it; `locale`: Faker's; `words`: 'lorem' (the
    locale's word list) or 'names' (its person and place names, for locales without one)."""

    code: str
    locale: str
    words: str = "lorem"


LANGUAGES = (
    Language("de", "de_DE"), Language("fr", "fr_FR"), Language("es", "es_ES"),
    Language("it", "it_IT"), Language("nl", "nl_NL"), Language("da", "da_DK"),
    Language("sv", "sv_SE", "names"), Language("pl", "pl_PL"), Language("cs", "cs_CZ"),
    Language("ru", "ru_RU"), Language("uk", "uk_UA"), Language("mk", "mk_MK"),
    Language("hy", "hy_AM"), Language("az", "az_AZ"), Language("fa", "fa_IR"),
    Language("ar", "ar_AA"), Language("hi", "hi_IN", "names"), Language("bn", "bn_BD"),
    Language("vi", "vi_VN"), Language("ja", "ja_JP", "names"),
)
"""Languages espeak-ng speaks well and Faker has words for. Mandarin, Greek, Thai and
Hebrew are left out: espeak-ng reads much of their text with its English voice (Debian's
espeak-ng has Mandarin's short dictionary only) or without vowels."""

BY_CODE = {language.code: language for language in LANGUAGES}

MIN_WORDS, MAX_WORDS = 5, 16


def check_languages(codes: list[str]) -> tuple[Language, ...]:
    """The named languages (['all']: every one), or an error naming the unknown ones and the
    choices."""
    if codes == ["all"]:
        return LANGUAGES
    unknown = [c for c in codes if c not in BY_CODE]
    if unknown:
        raise DiffshegError(f"unknown corpus language {', '.join(unknown)}: use some of "
                            f"{','.join(BY_CODE)} (or 'all')")
    return tuple(BY_CODE[c] for c in codes)


@lru_cache(maxsize=None)
def _faker(locale: str):
    try:
        from faker import Faker
    except ImportError as exc:
        raise DiffshegError("the corpus's other languages need Faker: pip install -e '.[train]'") from exc
    return Faker(locale)


def _words(language: Language, n: int) -> list[str]:
    fake = _faker(language.locale)
    if language.words == "lorem":
        return fake.words(n, unique=True)
    if language.code == "ja":  # espeak-ng reads kana, not kanji
        return [fake.last_kana_name() if i % 2 else fake.first_kana_name() for i in range(n)]
    return [(fake.first_name, fake.last_name, fake.city)[i % 3]() for i in range(n)]


def language_text(language: Language, rng: np.random.Generator) -> str:
    """A few seconds of words of `language`, in one or two phrases, drawn from `rng`."""
    _faker(language.locale).seed_instance(int(rng.integers(2**31)))
    words = _words(language, int(rng.integers(MIN_WORDS, MAX_WORDS + 1)))
    cut = int(rng.integers(2, len(words) - 1))
    return " ".join(words[:cut]) + ", " + " ".join(words[cut:]) + "."
