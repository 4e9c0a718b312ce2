"""A press of Generate: the request the panel's settings ask for, checked before anything
runs, and the background job that runs it.

The panel's settings (properties.py) are read on the main thread into a `Request`
(`prepare`): what to generate (the whole clip, from the character's pose where asked, or a
range of the take playing) and how to key it, with the checks and messages it needs
(packages, audio, model, targets, preset, timeline style and emotion markers). Its `run`
makes the Motion and touches no Blender data, so `GenerationJob` runs it in a daemon
thread, with progress and a cancel event; `apply` (`apply_result`) keys the result on the
main thread. `RequestQueue` runs several requests (one per sound strip, strips.py) one
after another, under one cancel event, for the main thread to key each as it finishes. One
line of batch_render.py is a `Request` too.

`BackgroundJob` is the daemon thread a modal operator polls: `GenerationJob` here, the
pip install of the preferences (preferences.InstallJob) and Live's finish too.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import bpy

from diffsheg_core.errors import DiffshegError

from ..environment import INSTALL_GPU_HINT, check_runtime, torch_installed
from ..scene import preset
from ..scene.report import model_label, report_details, report_line, write_report

# The panel's choices that mean "none of the model's": Generate reads them (properties.py offers them)
CUSTOM_PRESET = "__custom__"   # the preset: a .json file of the user's own
NO_MIX = "__none__"            # the second style: none
DEFAULT_STYLE = "__default__"  # the style: the model's default
SHARED_FACE = "__shared__"     # the language: none, the model's shared face
NEUTRAL = "neutral"            # the emotion: none (diffsheg_core.emotion.NAMES[0])


@dataclass
class Request:
    """One press of Generate, resolved on the main thread: the whole clip as a new take
    (from the character's pose where asked), or a range of the take playing generated anew."""

    path: Path
    options: object                  # BakeOptions
    generation: object               # GenerateSettings
    hold_face: bool = False          # a range: the take's face held, only the gestures new
    pins: tuple = ()                 # whole clip: the pose to start from
    range: object | None = None      # regenerate.RangeRequest

    def run(self, progress, cancel):
        """The Motion (worker thread; touches no Blender data)."""
        import diffsheg_core

        if self.range is None:
            return diffsheg_core.generate(str(self.path), settings=self.generation, pins=self.pins,
                                          progress=progress, cancel=cancel)
        r = self.range
        return diffsheg_core.regenerate(r.source.motion, str(self.path), start=r.start, end=r.end,
                                        settings=self.generation, hold_face=self.hold_face, pins=r.pins,
                                        progress=progress, cancel=cancel)

    def made_with(self, motion) -> dict:
        """What the result was made with (model, seed, ...): a range's own record."""
        return motion.meta["regenerated"][-1] if self.range is not None else motion.meta

    def apply(self, scene, motion):
        """Key `motion` (main thread): a new take of the whole clip, or of the range."""
        if self.range is None:
            from ..scene.bake import bake_motion

            return bake_motion(scene, motion, str(self.path), self.options)
        from .regenerate import apply_range

        return apply_range(scene, self.range, motion, self.options)


class BackgroundJob:
    """`work` in a daemon thread: `start` it, poll `done` (or `wait`), then read what it left."""

    def __init__(self):
        self.started = time.perf_counter()
        self._thread = threading.Thread(target=self.work, daemon=True)

    def work(self) -> None:
        raise NotImplementedError

    def start(self):
        self._thread.start()
        return self

    @property
    def elapsed(self) -> float:
        """Seconds since the job was made."""
        return time.perf_counter() - self.started

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)


class GenerationJob(BackgroundJob):
    """A request's generation in a daemon thread; poll `done`, then read `motion`/`error`.
    `elapsed` counts generation, then keying."""

    def __init__(self, request: Request, cancel: threading.Event | None = None):
        super().__init__()
        self.request = request
        self.cancel = cancel if cancel is not None else threading.Event()
        self.fraction = 0.0
        self.motion = None
        self.error: BaseException | None = None

    def work(self) -> None:
        try:
            self.motion = self.request.run(self._progress, self.cancel)
        except BaseException as exc:  # handed to the main thread, which reports it
            self.error = exc

    def _progress(self, p) -> None:
        self.fraction = p.fraction


class RequestQueue:
    """Requests generated one after another, each in its own `GenerationJob`, all under one
    cancel event. The main thread calls `advance` to start the next request once it has
    keyed the previous one's Motion (Blender data are written on the main thread only)."""

    def __init__(self, requests: list[Request]):
        self.requests = list(requests)
        self.cancel = threading.Event()
        self.index = -1                          # the request under way (or last run)
        self.job: GenerationJob | None = None
        self.started = time.perf_counter()

    def advance(self) -> GenerationJob | None:
        """Start the next request's job; None when all have run or the queue was cancelled."""
        if self.cancel.is_set() or self.index + 1 >= len(self.requests):
            self.job = None
            return None
        self.index += 1
        self.job = GenerationJob(self.requests[self.index], self.cancel).start()
        return self.job

    @property
    def fraction(self) -> float:
        """How far the whole queue is (each request an equal share)."""
        if not self.requests:
            return 1.0
        current = self.job.fraction if self.job is not None else 0.0
        return min(1.0, (max(self.index, 0) + current) / len(self.requests))

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.started


# ---------------------------------------------------------------- the panel's request

def audio_file(settings) -> Path:
    raw = settings.audio_path.strip()
    if not raw:
        raise DiffshegError("no audio file chosen: pick a speech recording in the panel")
    from diffsheg_core.audio import check_audio_path

    return check_audio_path(bpy.path.abspath(raw))


def preset_of(settings) -> preset.Preset | None:
    """The chosen rig preset; None for Auto (chosen from the rig's names when keying)."""
    if settings.preset == preset.AUTO:
        return None
    if settings.preset == CUSTOM_PRESET:
        if not settings.preset_file.strip():
            raise DiffshegError("'Custom file...' preset chosen but no preset file given")
        return preset.load_preset(bpy.path.abspath(settings.preset_file))
    return preset.load_preset(settings.preset)


def model_file(settings) -> str | None:
    """The panel's model file as an absolute path (None: the bundled model)."""
    raw = settings.model_path.strip()
    return bpy.path.abspath(raw) if raw else None


def generate_settings(settings):
    """The panel's generation options as one `GenerateSettings` (checked there); a switched-off
    "Set ..." toggle means the sampling's or the model's default, emotion Neutral none
    (`prepare` adds the timeline markers' changes)."""
    from diffsheg_core.settings import GenerateSettings

    return GenerateSettings(
        model=model_file(settings),
        seed=settings.seed,
        face_seed=settings.face_seed if settings.use_face_seed else None,
        sampling=settings.sampling.lower(),  # FAST, QUALITY: fast, quality
        steps=settings.steps if settings.set_steps else None,
        candidates=settings.candidates,
        overlap=settings.overlap if settings.set_overlap else None,
        style=panel_style(settings),
        style_guidance=settings.style_strength if settings.style_strength != 1.0 else None,
        emotion=panel_emotion(settings),
        upper_body_only=settings.upper_body_only,
        language=None if settings.language in ("", SHARED_FACE) else settings.language,
        guidance=settings.guidance if settings.set_guidance else None,
        skip_guidance=settings.gesture_energy if settings.set_gesture_energy else None,
        device=settings.device_arg())


def panel_emotion(settings) -> dict[str, float] | None:
    """The emotion the panel asks for and its intensity (None: Neutral)."""
    return None if settings.emotion == NEUTRAL else {settings.emotion: round(settings.emotion_intensity, 3)}


def panel_style(settings):
    """The style, or the mix of two styles, the panel asks for."""
    first = None if settings.style in ("", DEFAULT_STYLE) else settings.style
    second = settings.mix_style
    if second in ("", NO_MIX) or second == first or settings.style_mix <= 0.0:
        return first
    if settings.style_mix >= 1.0:
        return second
    if first is None:  # mixing needs a named first style
        raise DiffshegError("to mix styles, choose the first style by name instead of Default")
    return {first: 1.0 - settings.style_mix, second: settings.style_mix}


def bake_options(settings):
    from ..scene.bake import BakeOptions

    return BakeOptions(
        armature=settings.armature, face_meshes=settings.face_objects(), preset=preset_of(settings),
        start_frame=settings.start(),
        every_frame=settings.key_mode == "EVERY_FRAME", max_error=settings.max_error,
        max_face_error=settings.max_face_error,
        smoothing=settings.smoothing, add_sound=settings.add_sound,
        set_frame_range=settings.set_frame_range)


def check_model(settings) -> None:
    """What the chosen model and device need besides the runtime: torch for official
    checkpoints and CUDA GPUs (the GPU support of the preferences)."""
    from diffsheg_core.checkpoints import is_ours  # the runtime's packages: check_runtime came first

    if torch_installed():
        return
    chosen = model_file(settings)
    if chosen is not None and Path(chosen).is_file() and not is_ours(Path(chosen)):
        raise DiffshegError(f"{Path(chosen).name} is an official DiffSHEG checkpoint (a torch file): it needs "
                            f"torch, which is not installed: {INSTALL_GPU_HINT} (or choose a "
                            ".safetensors model, or none for the bundled one)")
    if settings.device == "GPU":
        raise DiffshegError(f"device GPU needs torch with CUDA, which is not installed: {INSTALL_GPU_HINT} "
                            "(CUDA build), or choose device Auto or CPU")


def check_ready(settings) -> tuple:
    """Everything checkable before generating: packages, the audio file (the whole clip's;
    a range uses its take's), model, targets, preset. Returns the audio and keying options."""
    check_runtime()
    path = audio_file(settings) if settings.range_mode == "WHOLE" else None
    return path, check_targets(settings)


def check_targets(settings):
    """What `check_ready` checks besides the packages and the audio: model, targets, preset,
    start frame. Returns the keying options."""
    check_model(settings)
    options = bake_options(settings)
    if options.armature is None and not options.face_meshes:
        raise DiffshegError("no target: choose an armature and/or a face mesh in the panel")
    from ..scene.bake import check_frames  # numpy: checked above

    check_frames(options.start_frame)
    from diffsheg_core.checkpoints import stored_rig  # the runtime's packages: checked above

    rig = stored_rig(model_file(settings))
    if options.armature is not None and rig is not None and options.preset is not None:
        options.preset.joint_map(rig)  # names the missing section before generating
    return options


def prepare(context) -> Request:
    """The panel's request, checked before anything runs (main thread): the whole clip of
    the panel's audio, or a range of the take playing (with the take's own audio). Timeline
    markers named 'style:...' and 'emotion:...' change the style and the emotion from their
    frame on. A range with emotion Neutral keeps its take's emotion: without emotion markers
    all of it (the core's regenerate does), with them the take's emotion until the first."""
    settings, scene = context.scene.diffsheg, context.scene
    path, options = check_ready(settings)
    generation = generate_settings(settings)
    if settings.range_mode == "WHOLE":
        generation = with_markers(generation, scene, options.start_frame)
        pins = ()
        if settings.start_from_pose:
            if options.armature is None:
                raise DiffshegError("'Start from pose' needs an armature: choose one, or turn it off")
            from .regenerate import pose_pins

            pins = pose_pins(scene, options, layout_motion(generation))
        return Request(path, options, generation, pins=pins)
    from diffsheg_core.audio import check_audio_path

    from .regenerate import prepare_range, scene_range

    first, last = scene_range(settings, scene)
    request = prepare_range(scene, options, first, last)
    path = check_audio_path(request.source.audio_path) if request.source.audio_path else None
    if path is None:
        raise DiffshegError(f"take '{request.take}' was made without an audio file: it cannot be regenerated")
    generation = with_markers(generation, scene, request.source.start_frame)
    if generation.emotion is None and generation.emotion_at is not None:
        generation = replace(generation, emotion=request.source.motion.meta.get("emotion") or None)
    return Request(path, options, generation, hold_face=settings.hold_face, range=request)


def with_markers(generation, scene, start_frame: int):
    """`generation` with the style and emotion changes of the scene's timeline markers, in
    seconds from `start_frame`."""
    return replace(generation, style_at=marker_styles(scene, start_frame),
                   emotion_at=marker_emotions(scene, start_frame))


STYLE_MARKER, EMOTION_MARKER = "style:", "emotion:"


def marker_styles(scene, start_frame: int) -> tuple | None:
    """The style changes the scene's timeline markers name ('style:calm',
    'style:calm=0.7,animated=0.3'), as (seconds from `start_frame`, style). None where
    there are none."""
    from diffsheg_core.style import parse_style

    return marker_changes(scene, start_frame, STYLE_MARKER, parse_style,
                          "style:calm or style:calm=0.7,animated=0.3")


def marker_emotions(scene, start_frame: int) -> tuple | None:
    """The emotion changes the scene's timeline markers name ('emotion:sad', 'emotion:sad=0.5',
    'emotion:happy=0.5,surprised=0.3', 'emotion:neutral'), as (seconds from `start_frame`,
    {name: intensity}). None where there are none."""
    from diffsheg_core.emotion import check_emotion

    return marker_changes(scene, start_frame, EMOTION_MARKER, check_emotion,
                          "emotion:sad or emotion:happy=0.5,surprised=0.3")


def marker_changes(scene, start_frame: int, prefix: str, parse, example: str) -> tuple | None:
    """The changes of the scene's timeline markers named `prefix` + value, as (seconds from
    `start_frame`, parse(value)) sorted by time; a marker before the start frame applies from
    the start, the later of two at one time wins. A marker whose value is missing or does not
    parse is a DiffshegError naming it and its frame (a missing one, `example` too). None
    where there are none."""
    import argparse

    from ..scene.bake import scene_fps

    changes = {}
    for marker in sorted(scene.timeline_markers, key=lambda m: m.frame):
        if not marker.name.startswith(prefix):
            continue
        value = marker.name[len(prefix):]
        where = f"timeline marker '{marker.name}' at frame {marker.frame}"
        if not value.strip():
            raise DiffshegError(f"{where} names no {prefix.rstrip(':')}: rename it like {example}")
        try:
            changes[max(0.0, (marker.frame - start_frame) / scene_fps(scene))] = parse(value)
        except (argparse.ArgumentTypeError, DiffshegError) as exc:
            raise DiffshegError(f"{where}: {exc}") from None
    return tuple(changes.items()) or None


def layout_motion(generation):
    """A one-frame Motion of the model's layout (its joint and face names), for mapping a rig."""
    import numpy as np

    from diffsheg_core.checkpoints import load_model
    from diffsheg_core.motion import Motion

    bundle = load_model(generation.model)
    layout = bundle.rig_layout
    return Motion(fps=bundle.config.fps, rig=layout.name, joint_names=list(layout.joint_names),
                  rotations=np.zeros((1, len(layout.joint_names), 3)), face_names=list(layout.face_names),
                  face=np.zeros((1, len(layout.face_names))))


def apply_result(context, settings, motion, request: Request, seconds: float) -> str:
    """Key `motion` into the scene (main thread only), write the report's details into the
    "DiffSHEG report" Text; returns the report's one line."""
    result = request.apply(context.scene, motion)
    meta = request.made_with(motion)
    settings.model_label = model_label(meta)
    line = report_line(result, seconds)
    write_report(report_details(result, seconds, settings.model_label, meta))
    settings.last_report, settings.last_failed = line, False
    return line


def error_message(exc: BaseException) -> str:
    if isinstance(exc, DiffshegError):
        return str(exc)
    return f"unexpected {type(exc).__name__}: {exc}"
