"""Lip-sync of the bundled model on real speech beyond English (issue 29, item 3): the
mouth-to-voice correlation over voiced frames per language against real English, and lip
closures during speech, on every recording of ../shared/data/audio/lang (seed 0, default
settings). bench/eval_languages.py prints the same figures for two seeds and more English."""

from collections import defaultdict

import numpy as np
import pytest

from conftest import DATA
from diffsheg_core.audio import Audio, load_audio
from diffsheg_core.checkpoints import load_model
from diffsheg_core.errors import DiffshegError
from diffsheg_core.motion import Motion
from diffsheg_core.pipeline import generate
from diffsheg_core.qc import lip_closures, voiced_frames, voiced_level_correlation, voiced_mouth_voice_correlation
from diffsheg_core.training.metrics import phone_tier, read_textgrid
from diffsheg_core.training.metrics.lipsync import BILABIALS, base_phone

LANG = DATA / "audio" / "lang"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
ENGLISH = (TAKE_WAV, DATA / "audio" / "12_zhao_2_3_3.wav")  # two real speakers, 120 s
GOAL = 0.9
"""Issue 29: voiced-frame correlation on non-English speech at least 0.9x English's."""

# language: (floor the model meets on voiced frames, the measured ratio to English if under GOAL)
# measured with v10 (seed 0; English 0.48 over the two English recordings): de 0.16 (0.33x
# English), es 0.42 (0.87x), fr 0.40 (0.83x), hi 0.31 (0.65x), ja 0.36 (0.76x), ru 0.62, sv 0.64,
# zh 0.52. Every language rose from v9's (English 0.40, de 0.14, es 0.37, fr 0.35, hi 0.23, ja
# 0.32, ru 0.54, sv 0.57, zh 0.47), English most: its face learnt a Mandarin reader's jaw, which
# follows the voice's level more (issue 42 retired this figure for the captured-face agreement).
LANGUAGES = {"de": (0.08, 0.33), "es": (0.3, 0.87), "fr": (0.25, 0.83), "hi": (0.15, 0.65), "ja": (0.2, 0.76),
             "ru": (0.4, None), "sv": (0.4, None), "zh": (0.35, None)}
CLOSURES_MIN = 0.3
"""Lip closures per second of voiced speech, a language's mean over its recordings, that every
language reaches (English 0.95-1.3; lowest zh 0.5, whose zh_aishell_1 has no p/b/m and no
closure at all, and fr 0.9)."""


@pytest.fixture(scope="module")
def generated() -> dict[str, tuple[Audio, Motion]]:
    """File name -> (audio, motion of the bundled model, seed 0) for English and every language,
    with the model's own sampling, which the figures below were measured with (the fast
    sampling's lip-sync against it: bench/bench_sampling.py)."""
    bundle = load_model()
    out = {}
    for path in (*ENGLISH, *sorted(LANG.glob("*.wav"))):
        audio = load_audio(path)
        out[path.name] = audio, generate(audio, model=bundle, seed=0, sampling="quality")
    return out


@pytest.fixture(scope="module")
def measured(generated) -> dict[str, dict[str, list[float]]]:
    """Per language ('en' too): voiced-frame correlations and closures per voiced second, one per recording."""
    out: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    english = [path.name for path in ENGLISH]
    for name, (audio, motion) in generated.items():
        lang = "en" if name in english else name.split("_", 1)[0]
        voiced = voiced_frames(audio.samples, audio.sample_rate, motion.fps, motion.n_frames)
        out[lang]["voiced"].append(voiced_mouth_voice_correlation(motion, audio.samples, audio.sample_rate))
        out[lang]["closures"].append(
            len(lip_closures(motion, audio.samples, audio.sample_rate)) / (voiced.sum() / motion.fps))
    return out


def test_every_language_is_measured(measured):
    assert sorted(measured) == sorted(["en", *LANGUAGES])


def _param(lang: str):
    short = LANGUAGES[lang][1]
    if short is None:
        return lang
    return pytest.param(lang, marks=pytest.mark.xfail(
        strict=True, reason=f"{lang}: voiced-frame correlation {short:.2f}x English's (seed 0), goal {GOAL}x"))


@pytest.mark.parametrize("lang", [_param(lang) for lang in LANGUAGES])
def test_lips_follow_the_voice_while_it_speaks(measured, lang):
    floor, _ = LANGUAGES[lang]
    english = np.mean(measured["en"]["voiced"])
    voiced = np.mean(measured[lang]["voiced"])
    assert voiced > floor, (lang, measured[lang]["voiced"])
    assert voiced >= GOAL * english, (lang, voiced, english)


@pytest.mark.parametrize("lang", list(LANGUAGES))
def test_lips_close_during_speech(measured, lang):
    """A proxy for closing on p/b/m (no phone timings outside English): the lips shut often
    while the voice sounds, as in English."""
    rates = measured[lang]["closures"]
    assert np.mean(rates) > CLOSURES_MIN, (lang, rates)


def test_a_captured_face_follows_the_voice_s_level_less_than_the_goal_asks(generated, measured):
    """Why the goal is a loudness figure that faithful lip-sync need not reach: the take's own
    motion capture (the BEAT2 SMPL-X jaw of the same take) follows the voice's level over
    voiced frames at 0.30, under 0.9x the model's English (0.40 over the two English
    recordings with v9, 0.48 with v10), so the goal asks a language's mouth to follow the level
    more than a real English face does. The model's jaw moves with that captured jaw (about 0.5
    over voiced frames; the exact visemes of the TextGrid 0.56), and
    making it follow the level enough to meet the goal moves it away (bench/eval_languages.py
    --loudness-gain)."""
    from diffsheg_core.training.evaluate import load_reference
    from diffsheg_core.training.metrics import mouth_opening
    from diffsheg_core.training.metrics.lipsync import voiced_reference_correlation

    audio, motion = generated[TAKE_WAV.name]
    real = mouth_opening(load_reference(DATA / "beat2" / "2_scott_0_1_1.npz", fps=motion.fps))
    english = np.mean(measured["en"]["voiced"])
    assert voiced_level_correlation(real, motion.fps, audio.samples, audio.sample_rate) < GOAL * english
    agree = voiced_reference_correlation(mouth_opening(motion), real, motion.fps, audio.samples, audio.sample_rate)
    assert agree > 0.4, agree


def test_closures_fall_on_bilabials_in_the_english_take(generated):
    """The proxy holds where phone timings exist: on the real take, the closures lie within a
    frame of a p/b/m far more often than voiced frames do."""
    audio, motion = generated[TAKE_WAV.name]
    phones = phone_tier(read_textgrid(DATA / "beat2" / "2_scott_0_1_1.TextGrid"))
    n, fps = motion.n_frames, motion.fps

    near = np.zeros(n, bool)
    for p in phones:
        if base_phone(p.label) in BILABIALS:
            near[max(0, int(np.ceil(p.start * fps)) - 1): int(p.end * fps) + 2] = True
    closures = lip_closures(motion, audio.samples, audio.sample_rate)
    voiced = voiced_frames(audio.samples, audio.sample_rate, fps, n)
    assert near[closures].mean() > 2 * near[voiced].mean(), (near[closures].mean(), near[voiced].mean())


TRANSCRIBED = {"de": "de", "es": "es", "fr": "fr", "hi": "hi", "ja": "ja", "ru": "ru", "sv": "sv"}
"""Languages whose transcripts espeak-ng reads (not Chinese characters or pinyin; Japanese
through its kana reading)."""
JAW_CONTRAST_MIN = 1.2
"""Mouth opening at open vowels over at p/b/m, pooled over a language's transcribed
recordings (bundled model, seed 0): de 1.87, es 2.05, fr 5.13, hi 3.12, ru 1.32, sv 2.87
(seeds 0-1: ja 2.37);
English on the take 2.34 with these approximate timings, 2.43 with its TextGrid."""


FOLLOWS_MIN = 0.3
"""Correlation over voiced frames of the mouth with the jaw the teacher's visemes give the
transcript's phones (lipsync.viseme_jaw), a language's mean over its recordings (seeds 0-1:
de 0.68, es 0.47, fr 0.72, hi 0.61, ja 0.45, ru 0.43, sv 0.48; English 0.62 on the take's
TextGrid)."""


@pytest.fixture(scope="module")
def aligned(generated) -> dict[str, list]:
    """File name -> the phones of its transcript timed on it (approximate), per transcribed recording."""
    from diffsheg_core.training.metrics.transcript_phones import transcript_phones

    out = {}
    for path in sorted(LANG.glob("*.wav")):
        lang = path.name.split("_", 1)[0]
        if lang in TRANSCRIBED and path.with_suffix(".txt").is_file():
            audio, _ = generated[path.name]
            out[path.name] = transcript_phones(audio.samples, audio.sample_rate,
                                               path.with_suffix(".txt").read_text(encoding="utf-8"), TRANSCRIBED[lang])
    return out


def test_transcript_phones_place_the_take_s_phones_as_its_textgrid_does(generated):
    """The approximate aligner on the one recording with real phone timings: espeak-ng's
    phones warped onto the take land vowels in vowels and p/b/m in p/b/m mostly, and give
    nearly the jaw contrast the TextGrid gives."""
    from diffsheg_core.training.metrics import mouth_opening, phoneme_contrast
    from diffsheg_core.training.metrics.transcript_phones import transcript_phones

    audio, motion = generated[TAKE_WAV.name]
    grid = read_textgrid(DATA / "beat2" / "2_scott_0_1_1.TextGrid")
    words = " ".join(w.label for w in grid["words"] if w.label.strip())
    aligned = transcript_phones(audio.samples, audio.sample_rate, words, "en-us")
    truth = phone_tier(grid)

    def kind_at(t: float) -> str:
        return next((base_phone(p.label) for p in aligned if p.start <= t < p.end), "SIL")

    for kind, share in ((("AA", "AE", "AH", "AO", "AW", "AY", "EH", "ER", "EY", "IH", "IY", "OW", "OY", "UH", "UW"), 0.7),
                        (BILABIALS, 0.6)):
        middles = [p.middle for p in truth if base_phone(p.label) in kind]
        assert np.mean([kind_at(t) in kind for t in middles]) > share, kind
    real = phoneme_contrast(mouth_opening(motion), motion.fps, truth)["ratio"]
    approximate = phoneme_contrast(mouth_opening(motion), motion.fps, aligned)["ratio"]
    assert abs(approximate - real) < 0.15 * real, (approximate, real)
    with pytest.raises(DiffshegError, match="the transcript is empty"):
        transcript_phones(audio.samples, audio.sample_rate, "  ", "en-us")


@pytest.mark.parametrize("lang", sorted(TRANSCRIBED))
def test_the_jaw_opens_on_vowels_and_closes_on_bilabials_in_every_transcribed_language(generated, aligned, lang):
    """Jaw open at open vowels against p/b/m (the model card's lip-sync figure) per language,
    on phone timings from the transcripts (approximate, see the test above)."""
    from diffsheg_core.training.metrics import mouth_opening
    from diffsheg_core.training.metrics.lipsync import OPEN_VOWELS, phone_middles, values_at

    opened, shut = [], []
    for name in (n for n in aligned if n.startswith(f"{lang}_")):
        _, motion = generated[name]
        phones = aligned[name]
        mouth, seconds = mouth_opening(motion), motion.n_frames / motion.fps
        opened += list(values_at(mouth, motion.fps, phone_middles(phones, OPEN_VOWELS, seconds)))
        shut += list(values_at(mouth, motion.fps, phone_middles(phones, BILABIALS, seconds)))
    assert len(opened) >= 10 and len(shut) >= 5, (lang, len(opened), len(shut))
    assert np.mean(opened) > JAW_CONTRAST_MIN * np.mean(shut), (lang, np.mean(opened), np.mean(shut))


def _follows(audio, motion, phones) -> float:
    from diffsheg_core.qc import mouth_curve
    from diffsheg_core.training.metrics.lipsync import phone_following

    return phone_following(mouth_curve(motion), motion.fps, phones, audio.samples, audio.sample_rate)


def _teacher_r(audio, motion, phones) -> float:
    """The loudness figure (voiced-frame mouth-to-voice correlation) of the viseme jaw of `phones`."""
    from diffsheg_core.qc import voiced_level_correlation
    from diffsheg_core.training.metrics.lipsync import viseme_jaw

    return voiced_level_correlation(viseme_jaw(phones, motion.n_frames, motion.fps), motion.fps, audio.samples,
                                    audio.sample_rate)


@pytest.mark.parametrize("lang", sorted(TRANSCRIBED))
def test_the_mouth_follows_the_phones_in_every_transcribed_language(generated, aligned, lang):
    """Whatever the loudness: the mouth opens as the teacher's visemes open the jaw for the
    transcript's phones (approximately timed), in every transcribed language."""
    follows = [_follows(*generated[name], aligned[name]) for name in aligned if name.startswith(f"{lang}_")]
    assert np.mean(follows) > FOLLOWS_MIN, (lang, follows)


def test_where_the_loudness_goal_is_missed_exact_phone_lip_sync_misses_it_more(generated, aligned):
    """The loudness goal measures the recordings as much as the model: lip-sync that follows
    the phones exactly (the viseme jaw of the transcript's phones) scores on the loudness
    figure, in each language short of the goal (de, es, fr, hi, ja), under the goal's share of
    what it scores on English (the take and its TextGrid), and the model scores above it
    there (v10, seeds 0-1, bench/eval_languages.py: teacher de 0.06, es 0.12, fr 0.07, hi 0.13,
    ja 0.14 against English 0.21; the model 0.15, 0.44, 0.48, 0.26, 0.42)."""
    audio, motion = generated[TAKE_WAV.name]
    english = _teacher_r(audio, motion, phone_tier(read_textgrid(DATA / "beat2" / "2_scott_0_1_1.TextGrid")))
    short = [lang for lang in TRANSCRIBED if LANGUAGES[lang][1] is not None]
    assert sorted(short) == ["de", "es", "fr", "hi", "ja"]
    for lang in short:
        names = [name for name in aligned if name.startswith(f"{lang}_")]
        teacher = np.mean([_teacher_r(*generated[name], aligned[name]) for name in names])
        model = np.mean([voiced_mouth_voice_correlation(generated[name][1], generated[name][0].samples,
                                                        generated[name][0].sample_rate) for name in names])
        assert teacher < GOAL * english and model > teacher, (lang, teacher, model, english)


def test_voiced_frames_on_real_phone_timings():
    audio = load_audio(TAKE_WAV)
    fps = 15.0
    n = int(audio.duration * fps)
    voiced = voiced_frames(audio.samples, audio.sample_rate, fps, n)
    label = np.full(n, "", object)
    for p in phone_tier(read_textgrid(DATA / "beat2" / "2_scott_0_1_1.TextGrid")):
        label[int(np.ceil(p.start * fps)): int(np.ceil(p.end * fps))] = base_phone(p.label)
    vowel = np.array([bool(x) and x[0] in "AEIOU" for x in label])
    pause = np.array([x in ("", "SIL", "SP") for x in label])
    assert voiced[vowel].mean() > 0.9 and voiced[pause].mean() < 0.05
    # the recording's gain changes nothing, a DC offset (zh_thchs30's) next to nothing,
    # room noise alone is not voice, and neither is mains hum in the pauses
    assert np.array_equal(voiced_frames(0.3 * audio.samples, audio.sample_rate, fps, n), voiced)
    shifted = voiced_frames(audio.samples - 0.012, audio.sample_rate, fps, n)
    assert (shifted == voiced).mean() > 0.98
    noise = np.random.default_rng(0).normal(0, 0.05, len(audio.samples))
    assert voiced_frames(noise, audio.sample_rate, fps, n).mean() < 0.02
    hum = 0.018 * np.sin(2 * np.pi * 50 * np.arange(len(audio.samples)) / audio.sample_rate)
    assert np.array_equal(voiced_frames(audio.samples + hum, audio.sample_rate, fps, n), voiced)


def test_the_hum_of_a_real_recording_is_not_voice():
    """zh_thchs30_1 hums at 50 Hz (a third of its energy lies under 80 Hz) about 17 dB under its
    speech: its pauses, the first 0.7 s and the last 3.6 s, hold no voiced frame (before
    voiced_frames heard only the audio above the lowest pitch, 51 of their frames were voiced
    and lifted the file's voiced-frame correlation, seeds 0 and 1, from 0.55 to 0.84)."""
    audio = load_audio(LANG / "zh_thchs30_1.wav")
    fps = 15.0
    voiced = voiced_frames(audio.samples, audio.sample_rate, fps, int(audio.duration * fps))
    assert not voiced[: int(0.7 * fps)].any() and not voiced[int(9.2 * fps):].any()
    assert voiced.sum() > 40


def test_a_face_shuffled_in_time_does_not_follow_the_voice(generated):
    audio, motion = generated["sv_nst_2.wav"]
    order = np.random.default_rng(0).permutation(motion.n_frames)
    shuffled = Motion(motion.fps, motion.rig, motion.joint_names, motion.rotations, motion.face_names,
                      motion.face[order])
    real = voiced_mouth_voice_correlation(motion, audio.samples, audio.sample_rate)
    assert voiced_mouth_voice_correlation(shuffled, audio.samples, audio.sample_rate) < real - 0.2


def test_lip_closures_of_a_clip_shorter_than_their_reach():
    """0.3 s (5 frames, fewer than the reach's 7): no broadcasting error."""
    audio = load_audio(LANG / "de_thorsten_1.wav")
    short = audio.samples[: int(0.3 * audio.sample_rate)]
    motion = generate(Audio(samples=short, sample_rate=audio.sample_rate, path=None), steps=3, device="cpu")
    assert len(lip_closures(motion, short, audio.sample_rate)) <= motion.n_frames


def test_a_japanese_transcript_is_read_as_kana_or_the_missing_reader_is_named(monkeypatch):
    import sys

    from diffsheg_core.training.metrics.transcript_phones import _readable

    assert _readable("単に与えられた", "ja") == "タンニアタエラレタ"
    assert _readable("Guten Tag", "de") == "Guten Tag"
    monkeypatch.setitem(sys.modules, "fugashi", None)  # not installed
    with pytest.raises(DiffshegError, match="pip install fugashi unidic-lite"):
        _readable("単に", "ja")


FACEGOOD = DATA / "lang_capture" / "zh_facegood"
# Issue 42: the bundled model (v10, seed 0) on the held-out FACEGOOD take 1114_2_05 against its
# captured face mapped onto ARKit (training.metrics.facegood), measured: jawOpen 0.74 over
# the whole clip, 0.47 over voiced frames, 0.94x the 0.50 of the model's jaw against BEAT2's
# captured jaw of the English take; joined into running speech 0.45 (0.90x; v9: 0.71x);
# mouthFunnel 0.57 / 0.47, mouthPucker 0.52 / 0.41, mouthClose 0.35 / 0.39 (whole / voiced).
# The floors leave about 0.1 of margin.
FACEGOOD_FLOORS = {"jawOpen": (0.6, 0.35), "mouthFunnel": (0.4, 0.35), "mouthPucker": (0.4, 0.3),
                   "mouthClose": (0.15, 0.2)}
"""ARKit channel: (floor whole clip, floor voiced frames) on 1114_2_05, seed 0."""
FACEGOOD_RATIO_FLOOR = 0.8
"""Voiced-frame jaw agreement on 1114_2_05 as read over English's (measured 0.94; v9 0.76)."""
FACEGOOD_RUNNING_FLOOR = 0.8
"""Voiced-frame jaw agreement on 1114_2_05 joined into running speech over English's (measured 0.90; v9 0.71)."""
FACEGOOD_OWN_FLOORS = {"mouthFunnel": (None, 0.35), "mouthPucker": (None, 0.3), "mouthClose": (None, 0.12)}
"""The other mouth channels' voiced-frame floors on 1114_2_05 joined, with Mandarin's own face (seed 0)."""


def test_the_facegood_mapping_reads_every_take(tmp_path):
    from diffsheg_core.training.metrics.facegood import (ARKIT_FROM_RIG, JAW, N_CHANNELS, arkit_curves, read_names,
                                                         read_take, resample_curves, take_names)

    names = read_names(FACEGOOD / "bs_names.json")
    assert len(names) == N_CHANNELS and names[74] == JAW
    assert take_names(FACEGOOD) == [f"1114_2_0{k}" for k in range(1, 6)]
    for name in take_names(FACEGOOD):
        take = read_take(FACEGOOD, name, names)
        assert take.values.shape[1] == N_CHANNELS and abs(take.n_frames / 30 - take.audio.duration) < 0.1
        n = int(take.audio.duration * 15)
        curves = arkit_curves(take, 15.0, n)
        assert sorted(curves) == sorted(ARKIT_FROM_RIG)
        for arkit, curve in curves.items():
            assert curve.shape == (n,) and curve.min() >= 0 and curve.max() <= 1, (name, arkit)
        # jawOpen is the rig's jaw opening at 15 fps, and it moves: open in speech, shut in pauses
        jaw = take.channel(JAW)
        i = 2 * np.arange(1, n - 1)  # frame i / 15 s is capture frame 2i, low-passed [1/4, 1/2, 1/4]
        assert np.allclose(curves["jawOpen"][1:-1], (jaw[i - 1] + 2 * jaw[i] + jaw[i + 1]) / 4)
        assert np.percentile(curves["jawOpen"], 95) > 0.3 and np.median(curves["jawOpen"]) < 0.05
        for rounding in ("mouthFunnel", "mouthClose"):  # every take rounds and shuts its lips somewhere
            assert curves[rounding].max() > 0.3, (name, rounding)
    assert np.allclose(resample_curves(np.arange(8.0), 30, 15, 4), [0.25, 2, 4, 6])

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "bs_names.json").write_text((FACEGOOD / "bs_names.json").read_text())
    (bad / "t.wav").write_bytes((FACEGOOD / "1114_2_05.wav").read_bytes())
    np.save(bad / "bs_value_t.npy", np.zeros((3384, 115), np.float32))
    with pytest.raises(DiffshegError, match="one column per name"):
        read_take(bad, "t")
    np.save(bad / "bs_value_t.npy", np.zeros((3000, 116), np.float32))
    with pytest.raises(DiffshegError, match="lasts 100.00 s"):
        read_take(bad, "t")


def test_a_take_joined_into_running_speech_keeps_every_word_and_its_face():
    """metrics.facegood.joined: the held-out take's pauses (about 0.6 s between words) cut to
    0.1 s, audio and face at the same frames: every sounding frame is kept with its face, no
    silence longer than the pause is left, and the voice sounds most of the time, as running
    speech does (English's take 0.74 voiced; the take as read 0.40)."""
    from diffsheg_core.qc import speech_level
    from diffsheg_core.training.metrics.facegood import HELD_OUT, JAW, SILENCE_DB, joined, read_take

    take = read_take(FACEGOOD, HELD_OUT)
    cut = joined(take, 0.1)
    assert 0.5 * take.audio.duration < cut.audio.duration < 0.7 * take.audio.duration
    assert abs(cut.audio.duration - cut.n_frames / cut.fps) < 1 / cut.fps
    level = speech_level(take.audio.samples, take.audio.sample_rate, take.fps, take.n_frames)
    sounding = level >= np.percentile(level, 95) - SILENCE_DB
    cut_level = speech_level(cut.audio.samples, cut.audio.sample_rate, cut.fps, cut.n_frames)
    cut_sounding = cut_level >= np.percentile(level, 95) - SILENCE_DB
    # the frames where the jaw opens are kept (all but 10 of 1497, opening in silence before a word)
    jaw, cut_jaw = take.channel(JAW), cut.channel(JAW)
    assert np.count_nonzero(cut_jaw > 0.02) >= 0.99 * np.count_nonzero(jaw > 0.02)
    assert abs(cut_jaw.sum() - jaw.sum()) < 0.01 * jaw.sum() and sounding.sum() > 0.4 * take.n_frames
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[1], cut_sounding.astype(np.int8), [1]]))))[::2]
    assert runs.max() <= 4, runs.max()  # silences of 0.1 s (3 frames) at most, give or take the level's window
    voiced = voiced_frames(cut.audio.samples, cut.audio.sample_rate, 15.0, int(cut.audio.duration * 15))
    assert voiced.mean() > 0.6
    with pytest.raises(DiffshegError, match="above 0 s"):
        joined(take, 0)


def test_the_facegood_takes_train_the_mouth_alone():
    """training.data.facegood: four takes train and the held-out one is the test split; a take
    fits the whole-body layout with only the jaw and the lips' rounding unmasked (the gestures,
    legs and every other face channel out of the loss), its jaw the captured one; with `pause`
    the take is the one joined into running speech."""
    from diffsheg_core.rigs import BEAT_BODY
    from diffsheg_core.training.data import DataConfig, find_sources
    from diffsheg_core.training.data.facegood import ROUNDING_GAIN, TRAINED, read_take as read_training_take
    from diffsheg_core.training.metrics.facegood import HELD_OUT, arkit_curves, joined, read_take

    config = DataConfig(kind="facegood", root=str(FACEGOOD), whole_body=True, style=1)
    assert config.layout is BEAT_BODY
    assert [s.name for s in find_sources(config, "test")] == [HELD_OUT]
    sources = find_sources(config, "train")
    assert len(sources) == 4 and HELD_OUT not in [s.name for s in sources]
    take = read_training_take(sources[0], config)
    face = [BEAT_BODY.gesture_dim + BEAT_BODY.face_names.index(n) for n in TRAINED]
    assert sorted(np.flatnonzero(take.mask)) == sorted(face) and take.style == 1
    capture = read_take(FACEGOOD, sources[0].name)
    curves = arkit_curves(capture, 15.0, take.n_frames)
    np.testing.assert_allclose(take.motion[:, face[0]], curves["jawOpen"], atol=1e-6)
    np.testing.assert_allclose(take.motion[:, face[1]], np.clip(ROUNDING_GAIN * curves["mouthFunnel"], 0, 1), atol=1e-6)
    assert not take.motion[:, ~take.mask].any()
    running = read_training_take(sources[0], DataConfig(kind="facegood", root=str(FACEGOOD), pause=0.1))
    assert abs(running.n_frames - joined(capture, 0.1).audio.duration * 15) <= 1


def test_the_held_out_mandarin_take_s_mouth_agrees_with_its_captured_face():
    """The bundled model's mouth on real read Mandarin against the speaker's captured face
    (FACEGOOD, mapped onto ARKit), and its jaw's agreement as a share of English's with
    BEAT2's captured jaw (bench/eval_languages.py prints every take, two seeds)."""
    from diffsheg_core.training.evaluate import load_reference
    from diffsheg_core.training.metrics import mouth_opening
    from diffsheg_core.training.metrics.facegood import (HELD_OUT, agreement, arkit_curves, joined, measure_take,
                                                         read_take)

    bundle = load_model()
    take = read_take(FACEGOOD, HELD_OUT)
    motion = generate(take.audio, model=bundle, seed=0)
    figures = measure_take(motion, take)
    english_audio = load_audio(TAKE_WAV)
    english = generate(english_audio, model=bundle, seed=0)
    real = mouth_opening(load_reference(DATA / "beat2" / "2_scott_0_1_1.npz", fps=english.fps))
    _, english_voiced = agreement(mouth_opening(english), real, english.fps, english_audio)
    ratio = figures["jawOpen"][1] / english_voiced
    running = joined(take, 0.1)
    running_jaw = measure_take(generate(running.audio, model=bundle, seed=0), running)["jawOpen"]
    running_ratio = running_jaw[1] / english_voiced
    print(f"{HELD_OUT}: " + ", ".join(f"{k} {w:.2f} / {v:.2f}" for k, (w, v) in figures.items())
          + f"; jaw over voiced frames {ratio:.2f}x English's {english_voiced:.2f}; joined into running "
          f"speech {running_jaw[1]:.2f} ({running_ratio:.2f}x)")
    for channel, (whole, voiced) in FACEGOOD_FLOORS.items():
        assert figures[channel][0] > whole and figures[channel][1] > voiced, (channel, figures[channel])
    assert ratio > FACEGOOD_RATIO_FLOOR, (ratio, figures["jawOpen"], english_voiced)
    assert running_ratio > FACEGOOD_RUNNING_FLOOR, (running_ratio, running_jaw, english_voiced)
    # the figure is the face's timing, not the mapping's level: the capture shuffled in time agrees with nothing
    order = np.random.default_rng(0).permutation(motion.n_frames)
    jaw = arkit_curves(take, motion.fps, motion.n_frames)["jawOpen"][order]
    assert abs(agreement(mouth_opening(motion), jaw, motion.fps, take.audio)[1]) < 0.1
    # issue 42's goal, with the model's own face for Mandarin: on the held-out take joined into
    # running speech its jaw agrees with the captured jaw at least 0.9x as well as the shared
    # face's English jaw with the English speaker's (the same English run: no language, to the bit)
    own = {label: measure_take(generate(version.audio, model=bundle, seed=0, language="zh"), version)
           for label, version in (("read", take), ("joined", running))}
    own_ratio = {label: figures["jawOpen"][1] / english_voiced for label, figures in own.items()}
    print(f"with --language zh: jaw over voiced frames {own['read']['jawOpen'][1]:.2f} as read "
          f"({own_ratio['read']:.2f}x), {own['joined']['jawOpen'][1]:.2f} joined ({own_ratio['joined']:.2f}x); "
          + ", ".join(f"{k} {v:.2f}" for k, (_, v) in own["joined"].items() if k != "jawOpen"))
    assert own_ratio["joined"] >= GOAL and own_ratio["read"] >= GOAL, (own_ratio, english_voiced)
    assert own["joined"]["jawOpen"][1] > running_jaw[1] + 0.02  # above the shared face's
    for channel, (whole, voiced) in FACEGOOD_OWN_FLOORS.items():
        assert own["joined"][channel][1] > voiced, (channel, own["joined"][channel])
