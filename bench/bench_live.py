"""Live generation: latency, compute and what the hop costs against offline generation.

For each hop H tried (and the diffusion steps), on one real take with its phone timings
(../shared/data/beat2/2_scott_0_1_1.wav and .TextGrid):

- quality against offline `generate` of the same speech and seeds: wrist speed and
  jitter, acceleration at the joins (the first frame of every hop; offline, every FOPPAS
  seam) over that elsewhere, lip-sync (mouth-to-voice envelope correlation; jawOpen at
  open vowels over bilabials);
- compute per second of speech (the audio fed as fast as the engine takes it);
- the legs, as a live session makes them (a whole-body model's own, from the live engine,
  planted as they come: lower_body.PlantStream; a `beat` model's cut from the capture to go
  with each hop of the upper body: lower_body.LowerBodyStream) against offline legs and the
  capture: hips sway speed and range, knee bend range, foot skating, time in contact, the
  most a contact foot moves between frames, and the milliseconds per hop they cost;
- with --realtime: latency p50/p95/max from the audio arriving to the frame being shown,
  the file played at real time through a `LiveSession` (as `diffsheg live` runs it), idle
  and with another process keeping one core busy (--busy).

    python bench/bench_live.py                         # quality and compute, hops 2 3, lookahead 1 2
    python bench/bench_live.py --hops 2 --lookaheads 1 --seeds 8   # the defaults, eight seeds
    python bench/bench_live.py --sampling fast quality --hops 2 --lookaheads 1   # both samplings
    python bench/bench_live.py --hops 2 --lookaheads 1 --realtime --seconds 30 --busy
    python bench/bench_live.py --realtime --seconds 600 --hops 2 --lookaheads 1 --no-quality --no-legs   # 10 minutes
    python bench/bench_live.py --hops 3 --lookaheads 2 --no-through-lookahead --face-scale 1 --skip-scale 2.2 \
        --no-match-velocity                             # live's defaults before 2026-12-06
    python bench/bench_live.py --model ../runs/default-v8.safetensors   # another model

One thread (DIFFSHEG_THREADS=1, the default). Say which machine the figures came from.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from diffsheg_core.audio import Audio, read_audio_file  # noqa: E402
from diffsheg_core.checkpoints import load_model  # noqa: E402
from diffsheg_core.live.engine import LiveConfig, LiveEngine  # noqa: E402
from diffsheg_core.motion import Motion  # noqa: E402
from diffsheg_core.pipeline import generate  # noqa: E402
from diffsheg_core.runtime.backends import open_network  # noqa: E402
from diffsheg_core.settings import GenerateSettings  # noqa: E402
from diffsheg_core.training.metrics.channels import face_channel, mouth_opening  # noqa: E402
from diffsheg_core.training.metrics.lipsync import envelope_correlation, phoneme_contrast  # noqa: E402
from diffsheg_core.training.metrics.posture import naturalness  # noqa: E402
from diffsheg_core.training.metrics.smoothness import acceleration_per_frame, foppas_seams  # noqa: E402
from diffsheg_core.training.metrics.textgrid import phone_tier, read_textgrid  # noqa: E402

TAKE = ROOT.parent / "shared" / "data" / "beat2" / "2_scott_0_1_1"


def quality(motion: Motion, audio: Audio, joins: list[int], phones) -> dict:
    """The figures compared between live and offline."""
    nat = naturalness(motion)
    gestures = motion.rotations.reshape(motion.n_frames, -1)
    acc = acceleration_per_frame(gestures, motion.fps)
    at = np.zeros(len(acc), bool)
    for j in joins:
        at[max(j - 1, 0): j + 1] = True
    corr, _ = envelope_correlation(mouth_opening(motion), motion.fps, audio.samples, audio.sample_rate)
    contrast = phoneme_contrast(face_channel(motion, "jawOpen"), motion.fps, phones)
    return {"wrist speed": nat["wrist speed (arm lengths/s)"], "wrist jitter": nat["wrist jitter (arm lengths/s^2)"],
            "join acc": float(acc[at].mean() / acc[~at].mean()), "mouth-voice r": corr,
            "jaw open/bilabial": contrast["ratio"]}


def run_live(bundle, network, audio: Audio, live: LiveConfig, settings: GenerateSettings) -> tuple[Motion, float]:
    """The engine fed 20 ms chunks as fast as it takes them: (motion, compute seconds)."""
    engine = LiveEngine(bundle, network, settings, audio.sample_rate, live)
    chunk, compute = audio.sample_rate // 50, 0.0
    for i in range(0, audio.n_samples, chunk):
        engine.push(audio.samples[i: i + chunk])
        while engine.ready():
            t0 = time.perf_counter()
            engine.step()
            compute += time.perf_counter() - t0
    t0 = time.perf_counter()
    engine.finish()
    compute += time.perf_counter() - t0
    return engine.motion(), compute


def mean_of(rows: list[dict]) -> dict:
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def bench_quality(args, bundle, network, audio: Audio, phones) -> None:
    seeds = range(args.seeds)
    base = {}
    for sampling in args.sampling:
        offline = []
        for seed in seeds:
            m = generate(audio, settings=GenerateSettings(model=bundle, seed=seed, threads=1, sampling=sampling))
            offline.append(quality(m, audio, foppas_seams(m.n_frames, bundle.config.clip_len, 4), phones))
        base[sampling] = mean_of(offline)
    print(f"\n{audio.duration:.1f} s of speech, seeds {list(seeds)}; ratios are live / offline of the same sampling")
    print(f"{'setting':<30}" + "".join(f"{k:>19}" for k in base[args.sampling[0]]) + f"{'compute/s':>11}")
    for sampling, values in base.items():
        print(f"{'offline ' + sampling:<30}" + "".join(f"{v:>19.3f}" for v in values.values()))
    for sampling, steps, hop, lookahead in settings_tried(args):
        rows, compute = [], 0.0
        for seed in seeds:
            settings = GenerateSettings(model=bundle, seed=seed, steps=steps, threads=1, sampling=sampling)
            m, c = run_live(bundle, network, audio, live_config(args, hop, lookahead), settings)
            compute += c / audio.duration / len(seeds)
            rows.append(quality(m, audio, list(range(hop, m.n_frames, hop)), phones))
        q = mean_of(rows)
        cells = "".join(f"{v:>11.3f} ({v / base[sampling][k]:4.2f}x)" for k, v in q.items())
        print(f"{label(sampling, steps, hop, lookahead):<30}{cells}{compute:>10.3f}s", flush=True)


def bench_legs(args, bundle, network, audio: Audio) -> None:
    """Live legs against offline's: a whole-body model's own legs as the live engine makes
    them, planted as they come (PlantStream); a `beat` model's cut from the capture to go
    with the offline arms (LowerBodyStream)."""
    from diffsheg_core import lower_body as lb

    capture = lb.read_capture(TAKE.with_suffix(".npz"), bundle.config.fps)
    fps, own = bundle.config.fps, bool(bundle.layout.root_translation)
    print(f"\nlegs ({'the model' if own else 'the capture'}'s), {audio.duration:.1f} s of speech, seeds "
          f"{list(range(args.seeds))}, hops of {args.hops[0]}, lookahead {args.lookaheads[0]} "
          f"(capture: {_legs_cells(lb.figures(capture[0], capture[1], fps))})")
    for seed in range(args.seeds):
        settings = GenerateSettings(model=bundle, seed=seed, threads=1, sampling=args.sampling[0])
        offline = generate(audio, settings=settings)
        hop = args.hops[0]
        live = live_config(args, hop, args.lookaheads[0])
        made = run_live(bundle, network, audio, live, settings)[0] if own else lb.upper_body(offline)
        stream, started = lb.PlantStream(fps) if own else lb.LowerBodyStream(fps, seed), time.perf_counter()
        for i in range(0, made.n_frames, hop):
            root = None if made.root_translation is None else made.root_translation[i:i + hop]
            stream.add(replace(made, rotations=made.rotations[i:i + hop], face=made.face[i:i + hop],
                               root_translation=root))
        per_hop = (time.perf_counter() - started) / -(-made.n_frames // hop) * 1000
        lower = offline.rotations[:, -len(lb.JOINTS):].astype(np.float64)
        trans = offline.root_translation.astype(np.float64)
        spans = {side: [tuple(s) for s in v] for side, v in offline.meta["contacts"].items()}
        print(f"  seed {seed} offline: {_legs_cells(lb.figures(lower, trans, fps))}, {_contact_cells(lower, trans, spans, fps)}")
        print(f"  seed {seed} live:    {_legs_cells(lb.figures(stream.lower, stream.trans, fps))}, "
              f"{_contact_cells(stream.lower, stream.trans, stream.contacts(), fps)}, {per_hop:.1f} ms per hop")


def _legs_cells(f: dict) -> str:
    return (f"sway {f['sway speed']:.3f} m/s over {f['sway range']:.2f} m, knees {f['knee range']:.0f} deg, "
            f"skating {100 * f['skating']:.1f} %")


def _contact_cells(lower, trans, spans: dict, fps: float) -> str:
    from diffsheg_core import lower_body as lb

    soles, worst = lb.foot_positions(lower, trans), 0.0
    for side, side_spans in spans.items():
        for a, b in side_spans:
            if b > a:
                worst = max(worst, float(np.linalg.norm(np.diff(soles[side][1][a:b + 1], axis=0), axis=-1).max()))
    share = np.mean([sum(b - a + 1 for a, b in v) / len(lower) for v in spans.values()])
    first = min((a for v in spans.values() for a, _ in v), default=None)
    return (f"in contact {100 * share:.0f} %, first contact at "
            f"{'never' if first is None else f'{first / fps:.1f} s'}, contact foot moves <= {100 * worst:.2f} cm")


LIVE_OPTIONS = ("legs_eta", "skip_scale", "legs_skip_scale", "face_scale", "through_lookahead", "candidates",
                "match_velocity")


def live_config(args, hop: int, lookahead: int) -> LiveConfig:
    """The default LiveConfig at `hop` and `lookahead`, with the options given."""
    given = {name: getattr(args, name) for name in LIVE_OPTIONS if getattr(args, name) is not None}
    return replace(LiveConfig.chosen(hop, lookahead), **given)


def settings_tried(args) -> list[tuple]:
    return [(sampling, steps, hop, lookahead) for sampling in args.sampling for steps in args.steps
            for hop in args.hops for lookahead in args.lookaheads]


def label(sampling: str, steps, hop: int, lookahead: int) -> str:
    return f"{sampling} H={hop} L={lookahead}" + (f" steps={steps}" if steps else "")


def busy_loop() -> None:
    while True:
        pass


def bench_latency(args, audio_path: Path) -> None:
    from diffsheg_core.live.session import LiveSession, latency_summary
    from diffsheg_core.live.sources import FileSource

    print(f"\nreal time: the first {args.seconds:g} s of {audio_path.name} (played again from its start "
          "as often as that needs) at 1x, latency from the audio arriving to the frame being shown (s)")
    print(f"{'setting':<36}{'p50':>8}{'p95':>8}{'max':>8}{'compute/s':>11}{'underrun s':>12}")
    clip = Path(args.out) / "live_clip.wav"
    import soundfile as sf
    full = read_audio_file(audio_path)
    n = int(args.seconds * full.sample_rate)
    sf.write(clip, np.tile(full.samples, -(-n // len(full.samples)))[:n], full.sample_rate)
    for load in (["idle", "busy"] if args.busy else ["idle"]):
        hog = None
        if load == "busy":
            hog = multiprocessing.Process(target=busy_loop, daemon=True)
            hog.start()
        try:
            for sampling, steps, hop, lookahead in settings_tried(args):
                settings = GenerateSettings(model=args.model, seed=0, steps=steps, threads=1, sampling=sampling)
                session = LiveSession(FileSource(str(clip)), settings, live_config(args, hop, lookahead))
                result = session.run_to_end()
                s = latency_summary(result.latencies)
                print(f"{label(sampling, steps, hop, lookahead) + ' ' + load:<36}{s['p50']:>8.3f}{s['p95']:>8.3f}{s['max']:>8.3f}"
                      f"{result.compute / result.audio.duration:>10.3f}s{result.underrun_seconds:>12.2f}", flush=True)
                if args.seconds >= 120:  # flat over a long session: each minute's latency
                    for minute in range(int(args.seconds // 60)):
                        m = latency_summary([(t, lat) for t, lat in result.latencies if minute * 60 <= t < minute * 60 + 60])
                        print(f"  minute {minute + 1:>2}: p50 {m['p50']:.3f}, p95 {m['p95']:.3f}, max {m['max']:.3f}",
                              flush=True)
        finally:
            if hog is not None:
                hog.terminate()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hops", type=int, nargs="+", default=[2, 3])
    p.add_argument("--sampling", nargs="+", default=["fast"], choices=["fast", "quality"],
                   help="samplings tried (default: fast, the default)")
    p.add_argument("--steps", type=int, nargs="+", default=[0], help="diffusion steps (0: the sampling's)")
    p.add_argument("--lookaheads", type=int, nargs="+", default=[1, 2], help="frames of lookahead tried")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--seconds", type=float, default=20.0,
                   help="audio played in the real-time runs (the take again from its start past its end; "
                        "120 and more: each minute's latency too)")
    p.add_argument("--realtime", action="store_true", help="also measure latency at real time")
    p.add_argument("--busy", action="store_true", help="real time also with one core kept busy")
    p.add_argument("--no-quality", action="store_true")
    p.add_argument("--no-legs", action="store_true")
    p.add_argument("--model", help="checkpoint (default: the bundled model)")
    p.add_argument("--legs-eta", type=float, help="DDIM eta of a whole-body model's legs live (LiveConfig.legs_eta)")
    p.add_argument("--skip-scale", type=float,
                   help="live gesture skip guidance, times the settings' (LiveConfig.skip_scale)")
    p.add_argument("--legs-skip-scale", type=float,
                   help="live skip guidance of a whole-body model's legs, times the settings' "
                        "(LiveConfig.legs_skip_scale)")
    p.add_argument("--face-scale", type=float,
                   help="live face classifier-free guidance, times the settings' (LiveConfig.face_scale)")
    p.add_argument("--through-lookahead", action=argparse.BooleanOptionalAction,
                   help="windows run on through their lookahead frames (LiveConfig.through_lookahead)")
    p.add_argument("--candidates", type=int,
                   help="best of this many samplings of each live window (LiveConfig.candidates)")
    p.add_argument("--match-velocity", action=argparse.BooleanOptionalAction,
                   help="a window's new gestures continue the frames shown in velocity too (LiveConfig.match_velocity)")
    p.add_argument("--out", default="/tmp")
    args = p.parse_args()
    args.steps = [s or None for s in args.steps]
    os.environ.setdefault("DIFFSHEG_THREADS", "1")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    bundle = load_model(args.model)
    network = open_network(bundle, "auto", "auto", "fp32", 1)
    audio = read_audio_file(TAKE.with_suffix(".wav"))
    phones = phone_tier(read_textgrid(TAKE.with_suffix(".TextGrid")))
    if not args.no_quality:
        bench_quality(args, bundle, network, audio, phones)
    if not args.no_legs:
        bench_legs(args, bundle, network, audio)
    if args.realtime:
        bench_latency(args, TAKE.with_suffix(".wav"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
