"""Style control (issue 16, after DiffuseStyleGesture): a style by index, name or weights,
style guidance eps_null + s (eps_style - eps_null), what a Motion records of it, and the
official networks' speaker one-hots taking weights too."""

from __future__ import annotations

import argparse
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from conftest import random_bundle
from diffsheg_core.errors import DiffshegError
from diffsheg_core.foppas import PRESETS
from diffsheg_core.guidance import Guidance, step_eps
from diffsheg_core.pipeline import generate
from diffsheg_core.runtime.backends import open_network
from diffsheg_core.settings import GenerateSettings
from diffsheg_core.style import parse_style, style_vector, style_weights
from test_pipeline import speech  # noqa: F401 (fixture: four seconds of real speech)

NAMES = ["calm", "conversational", "animated"]


@pytest.fixture(scope="module")
def styled():
    """A small random three-style model that learned a null style (names in its info)."""
    bundle = random_bundle(style_dim=3, seed=4)
    return replace(bundle, sampling=PRESETS["no-resample"], std=np.ones(bundle.config.dim, np.float32),
                   info={"style_names": NAMES, "null_style": True})


def test_a_style_is_an_index_a_name_or_weights(styled):
    assert style_weights(styled, 2) == style_weights(styled, "animated") == {2: 1.0}
    assert style_weights(styled, {"calm": 0.7, "animated": 0.3}) == pytest.approx({0: 0.7, 2: 0.3})
    assert style_weights(styled, {"calm": 2, 1: 2}) == {0: 0.5, 1: 0.5}  # normalised, names and indices
    np.testing.assert_allclose(style_vector(styled, {0: 0.7, 2: 0.3}), [[0.7, 0.0, 0.3]])
    assert parse_style("calm=0.7,animated=0.3") == {"calm": 0.7, "animated": 0.3}
    assert parse_style("2") == 2 and parse_style("calm") == "calm"


@pytest.mark.parametrize("style,match", [
    ("lively", "has no style 'lively': choose one of calm, conversational, animated"),
    ({"calm": 0.0}, "do not sum to a positive number"), ({"calm": -1.0, "animated": 2.0}, "must be a number >= 0"),
    (3, "from 0 to 2"), ({"calm": float("nan")}, "must be a number >= 0"),
])
def test_bad_styles_are_refused_by_name(styled, style, match):
    with pytest.raises(DiffshegError, match=match):
        style_weights(styled, style)


def test_only_ascii_digits_make_a_style_index(styled):
    """'²' is a digit to str.isdigit but no number to int(): it is a style name, and no style here."""
    assert parse_style("²") == "²" and parse_style(" 2 ") == 2
    assert parse_style("calm=0.5,²=0.5") == {"calm": 0.5, "²": 0.5}
    assert style_weights(styled, {"calm": 1.0, "2": 1.0}) == {0: 0.5, 2: 0.5}
    for style in ("²", {"calm": 0.5, "²": 0.5}):
        with pytest.raises(DiffshegError, match="has no style '²': choose one of calm, conversational, animated"):
            style_weights(styled, style)


def test_numpy_numbers_are_style_indices_and_weights(styled):
    assert style_weights(styled, {np.int64(0): np.int64(1), "animated": np.float32(3)}) == {0: 0.25, 2: 0.75}
    assert type(GenerateSettings(style=np.int64(2)).style) is int


def test_a_style_named_twice_is_refused():
    with pytest.raises(argparse.ArgumentTypeError, match="style 'calm' is given twice in 'calm=1, calm =0'"):
        parse_style("calm=1, calm =0")


def test_the_cli_refuses_odd_styles_in_one_line(speech):
    for style, match in (("calm=0.5,²=0.5", "has no style '²'"), ("calm=1,calm=0", "'calm' is given twice")):
        result = subprocess.run([sys.executable, "-m", "diffsheg_core", "generate", str(speech), "--style", style,
                                 "-o", str(speech.with_suffix(".npz"))], capture_output=True, text=True, timeout=300)
        assert result.returncode == 2 and "error: " in result.stderr and match in result.stderr, result.stderr
        assert "Traceback" not in result.stderr


class Recording:
    """A network that records the style rows of its gesture calls."""

    def __init__(self, net):
        self.net, self.styles = net, []

    def expression(self, *args):
        return self.net.expression(*args)

    def gesture(self, *args):
        self.styles.append(args[5])
        return self.net.gesture(*args)


def _eps(bundle, style, guidance: Guidance, net=None):
    cfg, rng = bundle.config, np.random.default_rng(0)
    x = rng.standard_normal((1, cfg.clip_len, cfg.dim), dtype=np.float32)
    mel = rng.random((1, cfg.clip_len, cfg.mel_dim), dtype=np.float32)
    coefs = (np.full((1, 1, 1), 2.0, np.float32), np.full((1, 1, 1), 1.5, np.float32))
    return step_eps(net or open_network(bundle), cfg.gesture_dim, x, np.array([500]), mel, None, style, coefs,
                    guidance)[0]


def test_style_guidance_is_null_plus_scale_times_the_difference(styled):
    """n + s (c - n) on the gestures, n from one more gesture pass with the null style, beside
    gesture skip guidance; the face is untouched; 1 is the plain conditioned prediction."""
    g = styled.config.gesture_dim
    style = style_vector(styled, {2: 1.0})
    for base in (Guidance(), Guidance(skip=0.3)):
        plain = _eps(styled, style, base)
        net = Recording(open_network(styled))
        twice = _eps(styled, style, replace(base, style=3.0), net)
        once = _eps(styled, style, replace(base, style=2.0))
        np.testing.assert_allclose(twice[..., :g] - plain[..., :g], 2 * (once[..., :g] - plain[..., :g]), atol=1e-5)
        assert np.abs(once[..., :g] - plain[..., :g]).max() > 1e-3
        np.testing.assert_array_equal(twice[..., g:], plain[..., g:])
        rows = net.styles[0]
        assert not rows[-1:].any() and (rows[:-1] == style).all()  # the last pass sees the null style
    np.testing.assert_array_equal(_eps(styled, style, Guidance(style=1.0)), _eps(styled, style, Guidance()))


def test_a_mix_of_two_styles_lies_between_them_and_guidance_goes_beyond(styled, speech):
    """Gesture mean pose along the line from calm to animated: the mix lies between the two,
    guidance above 1 beyond the style it steers."""
    def gestures(**kw):
        return generate(speech, model=styled, steps=3, device="cpu", seed=1, **kw).rotations.reshape(-1)

    calm, animated = gestures(style="calm"), gestures(style="animated")
    mixed = gestures(style={"calm": 0.5, "animated": 0.5})
    beyond = gestures(style="animated", style_guidance=2.0)
    axis = animated - calm

    def position(x):
        return float((x - calm) @ axis / (axis @ axis))

    assert 0.1 < position(mixed) < 0.9
    assert position(beyond) > 1.1


def test_a_motion_records_its_style(styled, speech):
    motion = generate(speech, model=styled, steps=3, device="cpu", style={"calm": 1, "animated": 3},
                      style_guidance=1.5)
    assert motion.meta["style_names"] == NAMES
    assert motion.meta["style_weights"] == {"calm": 0.25, "animated": 0.75}
    assert motion.meta["style"] is None and motion.meta["style_guidance"] == 1.5
    single = generate(speech, model=styled, steps=3, device="cpu", style="conversational")
    assert single.meta["style"] == 1 and single.meta["style_guidance"] == 1.0


def test_weights_near_the_float_limit_are_the_mix_they_describe(styled, speech):
    """Their sum overflows: normalised by the sum alone they became zeros, the null style."""
    huge = generate(speech, model=styled, steps=2, device="cpu", style=parse_style("calm=1e308,animated=1e308"))
    assert huge.meta["style_weights"] == {"calm": 0.5, "animated": 0.5}
    even = generate(speech, model=styled, steps=2, device="cpu", style={"calm": 1, "animated": 1})
    np.testing.assert_array_equal(huge.rotations, even.rotations)
    assert style_weights(styled, {"calm": 1.7e308, 0: 1.7e308, "animated": 1.7e308}) == \
        pytest.approx({0: 2 / 3, 2: 1 / 3})


def test_style_guidance_needs_a_null_style_and_a_scale_in_range(styled, speech):
    plain = replace(styled, info={"style_names": NAMES})
    with pytest.raises(DiffshegError, match="trained without a null style"):
        generate(speech, model=plain, steps=3, device="cpu", style_guidance=2.0)
    with pytest.raises(DiffshegError, match="style_guidance must be a number from 0 to 10"):
        GenerateSettings(style_guidance=11.0)
    with pytest.raises(DiffshegError, match="style must be a style index, a style name or weights"):
        GenerateSettings(style=1.5)


def test_official_layout_networks_take_weights_over_their_speaker_one_hots(golden_dir):
    """The official BEAT network (golden weights, 30 speaker one-hots): a weighted style
    input is the weights' mix of one-hots, and the network runs on it."""
    from test_model import golden_args, golden_bundle

    bundle = golden_bundle(golden_dir, "beat_small", {})
    io = dict(np.load(golden_dir / "beat_small_io.npz"))
    n = bundle.config.style_dim
    weights = style_weights(bundle, {3: 0.25, 7: 0.75})
    vector = style_vector(bundle, weights)
    assert vector.shape == (1, n) and vector[0, 3] == 0.25 and vector[0, 7] == 0.75
    x, t, mel, hubert, _, coefs = golden_args(io, slice(0, 1))
    net = open_network(bundle, backend="torch", device="cpu")
    mixed = step_eps(net, bundle.config.gesture_dim, x, t, mel, hubert, vector, coefs, Guidance())[0]
    one = step_eps(net, bundle.config.gesture_dim, x, t, mel, hubert, np.eye(n, dtype=np.float32)[7:8],
                   coefs, Guidance())[0]
    assert np.isfinite(mixed).all() and not np.allclose(mixed, one)


def test_style_over_time_with_the_bundled_model_on_real_speech(data_dir, tmp_path):
    """Issue 25, item 5: 20 s of real speech, calm for the first half and animated from
    10 s: the second half's wrists move at least 1.5x as fast (measured 2.1x and 2.3x for
    seeds 0 and 1; the reverse order 0.35x, 0.50x), with no jump at the switch: the
    wrists' acceleration over the second around it stays below the take's mean (measured
    0.5x, 0.7x), with the model's own sampling. The fast sampling tells the styles apart less
    (1.84x and 1.99x; the reverse 0.67x, 0.76x: its later windows' gestures start from the
    gesture prior three steps from the end, which the style steers less) with the switch at
    1.00x and 0.57x the mean. The CLI's --style-at gives the same motion and the meta records it."""
    import soundfile as sf

    from diffsheg_core.motion import Motion
    from diffsheg_core.style import parse_style_at
    from diffsheg_core.training.metrics.posture import wrist_positions

    audio, rate = sf.read(str(data_dir / "audio" / "2_scott_0_3_3.wav"), dtype="float32")
    audio = audio[5 * rate: 25 * rate]
    changes = ((0.0, "calm"), (10.0, "animated"))
    for sampling, faster, switch in (("quality", 1.5, 1.0), ("fast", 1.4, 1.1)):
        motion = generate(audio, rate, seed=0, style_at=changes, sampling=sampling)
        wrists = wrist_positions(motion)
        speed = np.linalg.norm(np.diff(wrists, axis=0), axis=-1).mean(axis=-1)
        acc = np.linalg.norm(np.diff(wrists, 2, axis=0), axis=-1).mean(axis=-1)
        half = len(speed) // 2
        assert speed[half:].mean() >= faster * speed[:half].mean(), sampling
        assert acc[half - 8: half + 8].mean() <= switch * acc.mean(), sampling
    assert motion.meta["style_at"] == [[0.0, {"calm": 1.0}], [10.0, {"animated": 1.0}]]
    assert parse_style_at("0=calm,10=animated") == changes

    wav = tmp_path / "talk.wav"
    sf.write(str(wav), audio, rate)
    out = tmp_path / "m.npz"
    proc = subprocess.run([sys.executable, "-m", "diffsheg_core", "generate", str(wav), "-o", str(out),
                           "--style-at", "0=calm,10=animated"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    np.testing.assert_allclose(Motion.load_npz(out).rotations, motion.rotations, atol=1e-5)


@pytest.mark.parametrize("changes,match", [
    (((0, "calm"), (0, "animated")), "twice for the same time"),
    (((-1, "calm"),), "style change time"),
    (((float("nan"), "calm"),), "style change time"),
    ((("soon", "calm"),), "style change time"),
    (((1, "calm", 2),), "pairs"),
])
def test_bad_style_changes_are_refused(changes, match):
    with pytest.raises(DiffshegError, match=match):
        GenerateSettings(style_at=changes)


def test_a_change_after_the_speech_never_takes_effect(speech, styled, tmp_path):
    """Issue 43 (c): `--style-at 0=calm,1e308=animated` and `--emotion-at 0=happy,1e308=sad`
    overflowed (1e308 s x 15 fps is inf, which round() refuses). A change after the end of
    the speech never takes effect: the motion is that of the style or emotion before it."""
    from diffsheg_core.emotion import emotion_track
    from diffsheg_core.motion import Motion
    from diffsheg_core.style import style_track

    for seconds in (1e308, 1.7976931348623157e308, 60.0):
        assert (style_track(styled, "animated", ((0, "calm"), (seconds, "animated")), 30).rows == [[1, 0, 0]]).all()
        np.testing.assert_array_equal(emotion_track({"happy": 1.0}, ((seconds, {"sad": 1.0}),), 30, 15.0),
                                      emotion_track({"happy": 1.0}, None, 30, 15.0))
    settings = GenerateSettings(steps=2, style_at=((0, "calm"), (1e308, "animated")),
                                emotion_at=((0, "happy"), (1e308, "sad")))
    assert settings.style_at[1][0] == settings.emotion_at[1][0] == 1e308
    motion = generate(speech, settings=settings)
    before = generate(speech, steps=2, style="calm", emotion="happy")
    np.testing.assert_array_equal(motion.rotations, before.rotations)
    np.testing.assert_array_equal(motion.face, before.face)
    assert motion.meta["style_at"][1] == [1e308, {"animated": 1.0}] and motion.meta["emotion_at"][1][0] == 1e308
    for option, value, kept in (("--style-at", "0=calm,1e308=animated", dict(style="calm")),
                                ("--emotion-at", "0=happy,1e308=sad", dict(emotion="happy"))):
        out = tmp_path / f"{option[2:]}.npz"
        proc = subprocess.run([sys.executable, "-m", "diffsheg_core", "generate", str(speech), "-o", str(out),
                               "--steps", "2", option, value], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
        expected = generate(speech, steps=2, **kept)
        np.testing.assert_allclose(Motion.load_npz(out).rotations, expected.rotations, atol=1e-5)


NOT_FINITE = "is not a finite number of seconds; give the seconds from the start of the speech"


@pytest.mark.parametrize("args,message", [
    (["--style-at", "0=calm,inf=animated"], f"'inf=animated' in '0=calm,inf=animated': inf {NOT_FINITE}"),
    (["--style-at", "nan=calm"], f"nan {NOT_FINITE}"),
    (["--style-at", "0=calm,1e309=animated"], f"1e309 {NOT_FINITE}"),
    (["--emotion-at", "0=happy,-inf=sad"], f"-inf {NOT_FINITE}"),
    (["--style", "calm=1e309"], "style weight 'calm=1e309' must be a finite number >= 0"),
    (["--style", "calm=0.5,animated=inf"], "style weight 'animated=inf' must be a finite number >= 0"),
    (["--style-at", "0=calm,5=calm=nan,animated=1"], "style weight 'calm=nan' must be a finite number >= 0"),
    (["--emotion", "happy=1e309"], "the intensity of emotion 'happy' must be a finite number from 0 to 1, got inf"),
    (["--emotion-at", "0=sad=nan"], "the intensity of emotion 'sad' must be a finite number from 0 to 1, got nan"),
])
def test_the_cli_refuses_non_finite_times_and_weights_in_one_line(speech, tmp_path, args, message):
    """Issue 43 (c, d): an infinite or NaN change time, style weight or emotion intensity is
    refused with the option, the value and what to give, before anything is generated."""
    proc = subprocess.run([sys.executable, "-m", "diffsheg_core", "generate", str(speech), "-o",
                           str(tmp_path / "m.npz"), "--steps", "2", *args], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    error = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(error) == 1 and f"argument {args[0]}: " in error[0] and message in error[0], proc.stderr
    assert not (tmp_path / "m.npz").exists()


@pytest.mark.parametrize("settings,match", [
    (dict(style_at=((0, "calm"), (float("inf"), "animated"))),
     r"style_at: the style change time inf is not a finite number of seconds: give the seconds"),
    (dict(style_at={float("nan"): "calm"}), "the style change time nan is not a finite number of seconds"),
    (dict(emotion_at=((np.float64("inf"), "sad"),)), "the emotion change time inf is not a finite number"),
    (dict(style={"calm": float("inf")}), r"the weight of style 'calm' must be a finite number >= 0, got inf"),
    (dict(style={"calm": 1, "animated": np.float32("nan")}), "the weight of style 'animated' must be a finite"),
    (dict(style={"calm": -1}), "the weight of style 'calm' must be a finite number >= 0, got -1"),
    (dict(style_at=((0, {"calm": float("inf")}),)), "the weight of style 'calm' must be a finite number"),
    (dict(emotion={"happy": float("inf")}), "the intensity of emotion 'happy' must be a finite number from 0 to 1"),
    (dict(emotion={"happy": 10 ** 400}), "the intensity of emotion 'happy' must be a number from 0 to 1"),
    (dict(emotion_at=((0, {"sad": float("nan")}),)), "the intensity of emotion 'sad' must be a finite number"),
])
def test_settings_refuse_non_finite_times_and_weights(settings, match):
    """The same checks where the add-on and batch_render.py make their settings."""
    with pytest.raises(DiffshegError, match=match):
        GenerateSettings(**settings)
