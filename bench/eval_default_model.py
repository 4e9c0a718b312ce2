"""Evaluate the bundled default model (or any checkpoint) the way its model card reports it.

Runs the project's evaluation command (`python -m diffsheg_core evaluate`) on speech the
model never saw, with the teacher's figures beside the model's:
  heldout       about 60 s of held-out corpus utterances (the val split of the corpus,
                concatenated), reference = their teacher motion, phones from the synthesiser
  take_teacher  the real take 2_scott_0_1_1 (audio + TextGrid), reference = the teacher run
                on its real phone timings
  take_mocap    the same take, reference = its real motion capture (gesture figures, FGD)
  teacher_mocap the teacher itself on that take, against the motion capture
  <recording>   real recordings with no motion (2_scott_0_4_4, 12_zhao_2_3_3): model only
and times generate() on 60 s of 2_scott_0_3_3.wav. Writes OUT/summary.md and
OUT/summary.json; each evaluation's report.md and plots are in OUT/<name>/.

    python bench/eval_default_model.py --autoencoder ../runs/ae-corpus.pt [--model ckpt] [--out out/eval-default]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import soundfile as sf
import torch

from diffsheg_core.audio import Audio, load_audio
from diffsheg_core.checkpoints import load_model
from diffsheg_core.training.corpus.teacher import load_utterance, teach_files
from diffsheg_core.training.data import DataConfig
from diffsheg_core.training.data.dataset import find_sources
from diffsheg_core.motion import Motion
from diffsheg_core.pipeline import generate, resolve_guidance, resolve_skip_guidance, uses_prior

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
TAKE_WAV = DATA / "beat2" / "2_scott_0_1_1.wav"
TAKE_TEXTGRID = DATA / "beat2" / "2_scott_0_1_1.TextGrid"
TAKE_BVH = DATA / "beat" / "2_scott_0_1_1.bvh"
RECORDINGS = (DATA / "audio" / "2_scott_0_4_4.wav", DATA / "audio" / "12_zhao_2_3_3.wav")
TIMING_SPEECH = DATA / "audio" / "2_scott_0_3_3.wav"
SEEDS = (0, 1, 2)


def write_textgrid(phones: list[tuple[float, float, str]], duration: float, path: Path) -> Path:
    """A one-tier ('phones') Praat TextGrid in the short text format."""
    lines = ['File type = "ooTextFile"', 'Object class = "TextGrid"', "", "0", f"{duration:.6f}",
             "<exists>", "1", '"IntervalTier"', '"phones"', "0", f"{duration:.6f}", str(len(phones))]
    for start, end, label in phones:
        lines += [f"{start:.6f}", f"{end:.6f}", f'"{label}"']
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def heldout_set(corpus: Path, seconds: float, out: Path) -> tuple[Path, Path, Path]:
    """Concatenate held-out (val split) corpus utterances up to `seconds`: wav, teacher npz, TextGrid.
    Each utterance's audio is cut or padded to exactly its motion frames, so nothing drifts."""
    sources = find_sources(DataConfig(kind="corpus", root=str(corpus)), "val")
    audio_parts, motions, phones, t = [], [], [], 0.0
    rate = None
    for source in sources:
        if source.missing or t >= seconds:
            continue
        motion, utt_phones, _ = load_utterance(source.files["motion"])
        audio = load_audio(source.files["audio"])
        rate = rate or audio.sample_rate
        n = int(round(motion.n_frames / motion.fps * rate))
        audio_parts.append(np.pad(audio.samples[:n], (0, max(0, n - len(audio.samples)))))
        motions.append(motion)
        phones += [(t + p.start, min(t + p.end, t + n / rate), p.label) for p in utt_phones if p.start < n / rate]
        t += n / rate
    first = motions[0]
    teacher = Motion(fps=first.fps, rig=first.rig, joint_names=first.joint_names,
                     rotations=np.concatenate([m.rotations for m in motions]), face_names=first.face_names,
                     face=np.concatenate([m.face for m in motions]),
                     meta={"model": first.meta.get("model"), "utterances": len(motions)})
    wav = out / "heldout.wav"
    sf.write(wav, np.concatenate(audio_parts), rate)
    return wav, teacher.save_npz(out / "heldout_teacher.npz"), write_textgrid(phones, t, out / "heldout.TextGrid")


def samples_for(bundle, audio_path: Path, out: Path, name: str, scales: dict) -> list[str]:
    """Samples for each seed; `scales` holds generate()'s guidance, skip_guidance and sampling."""
    paths = []
    for seed in SEEDS:
        path = out / f"{name}_seed{seed}.npz"
        if not path.is_file():  # a rerun reuses the samples it already made
            generate(str(audio_path), model=bundle, seed=seed, device="cpu", **scales).save_npz(path)
        paths.append(str(path))
    return paths


def mocap_reference(teacher: Motion, out: Path) -> Path:
    """The take's motion capture (body only) as a Motion npz; its face channels are the
    teacher's (the take has no ARKit capture), so only its gesture figures and FGD count."""
    from diffsheg_core.bvh import bvh_to_motion, read_bvh
    from diffsheg_core.rigs import BEAT

    body = bvh_to_motion(read_bvh(TAKE_BVH, fps=15.0), BEAT)
    n = min(body.n_frames - 1, teacher.n_frames)
    return Motion(fps=15.0, rig="beat", joint_names=body.joint_names, rotations=body.rotations[1: n + 1],
                  face_names=teacher.face_names, face=teacher.face[:n],
                  meta={"source": str(TAKE_BVH), "face": "teacher"}).save_npz(out / "take_mocap_body.npz")


def evaluate(name: str, audio: Path, motion: list[str], out: Path, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "diffsheg_core", "evaluate", "--audio", str(audio), "--motion", *motion,
           "--out", str(out / name), *extra]
    subprocess.run(cmd, check=True, cwd=REPO, stdout=subprocess.DEVNULL)
    return json.loads((out / name / "metrics.json").read_text())


def generation_seconds(bundle, threads: int, scales: dict, seconds: float = 60.0, repeats: int = 3) -> float:
    """Best of `repeats` wall times of generate() on `seconds` of real speech."""
    torch.set_num_threads(threads)
    audio = load_audio(TIMING_SPEECH)
    cut = Audio(audio.samples[: int(seconds * audio.sample_rate)], audio.sample_rate, audio.path)
    generate(Audio(cut.samples[: 3 * cut.sample_rate], cut.sample_rate), model=bundle, device="cpu", **scales)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        generate(cut, model=bundle, device="cpu", **scales)
        best = min(best, time.perf_counter() - start)
    return best


BARS = (
    ("mouth open: vowels / bilabials", ">= 2"),
    ("mouthClose: bilabials - vowels", "> 0"),
    ("mouthPressLeft: bilabials - vowels", "> 0"),
    ("mouth-envelope r", ">= 0.2"),
    ("mouth-envelope lag (s)", "|lag| <= 0.15"),
    ("blinks per minute", "8 - 30"),
    ("blink duration (s)", "0.1 - 0.4"),
    ("BA", ">= teacher - 0.05"),
    ("jitter (mean jerk, rad/s^3)", "<= 1.5x teacher"),
    ("seam acceleration / in-clip", "<= 1.5"),
    ("mean gesture speed (rad/s)", "close to the real take"),
)
COMPARED = ("Div between samples (gesture, rad)", "FGD", "FED", "FMD", "PCM gesture (delta 1.0)",
            "mouth r with reference", "jitter / reference jitter")


def summary_table(results: dict[str, dict]) -> str:
    def cell(v) -> str:
        return "" if v is None else f"{v:.3g}" if isinstance(v, float) else str(v)

    names = list(results)
    rows = ["| metric | bar | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for key, bar in BARS:
        for column, label in (("generated", ""), ("reference", " (reference)")):
            values = [results[n][column].get(key) for n in names]
            if any(v is not None for v in values):
                rows.append(f"| {key}{label} | {bar if not label else ''} | " + " | ".join(map(cell, values)) + " |")
    for key in COMPARED:
        values = [results[n]["comparison"].get(key) for n in names]
        if any(v is not None for v in values):
            rows.append(f"| {key} | | " + " | ".join(map(cell, values)) + " |")
    return "\n".join(rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", help="checkpoint (default: the bundled model)")
    p.add_argument("--corpus", default=str(REPO.parent / "corpus" / "v2"),
                   help="corpus whose val split is the held-out speech (default ../corpus/v2)")
    p.add_argument("--autoencoder", help="autoencoders (.pt) for FGD / FED / FMD")
    p.add_argument("--seconds", type=float, default=60.0, help="held-out corpus speech to evaluate on")
    p.add_argument("--guidance", type=float, help="classifier-free scale (default: the model's own)")
    p.add_argument("--skip-guidance", type=float, help="gesture skip-guidance scale (default: the model's own)")
    p.add_argument("--no-prior", action="store_true",
                   help="later FOPPAS windows from pure noise instead of the model's gesture prior")
    p.add_argument("--out", default="out/eval-default")
    args = p.parse_args()
    torch.set_num_threads(1)  # robust when other processes share the CPU; timing below uses 1 and 2
    out = Path(args.out)
    (out / "motion").mkdir(parents=True, exist_ok=True)
    bundle = load_model(args.model)
    ae = ["--autoencoder", args.autoencoder] if args.autoencoder else []

    results: dict[str, dict] = {}
    wav, teacher, grid = heldout_set(Path(args.corpus), args.seconds, out)
    sampling = replace(bundle.sampling, prior_start=False) if args.no_prior else bundle.sampling
    scales = {"guidance": args.guidance, "skip_guidance": args.skip_guidance, "sampling": sampling}
    heldout = samples_for(bundle, wav, out / "motion", "heldout", scales)
    results["heldout"] = evaluate("heldout", wav, heldout, out,
                                  ["--reference", str(teacher), "--textgrid", str(grid), *ae])
    teacher_motion = teach_files(TAKE_WAV, TAKE_TEXTGRID)
    take_teacher = teacher_motion.save_npz(out / "motion" / "take_teacher.npz")
    mocap = ["--reference", str(mocap_reference(teacher_motion, out / "motion"))]
    take = samples_for(bundle, TAKE_WAV, out / "motion", "take", scales)
    on_take = ["--textgrid", str(TAKE_TEXTGRID), *ae]
    results["take_teacher"] = evaluate("take_teacher", TAKE_WAV, take, out,
                                       ["--reference", str(take_teacher), *on_take])
    results["take_mocap"] = evaluate("take_mocap", TAKE_WAV, take, out, [*mocap, *on_take])
    results["teacher_mocap"] = evaluate("teacher_mocap", TAKE_WAV, [str(take_teacher)], out, [*mocap, *on_take])
    for recording in RECORDINGS:
        results[recording.stem] = evaluate(recording.stem, recording,
                                           samples_for(bundle, recording, out / "motion", recording.stem,
                                                       scales), out, ae)
    seconds = {threads: generation_seconds(bundle, threads, scales) for threads in (1, 2)}
    guidance = resolve_guidance(bundle, args.guidance)
    skip = resolve_skip_guidance(bundle, args.skip_guidance)
    prior = uses_prior(bundle, sampling)
    summary = {"model": bundle.model_id, "guidance": guidance, "skip_guidance": skip, "gesture_prior": prior,
               "generate_60s_seconds_by_threads": seconds, "results": results}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    timing = ", ".join(f"{s:.2f} s with {t} thread(s)" for t, s in seconds.items())
    text = (f"# Evaluation of {bundle.model_id}\n\n60 s of speech generated in {timing} "
            f"(preset as shipped), guidance {guidance}, skip guidance {skip}, "
            f"gesture prior {'on' if prior else 'off'}.\n\n{summary_table(results)}\n")
    (out / "summary.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
