"""`generate`: speech in, `Motion` out. The one entry point clients use.

Everything here is numpy: the network runs on the backend `runtime.backends` picks
(onnxruntime, or torch for CUDA and official checkpoints), the sampler (`foppas`), the
schedule (`diffusion`), the guidance mixing (`guidance`) and the gesture prior (`prior`)
are the same for both.
"""

from __future__ import annotations

import threading
from functools import partial
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterator, Optional, Union

import numpy as np

from . import __version__
from .audio import Audio, AudioFile, load_audio, n_motion_frames, open_audio_file
from .checkpoints import ModelBundle, load_model
from .conditioning import Conditioning, SpeechFeatures
from .diffusion import Schedule
from .emotion import apply_emotion, emotion_track, remove_emotion, take_emotion
from .errors import DiffshegError
from .foppas import (EpsFn, Foppas, FoppasConfig, FoppasStream, fast_sampling, inpaint_range, sampling_settings,
                     with_overrides)
from .guidance import Guidance, face_eps, gesture_eps, step_eps
from .lower_body import JOINTS as LOWER_JOINTS, add_lower_body, legs_source, lower_rotations, plant, upper_body
from .motion import Motion
from .progress import ProgressCallback
from .runtime.backends import cpu_threads, open_network, student_network
from .settings import GenerateSettings
from .speech_features import speech_chunks
from .style import StyleTrack, named_weights, resolve_style_guidance, style_meta, style_track, style_weights
from .validate import GUIDANCE, SKIP_GUIDANCE, check_number

AudioInput = Union[str, Path, np.ndarray, Audio]


def resolve_guidance(bundle: ModelBundle, guidance: Optional[float]) -> Optional[float]:
    if not bundle.config.classifier_free:
        if guidance not in (None, 1.0):
            raise DiffshegError(f"model {bundle.model_id} was trained without classifier-free guidance: "
                                "leave the guidance scale at 1")
        return None
    scale = bundle.guidance if guidance is None else float(guidance)
    return None if scale is None else check_number("guidance", scale, GUIDANCE)


def check_skip_guidance(scale: float) -> float:
    return float(check_number("skip_guidance (gesture energy)", scale, SKIP_GUIDANCE))


def resolve_skip_guidance(bundle: ModelBundle, skip_guidance: Optional[float]) -> Optional[float]:
    """The gesture skip-guidance scale to sample with: the model's default for None, off for 0."""
    scale = bundle.skip_guidance if skip_guidance is None else skip_guidance
    if scale is None:
        return None
    return check_skip_guidance(scale) or None  # 0 turns it off


def uses_prior(bundle: ModelBundle, config: FoppasConfig) -> bool:
    """Whether later windows start from the model's gesture prior (it has one and `config` asks)."""
    return bundle.prior is not None and config.prior_start


@dataclass(frozen=True)
class Plan:
    """A `GenerateSettings` resolved against a model once, for sampling and for the metadata
    alike: the sampler's settings, the guidance scales (None: off), the style's class
    weights and the style of every frame."""

    config: FoppasConfig
    guidance: Guidance
    guidance_scale: Optional[float]      # the classifier-free scale as chosen, for the record (1: off)
    style_weights: dict
    style: StyleTrack                    # the style of each frame (of the take; live, of a window)
    style_at: tuple = ()                 # ((seconds, {class: weight}), ...) of the track's changes
    sampling: str = "custom"             # the named sampling sampled with ("custom": settings given outright)
    student: bool = False                # the model's distilled student makes each step in one pass (`uses_student`)


def make_plan(bundle: ModelBundle, s: GenerateSettings, sampling: Optional[FoppasConfig] = None,
              n_frames: int = 0, holds: bool = False) -> Plan:
    """Resolve `s` against `bundle`: the sampling settings `s` asks for (its named sampling of
    the model's, or `sampling`) with its overrides, its guidance, and its style over
    `n_frames` frames (`s.style` changed at `s.style_at`). Bad settings raise DiffshegError.

    `holds`: the job holds frames (a range regenerated between the take's frames, pins). The
    fast sampling's few steps do not join held frames smoothly (a pin's neighbourhood at 2.7x
    the range's acceleration, a range's left join 2.7x the 25 steps'), so such a job samples
    with the model's own steps: a range is short, and that costs it a second or two."""
    name = "quality" if holds and s.sampling == "fast" else s.sampling
    config = with_overrides(sampling or sampling_settings(bundle.sampling, name), steps=s.steps,
                            overlap=s.overlap, candidates=s.candidates)
    scale = resolve_guidance(bundle, s.guidance)
    guidance = Guidance(scale, resolve_skip_guidance(bundle, s.skip_guidance),
                        resolve_style_guidance(bundle, s.style_guidance))
    changes = tuple((t, style_weights(bundle, spec)) for t, spec in s.style_at or ())
    return Plan(config, guidance, scale, style_weights(bundle, s.style),
                style_track(bundle, s.style, s.style_at, n_frames), changes, "custom" if sampling else name,
                student=sampling is None and uses_student(bundle, name, config, guidance))


def uses_student(bundle: ModelBundle, sampling: str, config: FoppasConfig, guidance: Guidance) -> bool:
    """Whether a job samples with the model's distilled student (training.distill): it asks for
    the fast sampling exactly as the student was distilled from it (the model's steps and
    guidance scales; the overlap and the candidates may differ)."""
    student = bundle.student
    if student is None or sampling != "fast":
        return False
    d = student.info["distilled"]
    fast = fast_sampling(bundle.sampling)
    return (guidance == Guidance(d["guidance"], d["skip_guidance"]) and fast.refine_skip == d["refine_skip"]
            and tuple(d["timesteps"]) == fast.timesteps
            and replace(config, overlap=fast.overlap, candidates=fast.candidates) == fast)


@dataclass(frozen=True, eq=False)
class Posture:
    """What a calibrated sampling's frames are moved by (training.calibrate: the mean its
    gestures lack of the model's own 25 steps'), (D,) each in normalised units, zero on the face
    and wherever nothing was calibrated."""

    later: np.ndarray  # from the third window on, eased in over the second (`posture_weights`)
    first: np.ndarray  # in the first window, eased out as the second begins (`first_window_weights`)


def calibrated_posture(bundle: ModelBundle, live: bool = False) -> Optional[Posture]:
    """The calibrated posture of the distilled student offline (its info["posture"] and
    info["first_posture"]) or, `live`, of the model's live fast sampling (info["live_posture"];
    a session's first window is not calibrated). None where none was calibrated."""
    info = bundle.info if live else bundle.student.info if bundle.student is not None else {}
    later, first = info.get("live_posture" if live else "posture"), None if live else info.get("first_posture")
    if later is None and first is None:
        return None
    return Posture(_shift(bundle, later), _shift(bundle, first))


def _shift(bundle: ModelBundle, posture: Optional[list]) -> np.ndarray:
    shift = np.zeros(bundle.config.dim, np.float32)
    if posture is not None:
        shift[: len(posture)] = posture
    return shift


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def posture_weights(start: int, n: int, clip_len: int) -> np.ndarray:
    """(n,) how much of a calibrated posture's `later` frames [start, start + n) of a take get:
    none in the first window, eased in (smoothstep) over the next `clip_len` frames, in full
    from frame 2 * clip_len on."""
    return _smoothstep((np.arange(start, start + n) - clip_len) / clip_len)


def first_window_weights(start: int, n: int, clip_len: int) -> np.ndarray:
    """(n,) how much of a calibrated posture's `first` frames [start, start + n) of a take get:
    in full in the first window, eased out (smoothstep) over 2 * (clip_len // 8) frames (at least
    2) about its end, where the second window's offset (the other way: the wrists high) begins."""
    ease = max(1, clip_len // 8)
    return 1.0 - _smoothstep((np.arange(start, start + n) - (clip_len - ease)) / (2 * ease))


def add_posture(frames: np.ndarray, start: int, posture: Optional[Posture], clip_len: int) -> np.ndarray:
    """`frames` (n, D), frames [start, start + n) of a take, moved by a calibrated `posture` as
    `posture_weights` and `first_window_weights` say (in place; a long take's frames are not
    copied whole)."""
    if posture is None:
        return frames
    first = first_window_weights(start, len(frames), clip_len)
    until = int(np.count_nonzero(first))
    frames[:until] += first[:until, None] * posture.first
    weights = posture_weights(start, len(frames), clip_len)
    full = int(np.searchsorted(weights, 1.0))
    frames[:full] += weights[:full, None] * posture.later
    frames[full:] += posture.later
    return frames


def build_sampling(bundle: ModelBundle, network, plan: Plan) -> tuple[Foppas, Callable[[Conditioning], EpsFn]]:
    """The FOPPAS sampler of `plan`, and the factory that binds the network and guidance
    scales to one window's conditioning. Bad settings raise DiffshegError."""
    config = plan.config
    student = student_network(bundle, network) if plan.student else None
    network, guidance = (network, plan.guidance) if student is None else (student, Guidance())
    refine_offset = 0 if student is None else bundle.student.info["distilled"].get("refine_offset", 0)
    try:
        sampler = Foppas(Schedule.linear(), config, bundle.config.clip_len, bundle.config.dim,
                         proposal=partial(bundle.prior.propose, spread=config.prior_spread)
                         if uses_prior(bundle, config) else None,
                         gestures=bundle.config.gesture_dim, branch=bundle.config.lower_dim)
    except ValueError as exc:
        raise DiffshegError(str(exc)) from None
    return sampler, make_eps_fn_factory(bundle, network, sampler, guidance, refine_offset)


def _repeat(values: Optional[np.ndarray], rows: int) -> Optional[np.ndarray]:
    return values if values is None or len(values) == rows else np.repeat(values, rows, axis=0)


def make_eps_fn_factory(bundle: ModelBundle, network, sampler: Foppas, guidance: Guidance,
                        refine_offset: int = 0) -> Callable[[Conditioning], EpsFn]:
    """Bind network and guidance scales; the result binds one window's conditioning, which
    it hands to the network as a batch of one: its speech features, and its style
    (`StyleTrack.window`). The sampler's refining pass steers the gestures with the
    skip-guidance scale times `refine_skip` of the sampling settings; a distilled student
    learnt that pass at its timestep plus `refine_offset` (training.distill)."""
    cfg, sched = bundle.config, sampler.schedule
    refining = guidance if guidance.skip is None else \
        replace(guidance, skip=guidance.skip * sampler.config.refine_skip)

    def make(cond: Conditioning) -> EpsFn:
        mel = cond.features.mel[None]
        speech = None if cond.features.speech is None else cond.features.speech[None]
        window_style = cond.style.window()
        fused: dict[int, np.ndarray] = {}  # the window's speech features at a step, (1, L, A)
        g = cfg.gesture_dim

        def eps_fn(x: np.ndarray, index: int, refine: bool = False, face_only: bool = False) -> np.ndarray:
            rows = len(x)  # best-of-N: one window, several candidates
            idx = np.full(rows, index)
            timesteps, speech_rows, style_rows = sched.model_timesteps(idx), _repeat(speech, rows), \
                _repeat(window_style, rows)
            if refine:  # the face is final: it is the gestures' face x0, and its branch need not run
                if index not in fused:
                    fused[index] = face_eps(network, x[:1, :, g:], timesteps[:1], mel, speech, window_style)[1]
                eps_ges = gesture_eps(network, x[..., :g], timesteps + refine_offset, _repeat(fused[index], rows),
                                      speech_rows, style_rows, x[..., g:], refining)
                return np.concatenate([eps_ges, np.zeros_like(x[..., g:])], axis=-1)
            eps, audio = step_eps(network, g, x, timesteps, _repeat(mel, rows), speech_rows, style_rows,
                                  sched.x0_coefs(idx, x), guidance, face_only)
            fused[index] = audio[:1]
            return eps

        return eps_fn

    return make


def conditioned(pieces: Iterator[SpeechFeatures], style: StyleTrack) -> Iterator[Conditioning]:
    """The conditioning of consecutive pieces of a take's speech features, each with the
    style of its frames."""
    done = 0
    for features in pieces:
        yield Conditioning(features, style.frames(done, done + len(features)))
        done += len(features)


def generate(audio: AudioInput, sample_rate: Optional[int] = None, *,
             settings: Optional[GenerateSettings] = None, sampling: Union[str, FoppasConfig, None] = None,
             hubert_path: Optional[str] = None, hubert_quirk: bool = False,
             pins: tuple["Pin", ...] = (), progress: Optional[ProgressCallback] = None,
             cancel: Optional[threading.Event] = None, **options) -> Motion:
    """Generate body, hand, head and face motion for a speech recording.

    audio: a file path, an array (with `sample_rate`) or a loaded `Audio`.
    settings: a `GenerateSettings` (see diffsheg_core.settings for every option); keyword
    `options` are its fields and replace those of `settings` (`generate(path, seed=3)`):
    model: None for the bundled default, a checkpoint path, or a loaded `ModelBundle`.
    seed: any whole number >= 0; the noise comes from numpy's PCG64 seeded with it, the
    same on every backend and device.
    face_seed: fixes the face's noise apart from `seed` (SpeechAct's fixed face beside a
    stochastic body): the same face for every seed, other gestures. None: `seed` drives both.
    guidance / skip_guidance: classifier-free and gesture skip-guidance scales (None: the
    model's defaults; 1 and 0 turn them off).
    sampling (a setting): 'fast' (default, five steps a window) or 'quality' (the model's own
    settings, 25 steps for the bundled model), or an official preset; the `sampling` argument,
    a FoppasConfig, replaces it outright (research). steps / overlap / candidates override
    what either gives. candidates: every window after the first is sampled this many times in
    one batch and the one that best continues the motion is kept (`foppas.seam_scores`).
    backend: 'auto' (onnx where the model has its graphs and no GPU is asked for or found),
    'onnx' (onnxruntime, CPU) or 'torch'; device: 'auto', 'cpu' or 'cuda' (torch).
    precision: 'fp32', or 'bf16' / 'fp16' autocast on CUDA. threads: CPU threads
    (default: `runtime.backends.default_threads`).
    pins: poses (`Pin`) the motion passes through, such as the character's pose at frame 0
    so that a take continues the previous shot.
    progress: called after every diffusion step; cancel: checked before every step.
    The result has one frame per 1/fps s of audio (fps of the model, 15 for BEAT).
    """
    s, sampling = _job_settings(settings, sampling, options)
    with cpu_threads(s.threads):
        return _generate(audio, sample_rate, s, sampling, hubert_path, hubert_quirk, pins, progress, cancel)


def job_model(s: GenerateSettings, bundle: Optional[ModelBundle] = None) -> ModelBundle:
    """The model a job runs: `bundle`, else the settings' (loaded from its file), with the own
    face of the language the job names in place of the shared one (`ModelBundle.for_language`)."""
    bundle = bundle or (s.model if isinstance(s.model, ModelBundle) else load_model(s.model))
    return bundle.for_language(s.language)


def _generate(audio: AudioInput, sample_rate: Optional[int], s: GenerateSettings, sampling: Optional[FoppasConfig],
              hubert_path: Optional[str], hubert_quirk: bool, pins: tuple["Pin", ...],
              progress: Optional[ProgressCallback], cancel: Optional[threading.Event]) -> Motion:
    bundle = job_model(s)
    network = open_network(bundle, s.backend, s.device, s.precision, s.threads)
    speech = open_speech(audio, sample_rate)
    n_frames = n_motion_frames(speech, bundle.config.fps)
    plan, sampler, make_eps_fn = _sampling(bundle, network, s, sampling, n_frames, holds=bool(pins))
    chunks = conditioned(speech_chunks(bundle, network, speech, hubert_path, hubert_quirk), plan.style)
    if pins:  # sampled as one range with the pinned poses held, from the first frame
        normalised = np.zeros((n_frames, bundle.config.dim), dtype=np.float32)
        hold = np.zeros(normalised.shape, dtype=bool)
        _hold_pins(bundle, normalised, hold, pins, 0, n_frames)
        normalised = inpaint_range(sampler, make_eps_fn, Conditioning.join(chunks), normalised, 0, n_frames,
                                   s.seed, hold, progress, cancel, face_seed=s.face_seed)
    else:
        stream = FoppasStream(sampler, make_eps_fn, s.seed, progress, cancel, expected_frames=n_frames,
                              face_seed=s.face_seed)
        parts = [stream.push(chunk) for chunk in chunks]
        normalised = np.concatenate(parts + [stream.finish()])
        del parts  # a long take's motion is held once, not twice
        if plan.student:
            add_posture(normalised, 0, calibrated_posture(bundle), bundle.config.clip_len)
    check_finite(bundle, normalised)
    meta = generation_meta(bundle, s, plan, network, speech)
    if pins:
        meta["pins"] = len(pins)
    motion = to_motion(bundle, normalised, meta=meta)
    track = emotion_track(s.emotion, s.emotion_at, n_frames, bundle.config.fps)
    if track is not None:
        motion = apply_emotion(motion, track, held=tuple((p.frame, p.joint) for p in pins))
    return with_legs(motion, s)


def with_legs(motion: Motion, s: GenerateSettings) -> Motion:
    """The hips and legs of a generated `motion`: none with `upper_body_only`; a whole-body
    model's own, settled and with the feet planted (lower_body.plant); else, on the BEAT
    skeleton, cut from the capture to go with the arms (lower_body.add_lower_body). The meta's
    "lower_body" says which ("model" or "capture")."""
    if s.upper_body_only:
        return upper_body(motion)
    source = legs_source(motion.rig, motion.root_translation is not None)
    if source is None:
        return motion
    legs = plant(motion) if source == "model" else add_lower_body(motion, s.seed)
    return replace(legs, meta={**legs.meta, "lower_body": source})


def _job_settings(settings: Optional[GenerateSettings], sampling: Union[str, FoppasConfig, None],
                  options: dict) -> tuple[GenerateSettings, Optional[FoppasConfig]]:
    """`settings` with `options` replacing its fields, and the sampling settings given
    outright (None: the settings' named sampling); a `sampling` name is a setting."""
    if isinstance(sampling, str):
        sampling, options = None, {**options, "sampling": sampling}
    return replace(settings or GenerateSettings(), **options), sampling


def _sampling(bundle: ModelBundle, network, s: GenerateSettings, sampling: Optional[FoppasConfig],
              n_frames: int, holds: bool = False) -> tuple[Plan, Foppas, Callable[[np.ndarray], EpsFn]]:
    """The plan of `s` for `n_frames` frames (`holds`: see make_plan), its sampler and eps factory."""
    plan = make_plan(bundle, s, sampling, n_frames, holds)
    return (plan, *build_sampling(bundle, network, plan))


def generation_meta(bundle: ModelBundle, s: GenerateSettings, plan: Plan, network,
                    speech: Union[Audio, AudioFile]) -> dict:
    """What a Motion records of how it was made."""
    config = plan.config
    prior = uses_prior(bundle, config)
    return {
        "model_id": bundle.model_id, "trained": bundle.trained, "seed": s.seed, "face_seed": s.face_seed,
        "language": s.language,
        "audio_file": speech.path, "sample_rate": speech.sample_rate,
        **style_meta(bundle, plan.style_weights, plan.guidance.style),
        "style_at": [[t, named_weights(bundle, weights)] for t, weights in plan.style_at],
        "emotion": s.emotion or {}, "emotion_at": [[t, spec] for t, spec in s.emotion_at or ()],
        "guidance": plan.guidance_scale, "student": bundle.student.model_id if plan.student else None,
        "student_posture": plan.student and calibrated_posture(bundle) is not None,
        "skip_guidance": plan.guidance.skip,
        "sampling": plan.sampling, "steps": config.steps,
        "timesteps": None if config.timesteps is None else list(config.timesteps),
        "overlap": config.overlap, "candidates": config.candidates,
        "prior_start": prior, "prior_spread": config.prior_spread if prior else None, "carry": config.carry,
        "refine": config.refine, "refine_skip": config.refine_skip if config.refine is not None else None,
        "clip_len": bundle.config.clip_len, "backend": network.name,
        "warnings": list(getattr(speech, "notes", [])),
        "device": str(network.device), "software": f"diffsheg_core {__version__}",
    }


@dataclass(frozen=True)
class Pin:
    """A pose the regenerated motion passes through: `joint`'s rotation (axis-angle, in its
    parent's frame, as Motion holds it) at `frame` of the motion."""

    frame: int
    joint: str
    rotation: tuple[float, float, float]


def regenerate(motion: Motion, audio: AudioInput, sample_rate: Optional[int] = None, *, start: int, end: int,
               settings: Optional[GenerateSettings] = None, hold_face: bool = False, pins: tuple[Pin, ...] = (),
               sampling: Union[str, FoppasConfig, None] = None, progress: Optional[ProgressCallback] = None,
               cancel: Optional[threading.Event] = None, **options) -> Motion:
    """`motion` (made from `audio` by a model of its layout) with frames [start, end)
    generated anew with other `settings` or options (a seed, a style): the frames before
    and after the range are held and the sampler inpaints the range against both
    (`foppas.inpaint_range`). Every frame outside the range is returned bit for bit; with
    `hold_face` the take's face inside it too (only the gestures change). `pins` are poses the new
    motion passes through. `sampling` as for `generate`: a name or a FoppasConfig. Without a
    language or emotion in the settings the range keeps the take's own."""
    s, sampling = _job_settings(settings, sampling, options)
    with cpu_threads(s.threads):
        return _regenerate(motion, audio, sample_rate, start, end, s, hold_face, pins, sampling, progress, cancel)


def _regenerate(motion: Motion, audio: AudioInput, sample_rate: Optional[int], start: int, end: int,
                s: GenerateSettings, hold_face: bool, pins: tuple[Pin, ...], sampling: Optional[FoppasConfig],
                progress: Optional[ProgressCallback], cancel: Optional[threading.Event]) -> Motion:
    if s.language is None:  # the range keeps the take's own language, as it keeps its emotion
        s = replace(s, language=motion.meta.get("language"))
    bundle = job_model(s)
    layout = bundle.layout
    whole, motion = motion, upper_body(motion)  # the take's hips and legs stay as they are
    if motion.rig != layout.rig or motion.fps != bundle.config.fps:
        raise DiffshegError(f"this motion is {motion.rig} at {motion.fps:g} fps, but model {bundle.model_id} "
                            f"makes {layout.rig} at {bundle.config.fps:g} fps: regenerate with the model "
                            "that made it")
    if isinstance(start, bool) or isinstance(end, bool) or not 0 <= int(start) < int(end) <= motion.n_frames:
        raise DiffshegError(f"the range to regenerate, frames {start} to {end}, must lie within the motion's "
                            f"{motion.n_frames} frames and hold at least one frame")
    network = open_network(bundle, s.backend, s.device, s.precision, s.threads)
    speech = open_speech(audio, sample_rate)
    if n_motion_frames(speech, bundle.config.fps) != motion.n_frames:
        raise DiffshegError(f"the audio gives {n_motion_frames(speech, bundle.config.fps)} frames of motion, the "
                            f"motion has {motion.n_frames}: regenerate with the audio it was made from")
    plan, sampler, make_eps_fn = _sampling(bundle, network, s, sampling, motion.n_frames, holds=True)
    cond = Conditioning.join(conditioned(speech_chunks(bundle, network, speech), plan.style))
    laid = take_emotion(motion)
    base = motion if laid is None else remove_emotion(motion, laid)  # what the take's emotion was laid over
    normalised, hold = known_values(bundle, base, whole)
    if hold_face:
        hold[start:end, layout.gesture_dim:] = True
    _hold_pins(bundle, normalised, hold, pins, start, end)
    new = inpaint_range(sampler, make_eps_fn, cond, normalised, start, end, s.seed, hold, progress, cancel,
                        face_seed=s.face_seed)
    check_finite(bundle, new)
    made = upper_body(to_motion(bundle, new, meta={}))  # the range's frames
    part = replace(base, rotations=base.rotations.copy(), face=base.face.copy())
    part.rotations[start:end], part.face[start:end] = made.rotations, made.face
    ease_into_pins(part.rotations, part.joint_names, pins, start, end)
    if s.emotion is None and s.emotion_at is None:  # the range keeps the take's own emotion
        s = replace(s, emotion=motion.meta.get("emotion") or None, emotion_at=motion.meta.get("emotion_at") or None)
    track = emotion_track(s.emotion, s.emotion_at, motion.n_frames, bundle.config.fps)
    if track is not None:
        part = apply_emotion(part, track, held=tuple((p.frame, p.joint) for p in pins))
    rotations, face = motion.rotations.copy(), motion.face.copy()
    rotations[start:end] = part.rotations[start:end]
    if not hold_face:
        face[start:end] = part.face[start:end]
    record = {"start": int(start), "end": int(end), "hold_face": hold_face, "pins": len(pins),
              **generation_meta(bundle, s, plan, network, speech)}
    lower = whole.rotations[:, len(motion.joint_names):]
    return replace(whole, rotations=np.concatenate([rotations, lower], axis=1), face=face,
                   meta={**motion.meta, "regenerated": list(motion.meta.get("regenerated", [])) + [record]})


def known_values(bundle: ModelBundle, upper: Motion, whole: Motion) -> tuple[np.ndarray, np.ndarray]:
    """(T, D) normalised model input of a take being regenerated (its `upper` body, without
    the emotion, and face), and which of it is held inside the range: nothing, except that
    a whole-body model holds the take's own hips and legs (`whole`'s), which stay as they
    are. A take without them (upper body only) shows that model the capture's mean legs."""
    layout = bundle.layout
    if not layout.root_translation:
        values = bundle.normalise(layout.join(upper.rotations, upper.face))
        return values.astype(np.float32), np.zeros(values.shape, dtype=bool)
    legs = slice(3 * len(upper.joint_names), layout.gesture_dim)
    if whole.root_translation is None:
        lower, root = np.zeros((upper.n_frames, len(LOWER_JOINTS), 3)), np.zeros((upper.n_frames, 3))
    else:
        lower, root = lower_rotations(whole), whole.root_translation
    values = bundle.normalise(layout.join(np.concatenate([upper.rotations, lower], axis=1), upper.face, root))
    hold = np.zeros(values.shape, dtype=bool)
    if whole.root_translation is None:
        values[:, legs] = 0.0  # the mean
    else:
        hold[:, legs] = True
    return values.astype(np.float32), hold


PIN_EASE = 12       # frames either side of a joint's pins over which its curve is eased through them
PIN_SMOOTH = 4.0    # frames: the smoothing length; the jerk weighs PIN_SMOOTH ** 6 against the pull to the sample


def ease_into_pins(rotations: np.ndarray, joint_names: list[str], pins, start: int, end: int) -> None:
    """Ease each pinned joint's rotations (T, J, 3, in place) through its pins: over PIN_EASE
    frames either side (within the range [start, end)) the curve becomes the one of least jerk
    that passes through every pin of the joint exactly and stays near the sampled curve as far
    as the pins allow, a pull that fades in by a raised cosine from nothing at a pin to full at
    the ease's ends, where the curve joins the sample with its value, velocity and acceleration.
    The sampler holds a pin's value but not the motion into it: its kink there, and the
    velocity two pins on neighbouring frames set, are spread over the ease, not left as a pop."""
    for j in sorted({joint_names.index(pin.joint) for pin in pins}):
        frames = np.array(sorted({pin.frame for pin in pins if joint_names.index(pin.joint) == j}))
        a, b = max(0, frames[0] - PIN_EASE - 3), min(len(rotations), frames[-1] + PIN_EASE + 4)
        t = np.arange(a, b)
        gap = np.abs(t[:, None] - frames[None, :]).min(axis=1)
        # as sampled: beyond the ease (three frames each side make the join) and outside the range
        held = (gap > PIN_EASE) | (t < start) | (t >= end) | (gap == 0)
        pull = 0.5 * (1.0 - np.cos(np.pi * np.clip(gap / (PIN_EASE + 1), 0.0, 1.0)))
        jerk = np.diff(np.eye(b - a), 3, axis=0)
        system = np.diag(pull) + PIN_SMOOTH ** 6 * jerk.T @ jerk
        curve = rotations[a:b, j].astype(np.float64)
        for pin in pins:
            if joint_names.index(pin.joint) == j:
                curve[pin.frame - a] = pin.rotation
        free = ~held
        curve[free] = np.linalg.solve(system[np.ix_(free, free)],
                                      pull[free, None] * curve[free] - system[np.ix_(free, held)] @ curve[held])
        rotations[a:b, j] = curve


def _hold_pins(bundle: ModelBundle, normalised: np.ndarray, hold: np.ndarray, pins, start: int, end: int) -> None:
    """Write each pin's pose into the (T, D) normalised motion and mark it held."""
    for pin in pins:
        channels = _pin_channels(bundle.layout, pin, start, end)
        rotation = np.array(pin.rotation, dtype=np.float32)
        normalised[pin.frame, channels] = (rotation - bundle.centre[channels]) / bundle.std[channels]
        hold[pin.frame, channels] = True


def _pin_channels(layout, pin: Pin, start: int, end: int) -> np.ndarray:
    """The model channels of a pin's joint; a pin outside the range or on a joint the
    model does not move raises DiffshegError."""
    if pin.joint in LOWER_JOINTS:
        raise DiffshegError(f"pin on '{pin.joint}': the hips and legs are not pinned (a take's stay as they are "
                            "when a range is regenerated, and the feet are planted where they land): pin a joint of "
                            "the upper body, or key the legs yourself")
    if pin.joint not in layout.gesture_joints:
        raise DiffshegError(f"pin on '{pin.joint}': the model does not move that joint (it moves "
                            f"{', '.join(layout.gesture_joints[:4])}, ...)")
    if not start <= pin.frame < end:
        raise DiffshegError(f"pin at frame {pin.frame} on {pin.joint} lies outside the range {start}-{end} "
                            "being regenerated: only the range is generated anew")
    j = layout.gesture_joints.index(pin.joint)
    return np.arange(3 * j, 3 * j + 3)


def check_finite(bundle: ModelBundle, normalised: np.ndarray) -> None:
    """Refuse NaN or infinite model output before anything is made of it."""
    bad = ~np.isfinite(normalised)
    if bad.any():
        raise DiffshegError(f"{bundle.source}: the model produced NaN or infinite motion "
                            f"({100 * bad.mean():.1f} % of the values): its weights are damaged; "
                            "nothing was written. Download or export the model again")


def open_speech(audio: AudioInput, sample_rate: Optional[int] = None) -> Union[Audio, AudioFile]:
    """The checked speech of `audio`: a file is read piece by piece (an AudioFile), unless it
    must be resampled first (`sample_rate`); an array or Audio is held as it is."""
    if isinstance(audio, (Audio, AudioFile)):
        return audio
    if isinstance(audio, (str, Path)) and sample_rate is None:
        return open_audio_file(audio)
    return load_audio(audio, sample_rate)


def to_motion(bundle: ModelBundle, normalised: np.ndarray, meta: dict) -> Motion:
    """Denormalise (T, D) model output and split it into named rotations and face weights."""
    layout = bundle.layout
    values = bundle.denormalise(normalised).astype(np.float32, copy=False)
    rotations, face = layout.split(values)
    if layout.rig == "beat":
        face = np.clip(face, 0.0, 1.0)  # ARKit weights are defined on [0, 1]
    return Motion(fps=bundle.config.fps, rig=layout.rig, joint_names=list(layout.joint_names),
                  rotations=rotations, face_names=list(layout.face_names), face=face,
                  root_translation=layout.root(values), meta=meta)
