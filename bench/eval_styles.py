"""Styles, best-of-N and naturalness of a model on real speech, measured side by side.

On the real take 2_scott_0_1_1 (its motion capture as the reference; its TextGrid for the
lip-sync contrast), three seeds per setting:
  - every named style of the model, mixes of its first and last style (0.25 / 0.5 / 0.75)
    and style guidance 1.5 and 2 on the last (the liveliest in the bundled model);
  - candidates 1 and 4 in the style closest to the capture (conversational), and there
    without the sampler's seam carry (FoppasConfig.carry) and without its refining pass
    (FoppasConfig.refine) when the model sets them;
each with wrist speed, jitter and spread (and their ratios to the capture), head pitch,
diversity between seeds, FGD to the take (with --autoencoder), beat alignment, lip-sync and
blinks; the take's last 20 s (which the teacher's gesture library never saw) are reported
apart. Prints one table; writes OUT/styles.md and OUT/styles.json.

    python bench/eval_styles.py [--model ckpt] [--autoencoder ../runs/ae-v3.pt] [--out out/eval-styles] [--only LABEL]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

from diffsheg_core.audio import Audio, load_audio
from diffsheg_core.checkpoints import load_model
from diffsheg_core.motion import Motion
from diffsheg_core.pipeline import generate
from diffsheg_core.training.corpus.gestures import HELD_OUT_SECONDS
from diffsheg_core.training.evaluate import EvalInputs, evaluate, load_reference
from diffsheg_core.training.metrics.textgrid import phone_tier, read_textgrid

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
TAKE_TEXTGRID = DATA / "beat2" / "2_scott_0_1_1.TextGrid"
TAKE_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
SEEDS = (0, 1, 2)
COLUMNS = (
    ("generated", "wrist speed (arm lengths/s)", "speed"),
    ("comparison", "wrist speed / reference", "speed/cap"),
    ("comparison", "wrist jitter / reference", "jitter/cap"),
    ("comparison", "wrist spread / reference", "spread/cap"),
    ("comparison", "head pitch - reference (deg)", "pitch-cap"),
    ("comparison", "Div between samples (gesture, rad)", "Div"),
    ("comparison", "FGD", "FGD"),
    ("generated", "BA", "BA"),
    ("generated", "seam acceleration / in-clip", "seam"),
    ("generated", "mouth open: vowels / bilabials", "jaw v/b"),
    ("generated", "mouthClose: bilabials - vowels", "close b-v"),
    ("generated", "mouth-envelope r", "env r"),
    ("generated", "blinks per minute", "blinks/min"),
)


def settings(bundle) -> list[tuple[str, dict]]:
    names = bundle.style_names or [str(i) for i in range(bundle.config.style_dim)]
    first, last = names[0], names[-1]
    rows = [(f"style {n}", {"style": n}) for n in names]
    if first != last:
        rows += [(f"{first} {1 - w:g} + {last} {w:g}", {"style": {first: 1 - w, last: w}})
                 for w in (0.25, 0.5, 0.75)]
    if bundle.null_style:
        rows += [(f"{last}, style guidance {g:g}", {"style": last, "style_guidance": g}) for g in (1.5, 2.0)]
    middle = "conversational" if "conversational" in names else first
    rows += [(f"{middle}, candidates 4", {"style": middle, "candidates": 4})]
    if bundle.sampling.carry:  # the seams as the sampler left them before the overlap's gap was carried
        rows += [(f"{middle}, seam carry off", {"style": middle, "sampling": replace(bundle.sampling, carry=0)})]
    if bundle.sampling.refine is not None:  # the windows as sampled, without the last pass over them
        rows += [(f"{middle}, refining pass off", {"style": middle, "sampling": replace(bundle.sampling, refine=None)})]
    return rows


def part(motion: Motion, frames: slice) -> Motion:
    root = None if motion.root_translation is None else motion.root_translation[frames]
    return replace(motion, rotations=motion.rotations[frames], face=motion.face[frames], root_translation=root)


def audio_part(audio: Audio, frames: slice, fps: float) -> Audio:
    rate = audio.sample_rate
    start = None if frames.start is None else int(frames.start * rate / fps)
    return Audio(audio.samples[start:], rate, audio.path)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", help="checkpoint (default: the bundled model)")
    p.add_argument("--autoencoder", help="motion autoencoders (.pt) for FGD")
    p.add_argument("--out", default="out/eval-styles")
    p.add_argument("--only", help="measure only the settings whose label holds this text (e.g. 'style conversational')")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bundle = load_model(args.model)
    features = None
    if args.autoencoder:
        from diffsheg_core.training.autoencoder import MotionFeatures

        features = MotionFeatures.load(args.autoencoder)
    audio = load_audio(TAKE_WAV)
    capture = load_reference(TAKE_BVH, fps=15.0)
    phones = phone_tier(read_textgrid(TAKE_TEXTGRID), str(TAKE_TEXTGRID))
    tail = slice(-int(HELD_OUT_SECONDS * capture.fps), None)
    results: dict[str, dict] = {}
    for label, options in settings(bundle):
        if args.only and args.only not in label:
            continue
        started = time.perf_counter()
        samples = [generate(audio, model=bundle, seed=s, **options) for s in SEEDS]
        seconds = (time.perf_counter() - started) / len(SEEDS)
        n = min(capture.n_frames, *(m.n_frames for m in samples))
        for name, frames in (("take", slice(0, n)), ("last 20 s", slice(n + tail.start, n))):
            inputs = EvalInputs(samples=[part(m, frames) for m in samples], reference=part(capture, frames),
                                audio=audio if name == "take" else audio_part(audio, frames, capture.fps),
                                phones=phones if name == "take" else None, features=features,
                                clip_len=bundle.config.clip_len, overlap=samples[0].meta["overlap"])
            result = evaluate(inputs, plots=False)
            result["seconds per take"] = seconds
            results[f"{label} | {name}"] = result
        print(f"{label}: {seconds:.1f} s per take", flush=True)
    header = "| setting | part | " + " | ".join(c[2] for c in COLUMNS) + " | s/take |"
    rows = [header, "|---|---|" + "---|" * (len(COLUMNS) + 1)]
    for key, result in results.items():
        cells = []
        for section, metric, _ in COLUMNS:
            value = result[section].get(metric)
            cells.append("" if value is None else f"{value:.3g}")
        label, name = key.split(" | ")
        rows.append(f"| {label} | {name} | " + " | ".join(cells) + f" | {result['seconds per take']:.1f} |")
    capture_row = results[next(iter(results))]["reference"]
    text = (f"# Styles, best-of-N and naturalness of {bundle.model_id} on 2_scott_0_1_1\n\n"
            f"Capture: wrist speed {capture_row['wrist speed (arm lengths/s)']:.3f} arm lengths/s, jitter "
            f"{capture_row['wrist jitter (arm lengths/s^2)']:.2f}, spread "
            f"{capture_row['wrist spread (arm lengths)']:.3f}, head pitch {capture_row['head pitch (deg, down)']:.1f} "
            f"deg (whole take). Seeds {SEEDS}.\n\n" + "\n".join(rows) + "\n")
    (out / "styles.md").write_text(text)
    (out / "styles.json").write_text(json.dumps(results, indent=1, default=float))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
