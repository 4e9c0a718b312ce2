"""The whole body of models on real speech against the real capture, measured side by side.

On the real take 2_scott_0_1_1's speech, seeds 0-2, each model's take with its hips and
legs (a whole-body model's own, settled and planted: lower_body.plant; a `beat` model's
cut from the capture by motion matching: lower_body.add_lower_body), against the BEAT2
SMPL-X capture of the same take: hips sway speed and range, knee bend range, foot skating
(SpeechAct's ratio), the share of frames with a foot in contact and the most a contact sole
moves between frames; on the whole take and on its last 20 s, which neither the teacher nor
the lower-body library saw. Prints one table; writes OUT/whole_body.md.

    python bench/eval_whole_body.py --model diffsheg_core/weights/default.safetensors --model ../runs/v8.safetensors
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from diffsheg_core import lower_body as lb
from diffsheg_core.audio import load_audio
from diffsheg_core.checkpoints import load_model
from diffsheg_core.pipeline import generate

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
TAKE_NPZ = DATA / "beat2" / "2_scott_0_1_1.npz"
SEEDS = (0, 1, 2)
FPS = 15.0
FIGURES = ("sway speed", "sway range", "knee range", "skating", "contact", "contact step")


def figures(lower: np.ndarray, trans: np.ndarray, spans: dict | None) -> dict[str, float]:
    """lower_body.figures, and with contact `spans` the share of frames with a foot down and
    the most a contact sole moves from frame to frame (cm)."""
    out = lb.figures(lower, trans, FPS)
    if spans is None:
        spans = lb.contacts(lower, trans, FPS)
    down = np.zeros(len(lower), bool)
    step = 0.0
    soles = lb.foot_positions(lower, trans)
    for side, side_spans in spans.items():
        for a, b in side_spans:
            down[a:b + 1] = True
            if b > a:
                step = max(step, float(np.linalg.norm(np.diff(soles[side][1][a:b + 1], axis=0), axis=-1).max()))
    return {**out, "contact": float(down.mean()), "contact step": 100 * step}


def part_spans(spans: dict, frames: slice, n: int) -> dict:
    first = range(n)[frames].start
    return {side: [(max(a, first) - first, b - first) for a, b in v if b >= first] for side, v in spans.items()}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", action="append", help="checkpoint (repeat to compare; default: the bundled model)")
    p.add_argument("--out", default="out/eval-whole-body")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    audio = load_audio(TAKE_WAV)
    lower, trans, _ = lb.read_capture(TAKE_NPZ, FPS)
    held = slice(-int(lb.HELD_OUT_S * FPS), None)
    rows = {("capture", "take"): figures(lower, trans, None),
            ("capture", "last 20 s"): figures(lower[held], trans[held], None)}
    for path in args.model or [None]:
        bundle = load_model(path)
        made = {"take": [], "last 20 s": []}
        started = time.perf_counter()
        for seed in SEEDS:
            motion = generate(audio, model=bundle, seed=seed)
            legs = lb.lower_rotations(motion)
            root, spans = motion.root_translation.astype(np.float64), motion.meta["contacts"]
            made["take"].append(figures(legs, root, spans))
            made["last 20 s"].append(figures(legs[held], root[held], part_spans(spans, held, motion.n_frames)))
        print(f"{bundle.model_id}: {(time.perf_counter() - started) / len(SEEDS):.1f} s per take", flush=True)
        for part, values in made.items():
            rows[(bundle.model_id, part)] = {k: (min(v[k] for v in values), max(v[k] for v in values)) for k in FIGURES}
    lines = ["| body | part | sway speed (m/s) | sway range (m) | knee range (deg) | skating (%) | contact (%) | "
             "contact step (cm) |", "|---|---|---|---|---|---|---|---|"]
    scale = {"skating": 100, "contact": 100}
    for (name, part), values in rows.items():
        cells = []
        for k in FIGURES:
            v = values[k]
            s = scale.get(k, 1)
            cells.append(f"{s * v[0]:.3g}-{s * v[1]:.3g}" if isinstance(v, tuple) else f"{s * v:.3g}")
        lines.append(f"| {name} | {part} | " + " | ".join(cells) + " |")
    text = (f"# The whole body on 2_scott_0_1_1's speech, seeds {SEEDS} (ranges over seeds)\n\n"
            + "\n".join(lines) + "\n")
    (out / "whole_body.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
