"""The samplings' posture (issue 40): the arms calibrated to the model's training data, the
fast sampling to the model's own 25 steps.

The fast sampling with the distilled student holds the body a little differently from the
model's own 25 steps, and the same way on every long speech: on four real takes of 29-119 s
(seeds 0-3, 2026-12-06) the wrists 0.10-0.12 arm lengths higher, the hips tilted back 0.8-1.3
degrees and the neck 1.3-1.6 degrees. The offsets of the whole pose correlate 0.92-1.00
between speeches. Their source is the later windows, which start from the gesture prior's
draws: the next few windows after the first hold the most (0.14-0.38 on three takes), the
rest about 0.10. A live session's windows start from the prior's draws too (the model's own
guided steps, a hop at a time): 0.07-0.4 after its first 34 frames. A constant is what is
wrong there, so a constant puts it right: the mean of each gesture channel the 25 steps make
minus the mean the sampling makes over the frames from 2 x clip_len (68) on, over speech and
seeds, stored in the file (normalised units, one value per gesture channel, the upper body's
and the hips' rotation: the student's info["posture"], the model's info["live_posture"]) and
added to the frames that sampling makes, in full from frame 68 on, eased in over the 34
before (`pipeline.posture_weights`). It moves where the motion sits, not how it moves.

The first window, sampled from noise, holds an offset of its own: the student's held the
wrists 0.15 arm lengths below the 25 steps' on one-window clips of the takes below and of
unseen speech alike. A constant for the whole pose there, calibrated on the first, moved the
head 1.6 degrees away from the 25 steps' on the second; one for the arms and hands alone (the
joints off the chain from the spine to the head, `arm_channels`), measured on clips of one
window every 2.5 s (`FIRST_EVERY_S`), brought the wrists to 0.03 below and left the head as it
was (-0.2 degrees; 40 clips of unseen speech, seeds 0-1). It is the student's
info["first_posture"], added in full to the first window and eased out about its end
(`pipeline.first_window_weights`). Live's first window is not calibrated: a whole-pose constant
brought its wrists no nearer and its head 0.9 degrees further.

The 25 steps themselves hold the arms lower than the data the model learnt from: over the
speech below (seeds 0-1, 2026-12-07) the mean of the arm channels (`arm_channels`) lies 0.26
of a channel's spread (rms) from the training data's mean, the same way on every speech (the
offsets correlate 0.84-0.99 between speeches, fast and 25 steps alike). On the Ready Player Me
avatar that put the hands 5.0-5.4 cm under the captured speaker's on 2_scott_0_1_1, whose
first 44 s the training data's gestures are cut from (`bench/eval_posture.py`, 18 seeds). The
training data's mean is the normalised zero, so the 25 steps' arm channels' mean, negated,
is the model's info["arm_posture"]: `ModelBundle.centre` adds it to the normalisation mean,
which moves every sampling (the 25 steps, the fast sampling, live, regenerated ranges, pins)
alike and leaves the relative postures above as they are. The head and the spine keep the 25
steps' posture: with the whole pose moved to the data's, the head pitched 1.2 degrees further
from the captured speaker's on the take's last 20 s (3.3 against the goal's 3 degrees).

Measured on takes apart from those the sampling, posture and live benches judge (`CALIBRATION`)
with the model file as it is, so a second run measures what is left and adds it (nothing, on
the same speech and seeds):

    python -m diffsheg_core.training.calibrate MODEL [--speech a.wav ...] [--seeds 0 1 2 3] [--no-live] [--no-first]
        [--no-student] [--no-arms] [--out FILE]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Sequence

import numpy as np

from ..audio import Audio, load_audio
from ..checkpoints import ModelBundle, load_model, save_checkpoint
from ..errors import DiffshegError
from ..kinematics import CHAINS
from ..live.engine import LiveEngine
from ..lower_body import upper_body
from ..motion import Motion
from ..pipeline import first_window_weights, generate, known_values, make_plan, posture_weights
from ..runtime.backends import cpu_threads, open_network
from ..settings import GenerateSettings

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "audio"
# long speech (two real takes, one text-to-speech reading) apart from what the sampling, posture and live benches judge (2_scott_0_1_1, 2_scott_0_3_3,
# 12_zhao_2_3_3); eval_default_model and eval_languages read some of it
CALIBRATION = (DATA / "2_scott_0_4_4.wav", DATA / "2_scott_0_103_103_28s.wav", DATA / "Forrest_tts.wav")
SEEDS = (0, 1, 2, 3)
FIRST_EVERY_S = 2.5  # one-window clips the first window's posture is measured on start this far apart


def gesture_means(bundle: ModelBundle, motion: Motion, first: bool = False) -> np.ndarray:
    """(gesture_dim,) the mean of each gesture channel of `motion` over the frames a posture
    moves in full, in the model's normalised units about its centre (`ModelBundle.centre`): from
    frame 2 x clip_len on (`pipeline.posture_weights`), or with `first` the first window's
    (`first_window_weights`)."""
    weights = (first_window_weights if first else posture_weights)(0, motion.n_frames, bundle.config.clip_len)
    full = weights == 1.0
    if not full.any():
        raise DiffshegError(f"speech of {motion.n_frames / motion.fps:.1f} s is too short to calibrate a posture "
                            f"on: give speech longer than {2 * bundle.config.clip_len / motion.fps:.1f} s (the "
                            "longer the better; the defaults are 29-119 s)")
    values, _ = known_values(bundle, upper_body(motion), motion)
    return values[full, : bundle.layout.gesture_dim].mean(axis=0)


def first_windows(audio: Audio, clip_len: int, fps: float) -> list[Audio]:
    """Clips of `audio` one window (`clip_len` frames) long, one every FIRST_EVERY_S seconds."""
    length, every = round(clip_len / fps * audio.sample_rate), round(FIRST_EVERY_S * audio.sample_rate)
    return [Audio(audio.samples[s: s + length], audio.sample_rate)
            for s in range(0, audio.n_samples - length + 1, every)]


def live_take(bundle: ModelBundle, audio: Audio, seed: int) -> Motion:
    """What a live session at the default LiveConfig makes of `audio` (the engine fed it all at
    once: with its hop held, the frames it makes at real time), on the CPU as sessions run (on
    onnxruntime, the model's int8 live graphs, even where torch sees a GPU)."""
    engine = LiveEngine(bundle, open_network(bundle, device="cpu", threads=1), GenerateSettings(seed=seed),
                        audio.sample_rate)
    with cpu_threads(1):
        engine.push(audio.samples)
        while engine.ready():
            engine.step()
        engine.finish()
    return engine.motion(meta=engine.meta())


def calibrated_channels(bundle: ModelBundle) -> np.ndarray:
    """(gesture_dim,) which gesture channels a posture moves: the upper body's joints and the
    hips' rotation. A whole-body model's legs and the hips' translation are planted after
    (lower_body.plant: the feet stand where they land), which would undo a constant there."""
    layout, upper = bundle.layout, 3 * len(bundle.rig_layout.joint_names)
    channels = np.zeros(layout.gesture_dim, bool)
    channels[:upper] = True
    if layout.root_translation:
        channels[upper: upper + 3] = True  # the first lower-body joint, the hips
    return channels


def arm_channels(bundle: ModelBundle) -> np.ndarray:
    """(gesture_dim,) the channels the first window's posture moves: the upper body's joints off
    the chain from the spine to the head (the shoulders, arms and hands), which cannot tilt the head."""
    chains = CHAINS.get(bundle.layout.rig)
    if chains is None:
        raise DiffshegError(f"{bundle.source}: no head chain is known for its '{bundle.layout.rig}' rig, "
                            "so the first window's posture cannot be kept off the head: calibrate with --no-first")
    channels = np.zeros(bundle.layout.gesture_dim, bool)
    for i, joint in enumerate(bundle.rig_layout.joint_names):
        channels[3 * i: 3 * i + 3] = joint not in chains["head"]
    return channels


def _student_take(bundle: ModelBundle, audio: Audio, seed: int) -> Motion:
    return generate(audio, model=bundle, seed=seed, sampling="fast", device="cpu")


def posture_offsets(bundle: ModelBundle, speeches: Sequence[Path], seeds: Sequence[int] = SEEDS,
                    live: bool = True, first: bool = True, student: bool = True,
                    arms: bool = True) -> dict[str, np.ndarray]:
    """(gesture_dim,) what the fast sampling's gestures lack of the 25 steps' (the quality
    sampling's minus its own) on average over `speeches` and `seeds`, per sampling calibrated,
    keyed as the file stores them: "posture" (the distilled student's, offline, from frame
    2 x clip_len on, on the `calibrated_channels`), "first_posture" (the student's first window,
    on one-window clips of the speech, on the `arm_channels`; with `first`) and "live_posture"
    (a live session's, as "posture"; with `live`), and "arm_posture" (what the 25 steps' arms lack
    of the training data's mean, the normalised zero, on the `arm_channels`; with `arms`); zero on
    the other channels. Without `student` the student's are left as they are (after live's
    defaults change)."""
    has_student = bundle.student is not None
    student = student and has_student
    if student and not make_plan(bundle, GenerateSettings(model=bundle)).student:
        raise DiffshegError(f"{bundle.source}: its fast sampling does not run its distilled student (the file's "
                            "sampling settings or guidance scales differ from those it was distilled at), so a "
                            "posture calibrated for the student would never apply")
    takes = {"posture": _student_take} if student else {}
    if live:
        takes["live_posture"] = live_take
    if not takes and not arms:
        raise DiffshegError(f"{bundle.source}: nothing to calibrate: the arms (--no-arms) and live (--no-live) are "
                            "left out, and " + ("so is the distilled student (--no-student); leave out one of them"
                                                if has_student else "the file has no distilled student; leave out "
                                                "--no-live or --no-arms"))
    channels = {key: calibrated_channels(bundle) for key in takes}
    if arms:
        channels["arm_posture"] = arm_channels(bundle)
        arms_now = np.asarray(bundle.info.get("arm_posture", np.zeros(bundle.layout.gesture_dim)), np.float64)
    if first and student:
        channels["first_posture"] = arm_channels(bundle)
    differences: dict[str, list] = {key: [] for key in channels}
    for path in speeches:
        audio = load_audio(str(path))
        for seed in seeds:
            quality = gesture_means(bundle, generate(audio, model=bundle, seed=seed, sampling="quality",
                                                     device="cpu"))
            if arms:  # the 25 steps' mean from the data's: normalised about the centre, plus the arms it moves
                differences["arm_posture"].append(-(quality + arms_now))
            for key, take in takes.items():
                differences[key].append(quality - gesture_means(bundle, take(bundle, audio, seed)))
            if "first_posture" in channels:
                for clip in first_windows(audio, bundle.config.clip_len, bundle.config.fps):
                    differences["first_posture"].append(
                        gesture_means(bundle, generate(clip, model=bundle, seed=seed, sampling="quality",
                                                       device="cpu"), first=True)
                        - gesture_means(bundle, _student_take(bundle, clip, seed), first=True))
    return {key: np.where(channels[key], np.mean(found, axis=0), 0.0) for key, found in differences.items()}


def calibrate(bundle: ModelBundle, speeches: Sequence[Path], seeds: Sequence[int] = SEEDS,
              live: bool = True, first: bool = True, student: bool = True,
              arms: bool = True) -> dict[str, np.ndarray]:
    """Add what each calibrated posture lacks to the file's (in place: the student's
    info["posture"] and info["first_posture"], the model's info["live_posture"] and
    info["arm_posture"]) and note what it was measured on; returns what was added to each."""
    added = posture_offsets(bundle, speeches, seeds, live, first, student, arms)
    measured = {"speech": [Path(p).name for p in speeches], "seeds": list(seeds)}
    for key, values in added.items():
        info = bundle.student.info if key in ("posture", "first_posture") else bundle.info
        info[key] = [round(float(v), 6) for v in np.asarray(info.get(key, 0.0), np.float64) + values]
        info["posture_measured_on"] = measured
    return added


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m diffsheg_core.training.calibrate",
                                     description="Calibrate the arms of every sampling to the model's training "
                                                 "data, and the fast sampling's posture (the distilled student's, "
                                                 "and live's) to the model's own 25 steps.")
    parser.add_argument("model", help="model file (.safetensors) of this project")
    parser.add_argument("--speech", nargs="+", type=Path, default=list(CALIBRATION),
                        help="long speech to measure on (default: three shared takes apart from those the "
                             "sampling, posture and live benches judge)")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    parser.add_argument("--no-live", action="store_true",
                        help="leave live's posture as it is (with --no-arms: calibrate the distilled student only)")
    parser.add_argument("--no-first", action="store_true", help="leave the student's first window as it is")
    parser.add_argument("--no-student", action="store_true",
                        help="leave the distilled student's posture as it is (after live's defaults change; with "
                             "--no-arms: calibrate live only)")
    parser.add_argument("--no-arms", action="store_true",
                        help="leave the model's arm posture (every sampling's) as it is")
    parser.add_argument("--out", help="where to write it (default: over the input, atomically)")
    args = parser.parse_args(argv)
    missing = [str(p) for p in args.speech if not Path(p).is_file()]
    if missing:
        raise DiffshegError(f"speech to calibrate on not found: {', '.join(missing)}: give --speech the paths of "
                            "speech recordings (wav, flac, ...), the longer the better")
    bundle = load_model(args.model)
    added = calibrate(bundle, args.speech, args.seeds, live=not args.no_live, first=not args.no_first,
                      student=not args.no_student, arms=not args.no_arms)
    path = save_checkpoint(bundle, args.out or args.model)
    print(f"wrote {path}, measured over {len(args.speech)} speeches, seeds {' '.join(map(str, args.seeds))}:")
    for key, values in added.items():
        print(f"  {key} moved by {np.abs(values).max():.4f} at most (mean |.| {np.abs(values).mean():.4f}, "
              "normalised units)")
    return 0


if __name__ == "__main__":
    try:
        raise SystemExit(main())
    except DiffshegError as exc:
        raise SystemExit(f"error: {exc}") from None
