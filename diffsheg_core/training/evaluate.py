"""`python -m diffsheg_core evaluate`: measure generated motion (DiffSHEG appendix E and
the animator-facing metrics) and write a Markdown report with PNG plots.

Generated motion comes from `--motion` files (one per sample, e.g. one per seed) or is
made here from `--audio` with `--model` and `--seeds`. A `--reference` (ground truth or
a teacher: a diffsheg Motion .npz, a BEAT .bvh with an optional .json / .csv face file
beside it, or a BEAT2 smplxflame .npz) adds FGD / FED / FMD (with `--autoencoder`), PCM,
correlation with the reference's mouth, and the same per-motion metrics for the
reference in a second column. BEAT's semantic relevance annotation of the take (`--semantic`,
or found beside a BEAT reference) adds SRGR.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..audio import Audio, load_audio
from ..errors import DiffshegError
from .metrics import (
    Interval, SemanticSpan, audio_beats, beat_alignment, blink_signal, blink_stats, diversity,
    envelope_correlation, find_semantic, foppas_seams, frechet_distance, layout_array, mean_jerk,
    motion_beats, motion_curves, mouth_opening, pcm, phone_tier, phoneme_contrast, read_semantic,
    read_textgrid, reference_correlation, seam_smoothness, semantic_weights, speed, srgr,
)
from .metrics.channels import face_channel, gesture_array, has_face_channels, has_mouth
from .metrics.posture import NATURALNESS, naturalness
from ..motion import Motion, resample_motion
from ..rigs import Layout, get_layout


@dataclass
class EvalInputs:
    samples: list[Motion]
    audio: Audio
    reference: Motion | None = None
    phones: list[Interval] | None = None
    semantic: list[SemanticSpan] | None = None  # BEAT semantic relevance of the reference take
    features: object | None = None            # autoencoder.MotionFeatures
    clip_len: int | None = None                # FOPPAS windows, for seam smoothness
    overlap: int | None = None
    labels: tuple[str, str] = ("generated", "reference")
    notes: list[str] = field(default_factory=list)


# ---------------------------------------------------------------- loading

def load_reference(path: str | Path, fps: float | None = None) -> Motion:
    """Reference motion from a diffsheg .npz, a BEAT2 smplxflame .npz or a BVH (+ face file).

    `fps` is the BVH's real rate when its header cannot be trusted (BEAT files made for
    DiffSHEG: 15)."""
    from ..bvh import bvh_to_motion, read_bvh
    from .data.beat2 import read_motion
    from ..motion import read_arkit_json, read_livelink_csv
    from ..rigs import BEAT, SMPLX

    path = Path(path)
    if path.suffix.lower() == ".bvh":
        body = bvh_to_motion(read_bvh(path, fps=fps), BEAT)
        face_file = next((path.with_suffix(s) for s in (".json", ".csv") if path.with_suffix(s).is_file()), None)
        if face_file is None:
            return body
        face = (read_arkit_json if face_file.suffix == ".json" else read_livelink_csv)(face_file)
        t = np.arange(body.n_frames) / body.fps
        weights = np.stack([np.interp(t, np.arange(len(face.weights)) / face.fps, face.weights[:, k])
                            for k in range(len(face.names))], axis=1)
        return Motion(fps=body.fps, rig="beat", joint_names=body.joint_names, rotations=body.rotations,
                      face_names=face.names, face=weights, meta={"source": str(path)})
    if path.suffix.lower() != ".npz":
        raise DiffshegError(f"{path}: reference must be a .npz (diffsheg or BEAT2) or a .bvh file")
    with np.load(path, allow_pickle=False) as z:
        is_beat2 = "poses" in z.files
    if not is_beat2:
        return Motion.load_npz(path)
    target = fps or SMPLX.fps
    rotations, face = SMPLX.split(read_motion(path, target))
    return Motion(fps=target, rig="smplx", joint_names=list(SMPLX.joint_names), rotations=rotations,
                  face_names=list(SMPLX.face_names), face=face, meta={"source": str(path)})


def generate_samples(audio: Audio, model: str | None, seeds: list[int], steps: int | None,
                     device: str) -> list[Motion]:
    from ..checkpoints import load_model
    from ..pipeline import generate

    bundle = load_model(model)
    return [generate(audio, model=bundle, seed=s, steps=steps, device=device) for s in seeds]


# ---------------------------------------------------------------- per-motion metrics



def motion_metrics(motion: Motion, inputs: EvalInputs, onsets: np.ndarray) -> dict[str, float]:
    """Metrics of one motion on its own (no reference needed)."""
    layout = get_layout(motion.rig)
    gesture = gesture_array(motion, layout)
    fps = motion.fps
    out: dict[str, float] = {
        "BA": beat_alignment(onsets, motion_beats(gesture, fps)),
        "jitter (mean jerk, rad/s^3)": mean_jerk(gesture, fps),
        "mean gesture speed (rad/s)": float(speed(gesture, fps).mean()),
        **naturalness(motion),
    }
    if inputs.clip_len and inputs.overlap is not None and motion.n_frames > inputs.clip_len:
        seams = foppas_seams(motion.n_frames, inputs.clip_len, inputs.overlap)
        out["seam acceleration / in-clip"] = seam_smoothness(gesture, fps, seams, inputs.overlap)
    if not has_mouth(motion):  # a body-only capture: gesture metrics only
        return out
    mouth = mouth_opening(motion)
    r, lag = envelope_correlation(mouth, fps, inputs.audio.samples, inputs.audio.sample_rate)
    out["mouth-envelope r"], out["mouth-envelope lag (s)"] = r, lag
    if inputs.phones:
        contrast = phoneme_contrast(mouth, fps, inputs.phones)
        out["mouth open: vowels / bilabials"] = contrast["ratio"]
        out["mouth open at open vowels"] = contrast["open"]
        out["mouth open at bilabials"] = contrast["bilabial"]
        for name in ("mouthClose", "mouthPressLeft"):
            if has_face_channels(motion, name):
                c = phoneme_contrast(face_channel(motion, name), fps, inputs.phones)
                out[f"{name}: bilabials - vowels"] = c["bilabial"] - c["open"]
    if has_face_channels(motion, "eyeBlinkLeft", "eyeBlinkRight"):
        blinks = blink_stats(blink_signal(motion), fps)
        out["blinks per minute"] = blinks["per_minute"]
        out["blink duration (s)"] = blinks["mean_duration"]
    return out


def _mean_dicts(dicts: list[dict[str, float]]) -> dict[str, float]:
    return {k: float(np.mean([d[k] for d in dicts if k in d])) for k in dicts[0]}


# ---------------------------------------------------------------- comparisons

def comparison_metrics(inputs: EvalInputs, layout: Layout) -> dict[str, float]:
    """Metrics between samples (Div) and against the reference (FGD / FED / FMD, PCM)."""
    out: dict[str, float] = {}
    arrays = [layout_array(m, layout) for m in inputs.samples]
    n = min(len(a) for a in arrays)
    if len(arrays) > 1:
        out["Div between samples (gesture, rad)"] = diversity(np.stack([a[:n, : layout.gesture_dim] for a in arrays]))
    feats = inputs.features
    if feats is not None:
        generated = feats.features(arrays)
        out["Div between clips (autoencoder latent)"] = diversity(generated["motion"])
        if inputs.reference is not None:
            ref_full = _full_reference(inputs.reference, layout)
            # a body-only reference has no face: zeros stand in for it, and only the gesture
            # distance (whose autoencoder never sees the face channels) is reported
            real = feats.features([ref_full if ref_full is not None else np.concatenate(
                [gesture_array(inputs.reference, layout),
                 np.zeros((inputs.reference.n_frames, layout.expression_dim))], axis=1)])
            parts = (("motion", "FMD"), ("gesture", "FGD"), ("expression", "FED")) if ref_full is not None \
                else (("gesture", "FGD"),)
            for part, name in parts:
                out[name] = frechet_distance(generated[part], real[part])
    if inputs.reference is not None:
        ref = gesture_array(inputs.reference, layout)
        m = min(n, len(ref))
        out["PCM gesture (delta 1.0)"] = float(np.mean([pcm(a[:m, : layout.gesture_dim], ref[:m])
                                                        for a in arrays]))
        if inputs.semantic is not None:
            weights = semantic_weights(inputs.semantic, m, inputs.samples[0].fps)
            if weights.any():
                out["SRGR gesture (delta 1.0)"] = float(np.mean([
                    srgr(a[:m, : layout.gesture_dim], ref[:m], weights) for a in arrays]))
            else:
                inputs.notes.append("no semantic gesture annotated in the compared frames: no SRGR")
        if has_mouth(inputs.reference):
            out["mouth r with reference"] = float(np.mean([
                reference_correlation(mouth_opening(s)[:m], mouth_opening(inputs.reference)[:m], s.fps)[0]
                for s in inputs.samples]))
    return out


def _full_reference(reference: Motion, layout: Layout) -> np.ndarray | None:
    """The reference in layout order, or None when it has no face channels (body-only)."""
    if not has_face_channels(reference, *layout.face_names) or \
            not all(j in reference.joint_names for j in layout.face_rotation_joints):
        return None
    return layout_array(reference, layout)


def _normaliser(inputs: EvalInputs, layout: Layout) -> tuple[np.ndarray, np.ndarray]:
    if inputs.features is not None:
        g = layout.gesture_dim
        return inputs.features.mean[:g], inputs.features.std[:g]
    base = gesture_array(inputs.reference if inputs.reference is not None else inputs.samples[0], layout)
    return base.mean(axis=0), np.maximum(base.std(axis=0), 1e-4)


def evaluate(inputs: EvalInputs, out_dir: str | Path | None = None, plots: bool = True) -> dict:
    """All metrics as a dict; with `out_dir`, also report.md, metrics.json and PNG plots."""
    if not inputs.samples:
        raise DiffshegError("nothing to evaluate: give generated motion files or a model and seeds")
    rigs = {m.rig for m in inputs.samples} | ({inputs.reference.rig} if inputs.reference is not None else set())
    if len(rigs) > 1:
        raise DiffshegError(f"generated and reference motion use different rigs ({', '.join(sorted(rigs))})")
    layout = get_layout(inputs.samples[0].rig)
    fps = inputs.samples[0].fps
    if inputs.reference is not None and abs(inputs.reference.fps - fps) > 1e-6:
        inputs.reference = resample_motion(inputs.reference, fps)
    onsets = audio_beats(inputs.audio.samples, inputs.audio.sample_rate)
    generated = _mean_dicts([motion_metrics(m, inputs, onsets) for m in inputs.samples])
    reference = motion_metrics(inputs.reference, inputs, onsets) if inputs.reference is not None else {}
    compared = comparison_metrics(inputs, layout)
    if "jitter (mean jerk, rad/s^3)" in reference:
        compared["jitter / reference jitter"] = (generated["jitter (mean jerk, rad/s^3)"]
                                                 / reference["jitter (mean jerk, rad/s^3)"])
    for key in NATURALNESS:
        if key in reference:
            if key.startswith("head pitch"):
                compared["head pitch - reference (deg)"] = generated[key] - reference[key]
            else:
                compared[f"{key.split(' (')[0]} / reference"] = generated[key] / max(reference[key], 1e-12)
    result = {"layout": layout.name, "fps": fps, "samples": len(inputs.samples),
              "audio": inputs.audio.path, "audio_beats": len(onsets),
              "generated": generated, "reference": reference, "comparison": compared}
    if out_dir is not None:
        write_outputs(result, inputs, layout, Path(out_dir), plots)
    return result


def write_outputs(result: dict, inputs: EvalInputs, layout: Layout, out: Path, plots: bool) -> Path:
    from .metrics.lipsync import ENVELOPE_RATE, resample_curve, speech_envelope_db
    from .metrics.report import markdown_table, plot_curves, plot_histograms, plot_series, write_report

    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(result, indent=1), encoding="utf-8")
    gen, ref = result["generated"], result["reference"]
    rows = [(k, v, ref.get(k)) for k, v in gen.items()] + [(k, v, None) for k, v in result["comparison"].items()]
    figures: list[Path] = []
    if plots:
        mean, std = _normaliser(inputs, layout)
        fps = inputs.samples[0].fps
        named = {inputs.labels[0]: inputs.samples[0]}
        if inputs.reference is not None:
            named[inputs.labels[1]] = inputs.reference
        curves = {k: motion_curves((gesture_array(m, layout) - mean) / std) for k, m in named.items()}
        figures.append(plot_curves(curves, fps, out / "curves.png"))
        figures.append(plot_histograms({k: speed(gesture_array(m, layout), fps) for k, m in named.items()},
                                       "gesture speed (rad/s)", out / "speed_histogram.png"))
        env = speech_envelope_db(inputs.audio.samples, inputs.audio.sample_rate)
        span = int(20 * ENVELOPE_RATE)
        series = {"speech envelope (dB)": (np.arange(len(env[:span])) / ENVELOPE_RATE, env[:span])}
        for k, m in named.items():
            mouth = resample_curve(mouth_opening(m), m.fps)[:span]
            series[f"mouth opening, {k}"] = (np.arange(len(mouth)) / ENVELOPE_RATE, mouth)
        figures.append(plot_series(series, "scaled to 0..1", out / "mouth_vs_speech.png"))
    notes = [f"{result['samples']} generated sample(s), layout {layout.name}, {result['fps']:g} fps",
             f"audio {result['audio']}: {result['audio_beats']} onsets", *inputs.notes]
    return write_report(out / "report.md", "Evaluation", notes, markdown_table(rows, inputs.labels), figures)


# ---------------------------------------------------------------- command line

def main(argv: list[str] | None = None) -> int:
    """Evaluate generated motion and write a report."""
    p = argparse.ArgumentParser(prog="python -m diffsheg_core evaluate", description=main.__doc__)
    p.add_argument("--audio", required=True, help="the speech the motion was generated from")
    p.add_argument("--motion", nargs="*", default=[], help="generated motion .npz files (one per sample)")
    p.add_argument("--model", help="checkpoint to generate samples with (instead of --motion); "
                   "'default' for the bundled model")
    p.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2], help="seeds for --model")
    p.add_argument("--steps", type=int, help="DDIM steps for --model")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    p.add_argument("--reference", help="ground-truth / teacher motion (.npz or .bvh)")
    p.add_argument("--reference-fps", type=float, help="the reference BVH's real frame rate when its header is stale")
    p.add_argument("--semantic", help="BEAT semantic relevance annotation of the reference take, "
                   "for SRGR (default: <take>.txt beside a .bvh reference or sem/<take>.txt)")
    p.add_argument("--textgrid", help="Praat TextGrid with a phone tier, for the phoneme lip-sync contrast")
    p.add_argument("--autoencoder", help="motion autoencoders (.pt) for FGD / FED / FMD")
    p.add_argument("--clip-len", type=int, help="FOPPAS window length, for seam smoothness (default: "
                   "from the motion's meta, else 34)")
    p.add_argument("--overlap", type=int, help="FOPPAS overlap (default: from the motion's meta)")
    p.add_argument("--out", default="out/evaluation", help="report folder (default %(default)s)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    args = p.parse_args(argv)

    semantic = args.semantic or (find_semantic(args.reference) if args.reference else None)
    if semantic and not args.reference:
        raise DiffshegError("--semantic weights the comparison with a reference (SRGR): give --reference too")
    spans = read_semantic(semantic) if semantic else None
    audio = load_audio(args.audio)
    if args.motion and args.model:
        raise DiffshegError("give either --motion files or --model, not both")
    if args.motion:
        samples = [Motion.load_npz(m) for m in args.motion]
    elif args.model:
        samples = generate_samples(audio, None if args.model == "default" else args.model,
                                   args.seeds, args.steps, args.device)
    else:
        raise DiffshegError("nothing to evaluate: give --motion files or --model")
    features = None
    if args.autoencoder:
        from .autoencoder import MotionFeatures

        features = MotionFeatures.load(args.autoencoder)
    meta = samples[0].meta
    inputs = EvalInputs(
        samples=samples, audio=audio,
        reference=load_reference(args.reference, args.reference_fps) if args.reference else None,
        phones=phone_tier(read_textgrid(args.textgrid), args.textgrid) if args.textgrid else None,
        features=features,
        clip_len=args.clip_len or meta.get("clip_len") or 34,
        overlap=args.overlap if args.overlap is not None else meta.get("overlap"),
        semantic=spans,
        notes=[f"semantic relevance (SRGR weights): {semantic}"] if semantic else [],
    )
    result = evaluate(inputs, args.out, plots=not args.no_plots)
    print(json.dumps({"report": str(Path(args.out) / "report.md"), **result["comparison"],
                      **{f"generated {k}": v for k, v in result["generated"].items()}}, indent=1))
    return 0
