"""The corpus's other languages: espeak-ng speaks every listed language, its phonemes land
on the one ARPAbet set (lips closing on bilabials, no blind guesses), and a build adds
them beside the English utterances without touching those."""

from __future__ import annotations

import numpy as np
import pytest

from system_tools import require_path

from diffsheg_core.errors import DiffshegError
from diffsheg_core.training.corpus.__main__ import main
from diffsheg_core.training.corpus.build import LANGUAGE_INDEX_START, BuildConfig, build, read_manifest
from diffsheg_core.training.corpus.espeak import _is_modifier, _run_isolated
from diffsheg_core.training.corpus.languages import BY_CODE, LANGUAGES, check_languages, language_text
from diffsheg_core.training.corpus.phones import SILENCE, check_phones, from_espeak
from diffsheg_core.training.corpus.synthesis import VoiceSpec, espeak_voice, synthesize
from diffsheg_core.training.corpus.teacher import load_utterance
from diffsheg_core.training.corpus.texts import FORTUNES_DIR
from diffsheg_core.phonetic import VOWELS

BILABIAL_WORDS = {
    "de": "Baum Papier Mama", "fr": "beau papa maman", "es": "boca padre mamá",
    "ru": "мама папа баба", "hi": "माँ पापा बाबा", "ja": "ママ パパ バブ", "sv": "mamma pappa bebis",
}


@pytest.mark.parametrize("code", sorted(BY_CODE))
def test_every_language_is_spoken_and_mapped_without_guessing(code):
    rng = np.random.default_rng([1, 2])
    language = BY_CODE[code]
    text = language_text(language, rng)
    samples, events, _ = _run_isolated(VoiceSpec("espeak", code), text)
    assert len(samples) > 0.8 * 22050
    symbols = [s for _, s in events if not _is_modifier(s)]
    labels = [from_espeak(s, code) for s in symbols]
    speech = [l for l in labels if l != SILENCE]
    assert 0.25 < sum(l in VOWELS for l in speech) / len(speech) < 0.65, (text, symbols)
    # every symbol is in a table: the blind fallback (AH for a vowel letter, T otherwise)
    # must not be what decides it
    from diffsheg_core.training.corpus.phones import _from_espeak_world

    unmapped = {s for s in symbols if from_espeak(s, code) != SILENCE and _from_espeak_world(s) is None}
    assert not unmapped, (code, unmapped)


@pytest.mark.parametrize("code", sorted(BILABIAL_WORDS))
def test_bilabials_close_the_lips_in_every_language(code):
    phones = synthesize(BILABIAL_WORDS[code], VoiceSpec("espeak", code)).phones
    check_phones(phones)
    labels = [p.label for p in phones]
    assert sum(l in ("P", "B", "M") for l in labels) >= 4, labels


def test_english_mnemonics_keep_their_english_phones():
    assert from_espeak("a") == "AE" and from_espeak("a", "de") == "AA"
    assert from_espeak("3:") == "ER" and from_espeak("3", "de") == "AH"
    assert from_espeak("y", "fr") == "UW" and from_espeak("a55", "vi") == "AA"
    assert from_espeak("t_s\\", "ja") == "CH" and from_espeak("ts;", "pl") == "CH"


def test_unknown_languages_are_named_with_the_choices(tmp_path, capsys):
    with pytest.raises(DiffshegError, match="unknown corpus language xx.*de,fr"):
        check_languages(["de", "xx"])
    assert check_languages(["all"]) == LANGUAGES and check_languages(["ja", "de"]) == (BY_CODE["ja"], BY_CODE["de"])
    assert main(["build", "--out", str(tmp_path / "c"), "--hours", "0.001", "--languages", "klingon",
                 "--language-hours", "0.1"]) == 2
    assert "unknown corpus language klingon" in capsys.readouterr().err
    with pytest.raises(DiffshegError, match="--language-hours and --languages go together"):
        build(BuildConfig(out=tmp_path / "c", hours=0.001, languages=LANGUAGES[:1]), progress=False)


def test_a_build_adds_other_languages_beside_english_and_resumes(tmp_path):
    require_path(FORTUNES_DIR, "fortunes")  # the build's default English texts
    config = BuildConfig(out=tmp_path / "c", hours=4 / 3600, jobs=1, seed=2, engines=("espeak",))
    english = build(config, progress=False)
    before = (config.out / "manifest.jsonl").read_text()
    languages = check_languages(["de", "ja", "hi"])
    both = BuildConfig(**{**config.__dict__, "languages": languages, "language_hours": 8 / 3600})
    summary = build(both, progress=False)
    assert (config.out / "manifest.jsonl").read_text().startswith(before)  # English untouched
    records = read_manifest(config.out)
    other = [r for i, r in records.items() if i >= LANGUAGE_INDEX_START]
    assert summary["utterances"] == english["utterances"] + len(other) and other
    assert sum(r["duration"] for r in other) >= 8 and {r["language"] for r in other} <= {"de", "ja", "hi"}
    assert {r["language"] for r in other} <= set(summary["languages"])
    for rec in other:
        motion, phones, info = load_utterance(config.out / rec["npz"])
        check_phones(phones)
        assert info["voice"]["name"].split("+")[0] == rec["language"]
        assert motion.face.shape[1] == 51 and np.isfinite(motion.face).all()
    again = build(both, progress=False)
    assert again["speech_seconds_this_run"] == 0 and again["utterances"] == summary["utterances"]


def test_language_voices_are_drawn_from_the_seed():
    a = espeak_voice(np.random.default_rng(3), "de")
    assert a == espeak_voice(np.random.default_rng(3), "de") and a.language == "de"
    assert language_text(BY_CODE["fr"], np.random.default_rng(4)) == language_text(BY_CODE["fr"], np.random.default_rng(4))
