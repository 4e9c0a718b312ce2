"""Fewer sampling steps against the bundled model's own sampling, side by side in one run.

On the real take 2_scott_0_1_1 (its motion capture as the reference, its TextGrid for the
lip-sync contrast), seeds 0 and 1: the bundled model's sampling settings (25 DDIM steps,
later windows from step 17, eta 1, the refining pass) and the same settings at N steps with
eta 0 (deterministic DDIM) and eta 1, for each N asked. Prints, per setting, the seconds per
take and its ratio to the shipped sampling's, and the quality figures issue 39 judges a
few-step sampler by: wrist speed and jitter against the capture, diversity between seeds,
the jaw's vowel/bilabial contrast, the mouth-envelope correlation and the seams'
acceleration, each also as a ratio to the shipped sampling's.

    python bench/bench_sampling.py [--steps 4,6,8] [--model ckpt]

Timings are only comparable within one run on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from diffsheg_core.audio import load_audio
from diffsheg_core.checkpoints import load_model
from diffsheg_core.pipeline import generate
from diffsheg_core.training.evaluate import EvalInputs, evaluate, load_reference
from diffsheg_core.training.metrics.textgrid import phone_tier, read_textgrid

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
TAKE_TEXTGRID = DATA / "beat2" / "2_scott_0_1_1.TextGrid"
TAKE_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
SEEDS = (0, 1)
FIGURES = (("comparison", "wrist speed / reference", "speed/cap"),
           ("comparison", "wrist jitter / reference", "jitter/cap"),
           ("comparison", "Div between samples (gesture, rad)", "Div"),
           ("generated", "mouth open: vowels / bilabials", "jaw v/b"),
           ("generated", "mouth-envelope r", "env r"),
           ("generated", "seam acceleration / in-clip", "seam"))


def settings(bundle, steps: list[int]) -> dict:
    base = bundle.sampling
    out = {f"shipped ({base.steps} steps, eta {base.eta:g})": base}
    for n in steps:
        for eta in (0.0, 1.0):
            out[f"{n} steps, eta {eta:g}"] = replace(base.with_steps(n), eta=eta)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", default="4,6,8", help="comma-separated step counts to try (default %(default)s)")
    p.add_argument("--model", help="checkpoint (default: the bundled model)")
    args = p.parse_args()
    bundle = load_model(args.model)
    audio = load_audio(TAKE_WAV)
    capture = load_reference(TAKE_BVH, fps=15.0)
    phones = phone_tier(read_textgrid(TAKE_TEXTGRID), str(TAKE_TEXTGRID))
    rows = []
    for label, sampling in settings(bundle, [int(n) for n in args.steps.split(",")]).items():
        started = time.perf_counter()
        samples = [generate(audio, model=bundle, seed=s, sampling=sampling) for s in SEEDS]
        seconds = (time.perf_counter() - started) / len(SEEDS)
        n = min(capture.n_frames, *(m.n_frames for m in samples))

        def part(m):
            root = None if m.root_translation is None else m.root_translation[:n]
            return replace(m, rotations=m.rotations[:n], face=m.face[:n], root_translation=root)

        result = evaluate(EvalInputs(samples=[part(m) for m in samples], reference=part(capture), audio=audio,
                                     phones=phones, features=None, clip_len=bundle.config.clip_len,
                                     overlap=samples[0].meta["overlap"]), plots=False)
        rows.append((label, seconds, [result[section][name] for section, name, _ in FIGURES]))
        print(f"{label}: {seconds:.1f} s per take", flush=True)
    _, base_seconds, base = rows[0]
    print(f"\n| setting | s/take | x faster | " + " | ".join(short for _, _, short in FIGURES) + " |")
    print("|---|---|---|" + "---|" * len(FIGURES))
    for label, seconds, values in rows:
        cells = [f"{v:.3g} ({v / b:.2f}x)" for v, b in zip(values, base)]
        print(f"| {label} | {seconds:.1f} | {base_seconds / seconds:.1f} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
