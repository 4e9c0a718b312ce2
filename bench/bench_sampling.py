"""The fast sampling against the model's own 25-step sampling, side by side in one run (issue 39).

Both samplings of the bundled model on real speech, seeds 0-3 (with two, the window Fréchet
distance of the same sampling moved 1.12x -> 1.27x between seeds 0-1 and 2-3):
- the real take 2_scott_0_1_1 (64 s; its motion capture as the reference, its TextGrid for the
  jaw's vowel/bilabial contrast), and its held-out last 20 s (the gestures the model learned
  come from the first 44 s only);
- speech the model never heard: 2_scott_0_3_3 (30 s) and another speaker, 12_zhao_2_3_3 (30 s),
  without a capture: figures against the quality sampling's.
With a distilled student in the model file (training.distill), fast runs the student and a row
"fast, guided teacher" runs the same fast sampling with the teacher's guided steps.
Per sampling it prints the seconds per take (the whole take, one thread), how much faster than
the quality sampling and than real time; then, per speech, wrist speed and jitter (against the
capture where there is one), diversity between seeds, the window Fréchet distance to the
capture (`window_fd`), lip-sync (mouth-envelope correlation; the jaw's vowel/bilabial
contrast on the take), blinks a minute and the seams' acceleration, each also as a ratio to the
quality sampling's; the joins of a regenerated range (issue 25's measure, seeds 7-9; also over
the same measure of the take before the range was regenerated: what the joins add), and how
far the styles lie apart (calm and animated wrist speed over conversational's).

    python bench/bench_sampling.py [--steps 3,6] [--model ckpt]

--steps adds the model's sampling at N evenly spaced steps (eta 0 and 1), the plain few-step
sampling the fast one was chosen against. Timings are only comparable within one run on an
otherwise idle machine: say which machine they came from.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

os.environ.setdefault("DIFFSHEG_THREADS", "1")

from diffsheg_core.audio import Audio, load_audio  # noqa: E402
from diffsheg_core.checkpoints import load_model  # noqa: E402
from diffsheg_core.foppas import sampling_settings  # noqa: E402
from diffsheg_core.motion import Motion  # noqa: E402
from diffsheg_core.pipeline import generate, regenerate  # noqa: E402
from diffsheg_core.rigs import BEAT  # noqa: E402
from diffsheg_core.training.evaluate import EvalInputs, evaluate, load_reference  # noqa: E402
from diffsheg_core.training.metrics import frechet_distance  # noqa: E402
from diffsheg_core.training.metrics.channels import gesture_array  # noqa: E402
from diffsheg_core.training.metrics.posture import wrist_positions  # noqa: E402
from diffsheg_core.training.metrics.textgrid import phone_tier, read_textgrid  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TAKE = DATA / "beat2" / "2_scott_0_1_1"
TAKE_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
UNSEEN = (DATA / "audio" / "2_scott_0_3_3.wav", DATA / "audio" / "12_zhao_2_3_3.wav")
HELD_OUT_S = 20.0
UNSEEN_S = 30.0
SEEDS = (0, 1, 2, 3)
RANGE = (300, 370)  # frames of the take regenerated (20 s to 24.7 s)
FIGURES = (("comparison", "wrist speed / reference", "speed/cap"),
           ("comparison", "wrist jitter / reference", "jitter/cap"),
           ("generated", "wrist speed (arm lengths/s)", "speed"),
           ("generated", "wrist jitter (arm lengths/s^2)", "jitter"),
           ("comparison", "Div between samples (gesture, rad)", "Div"),
           ("generated", "mouth open: vowels / bilabials", "jaw v/b"),
           ("generated", "mouth-envelope r", "env r"),
           ("generated", "blinks per minute", "blinks/min"),
           ("generated", "seam acceleration / in-clip", "seam"))


def window_fd(samples: list[Motion], reference: Motion, length: int = 34, stride: int = 4, dims: int = 16) -> float:
    """Fréchet distance between the 34-frame windows of `samples` and of `reference`: each
    window described by the mean pose, the spread and the mean speed of its upper-body
    gesture channels, reduced to the `dims` principal axes of the reference's windows."""
    def features(motion: Motion) -> np.ndarray:
        x = gesture_array(motion, BEAT)
        rows = [np.concatenate([w.mean(0), w.std(0), np.abs(np.diff(w, axis=0)).mean(0)])
                for w in (x[s: s + length] for s in range(0, len(x) - length + 1, stride))]
        return np.stack(rows)

    real = features(reference)
    mean, scale = real.mean(0), real.std(0) + 1e-6
    axes = np.linalg.svd((real - mean) / scale, full_matrices=False)[2][:dims]
    project = lambda f: ((f - mean) / scale) @ axes.T  # noqa: E731
    return frechet_distance(np.concatenate([project(features(m)) for m in samples]), project(real))


def cut(motion: Motion, start: int, stop: int) -> Motion:
    root = None if motion.root_translation is None else motion.root_translation[start:stop]
    return replace(motion, rotations=motion.rotations[start:stop], face=motion.face[start:stop], root_translation=root)


def seconds_of(audio: Audio, start: float, stop: float) -> Audio:
    rate = audio.sample_rate
    return Audio(audio.samples[int(start * rate): int(stop * rate)], rate)


def figures(samples: list[Motion], audio: Audio, clip_len: int, reference: Motion | None = None,
            phones=None) -> dict:
    n = min(m.n_frames for m in samples) if reference is None else min(reference.n_frames, *(m.n_frames for m in samples))
    samples = [cut(m, 0, n) for m in samples]
    reference = None if reference is None else cut(reference, 0, n)
    result = evaluate(EvalInputs(samples=samples, reference=reference, audio=audio, phones=phones, features=None,
                                 clip_len=clip_len, overlap=samples[0].meta["overlap"]), plots=False)
    out = {short: result[section].get(name) for section, name, short in FIGURES}
    if reference is not None:
        out["window FD"] = window_fd(samples, reference)
    return out


def _join_ratios(motion: Motion) -> tuple[float, float]:
    """The joints' acceleration at the two ends of RANGE over that inside it."""
    start, end = RANGE
    acc = np.linalg.norm(np.diff(motion.rotations, 2, axis=0), axis=2).mean(axis=1)
    inside = acc[start + 1: end - 3].mean()
    return acc[start - 3: start + 1].mean() / inside, acc[end - 3: end + 1].mean() / inside


def join_ratios(take: Motion, audio: Audio, model, sampling: str) -> tuple[float, float, float, float]:
    """Issue 25's measure: the joints' acceleration at the two joins of a regenerated range over
    that inside it, averaged over seeds 7-9; then each over the same ratio in the take before
    the range was regenerated. The first pair also counts how the take happens to move around
    the range's ends (before any regeneration, the fast take's seed 0 accelerates at the left
    end 0.93x as much as inside, the quality take's 0.47x); the second is what the joins add."""
    new = np.mean([_join_ratios(regenerate(take, audio, start=RANGE[0], end=RANGE[1], model=model, seed=seed,
                                           sampling=sampling)) for seed in (7, 8, 9)], axis=0)
    own = _join_ratios(take)
    return float(new[0]), float(new[1]), float(new[0] / own[0]), float(new[1] / own[1])


def style_spread(audio: Audio, model, sampling) -> tuple[float, float]:
    """calm's and animated's wrist speed over conversational's, seed 0."""
    speed = {}
    for style in ("calm", "conversational", "animated"):
        wrists = wrist_positions(generate(audio, model=model, seed=0, style=style, sampling=sampling))
        speed[style] = float(np.linalg.norm(np.diff(wrists, axis=0), axis=-1).mean())
    return speed["calm"] / speed["conversational"], speed["animated"] / speed["conversational"]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", default="", help="comma-separated even step counts to add (default: none)")
    p.add_argument("--model", help="checkpoint (default: the bundled model)")
    args = p.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, one thread; seeds {list(SEEDS)}")
    bundle = load_model(args.model)
    # label: (model, sampling); with a distilled student, fast runs it and "fast, guided" the teacher
    samplings: dict[str, tuple] = {"quality": (bundle, "quality"), "fast": (bundle, "fast")}
    if bundle.student is not None:
        samplings["fast, guided teacher"] = (replace(bundle, student=None), "fast")
    for n in filter(None, args.steps.split(",")):
        for eta in (0.0, 1.0):
            samplings[f"{n} even steps, eta {eta:g}"] = (bundle, replace(
                sampling_settings(bundle.sampling, "quality").with_steps(int(n)), eta=eta))
    take_audio = load_audio(TAKE.with_suffix(".wav"))
    capture = load_reference(TAKE_BVH, fps=15.0)
    phones = phone_tier(read_textgrid(TAKE.with_suffix(".TextGrid")), str(TAKE.with_suffix(".TextGrid")))
    held_from = take_audio.duration - HELD_OUT_S
    held_audio = seconds_of(take_audio, held_from, take_audio.duration)
    held_capture = cut(capture, int(held_from * 15), capture.n_frames)
    unseen = {path.stem: seconds_of(load_audio(path), 0.0, UNSEEN_S) for path in UNSEEN}
    for model, sampling in samplings.values():  # load and warm the networks
        generate(seconds_of(take_audio, 0, 3), model=model, sampling=sampling)

    rows: dict[str, dict] = {}
    for label, (model, sampling) in samplings.items():
        started = time.perf_counter()
        takes = [generate(take_audio, model=model, seed=s, sampling=sampling) for s in SEEDS]
        seconds = (time.perf_counter() - started) / len(SEEDS)
        row = {"seconds": seconds, "take": figures(takes, take_audio, bundle.config.clip_len, capture, phones)}
        held = [generate(held_audio, model=model, seed=s, sampling=sampling) for s in SEEDS]
        row["held-out 20 s"] = figures(held, held_audio, bundle.config.clip_len, held_capture)
        for name, audio in unseen.items():
            row[name] = figures([generate(audio, model=model, seed=s, sampling=sampling) for s in SEEDS], audio,
                                bundle.config.clip_len)
        if isinstance(sampling, str):
            row["joins"] = join_ratios(takes[0], take_audio, model, sampling)
            row["styles"] = style_spread(unseen[UNSEEN[0].stem], model, sampling)
        rows[label] = row
        print(f"{label}: {seconds:.2f} s per {take_audio.duration:.0f} s take", flush=True)

    base = rows["quality"]
    print(f"\n| sampling | s per take | x faster | x real time | regenerated joins (left, right) "
          f"| over the take's own | calm, animated speed |")
    print("|---|---|---|---|---|---|---|")
    for label, row in rows.items():
        joins = own = ""
        if "joins" in row:
            ratios = [a / b for a, b in zip(row["joins"], base["joins"])]
            joins = "%.2f, %.2f (%.2fx, %.2fx)" % (*row["joins"][:2], *ratios[:2])
            own = "%.2f, %.2f (%.2fx, %.2fx)" % (*row["joins"][2:], *ratios[2:])
        styles = "" if "styles" not in row else "%.2f, %.2f" % row["styles"]
        print(f"| {label} | {row['seconds']:.2f} | {base['seconds'] / row['seconds']:.1f} | "
              f"{take_audio.duration / row['seconds']:.0f} | {joins} | {own} | {styles} |")
    for speech in ["take", "held-out 20 s", *unseen]:
        names = [k for k, v in base[speech].items() if v is not None]
        print(f"\n{speech} (ratio to quality's)\n| sampling | " + " | ".join(names) + " |")
        print("|---|" + "---|" * len(names))
        for label, row in rows.items():
            cells = [f"{row[speech][k]:.3g} ({row[speech][k] / base[speech][k]:.2f}x)" for k in names]
            print(f"| {label} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
