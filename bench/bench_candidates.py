"""Benchmark: best-of-N windows (S2G-MDDiffusion's optimal motion selection) against N = 1 on
real speech, with the bundled model over several seeds. Prints, side by side:
seam-to-clip acceleration ratio (1 = seams invisible), beat alignment, gesture jitter and
speed, diversity between seeds, and the time, measured in one run on this machine:

    python bench/bench_candidates.py [--seconds 60] [--seeds 0 1 2] [--candidates 1 4]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import diffsheg_core
from diffsheg_core.audio import Audio, load_audio
from diffsheg_core.checkpoints import load_model
from diffsheg_core.rigs import BEAT
from diffsheg_core.training.metrics import (audio_beats, beat_alignment, diversity, layout_array, mean_jerk,
                                            motion_beats, speed)
from diffsheg_core.training.metrics.smoothness import foppas_seams, seam_smoothness

SPEECH = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "audio" / "2_scott_0_3_3.wav"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--candidates", type=int, nargs="+", default=[1, 4])
    args = parser.parse_args()
    bundle = load_model()
    audio = load_audio(SPEECH)
    audio = Audio(audio.samples[: int(args.seconds * audio.sample_rate)], audio.sample_rate, audio.path)
    beats = audio_beats(audio.samples, audio.sample_rate)
    g = BEAT.gesture_dim
    print(f"{bundle.model_id}, {args.seconds:g} s of {SPEECH.name}, seeds {args.seeds}")
    print(f"{'N':>3}{'seam/clip acc':>15}{'beat align':>12}{'jitter':>9}{'speed':>8}{'diversity':>11}{'time s':>9}")
    for n in args.candidates:
        rows, gestures, seconds = [], [], []
        for seed in args.seeds:
            started = time.perf_counter()
            motion = diffsheg_core.generate(audio, model=bundle, seed=seed, candidates=n)
            seconds.append(time.perf_counter() - started)
            x = layout_array(motion, BEAT)[:, :g]
            gestures.append(x)
            seams = foppas_seams(len(x), bundle.config.clip_len, bundle.sampling.overlap)
            rows.append((seam_smoothness(x, motion.fps, seams, bundle.sampling.overlap),
                         beat_alignment(beats, motion_beats(x, motion.fps)),
                         mean_jerk(x, motion.fps), float(speed(x, motion.fps).mean())))
        seam, align, jitter, pace = np.mean(rows, axis=0)
        print(f"{n:>3}{seam:>15.3f}{align:>12.3f}{jitter:>9.1f}{pace:>8.3f}"
              f"{diversity(np.stack(gestures)):>11.4f}{np.mean(seconds):>9.2f}")


if __name__ == "__main__":
    main()
