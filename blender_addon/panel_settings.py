"""What the panel's settings ask for, checked before anything runs: the Request of a press of
Generate (the whole clip, or a range of the take playing), and the checks and messages it
needs (packages, audio, model, targets, preset, timeline style and emotion markers). Read
on the main thread; the operators run what it returns (operators.py, job.py).
"""

from __future__ import annotations

import importlib
from dataclasses import replace
from pathlib import Path

import bpy

from diffsheg_core.errors import DiffshegError

from . import preset
from .job import Request
from .preferences import INSTALL_GPU_HINT, RUNTIME, missing_runtime, runtime_fix, torch_installed
from .properties import CUSTOM_PRESET, DEFAULT_STYLE, NEUTRAL, NO_MIX
from .report import model_label, report_details, report_line, write_report


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


def generate_settings(settings):
    """The panel's generation options as one `GenerateSettings` (checked there); a switched-off
    "Set ..." toggle means the model's default, emotion Neutral none (`prepare` adds the
    timeline markers' changes)."""
    from diffsheg_core.settings import GenerateSettings

    return GenerateSettings(
        model=bpy.path.abspath(settings.model_path) if settings.model_path.strip() else None,
        seed=settings.seed,
        face_seed=settings.face_seed if settings.keep_face else None,
        steps=settings.steps if settings.set_steps else None,
        candidates=settings.candidates,
        overlap=settings.overlap if settings.set_overlap else None,
        style=panel_style(settings),
        style_guidance=settings.style_strength if settings.style_strength != 1.0 else None,
        emotion=panel_emotion(settings),
        upper_body_only=settings.upper_body_only,
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
    from .bake import BakeOptions

    return BakeOptions(
        armature=settings.armature, face_meshes=settings.face_objects(), preset=preset_of(settings),
        start_frame=settings.start(),
        every_frame=settings.key_mode == "EVERY_FRAME", max_error=settings.max_error,
        max_face_error=settings.max_face_error,
        smoothing=settings.smoothing, add_sound=settings.add_sound,
        set_frame_range=settings.set_frame_range)


def check_runtime() -> None:
    """The runtime packages are there and import (e.g. a wheel for a newer OS fails here)."""
    missing = missing_runtime()
    if missing:
        raise DiffshegError(f"missing Python packages: {', '.join(missing)}; {runtime_fix()}")
    for name in RUNTIME:
        try:
            importlib.import_module(name)
        except Exception as exc:  # ImportError, or an OSError from a shared library
            needs = bundled_wheels_need()
            raise DiffshegError(f"the Python package {name} is installed but does not load "
                                f"({type(exc).__name__}: {exc}); "
                                + (f"the bundled wheels need {needs} or newer; " if needs else "")
                                + runtime_fix()) from None


def bundled_wheels_need() -> str | None:
    """The OS release the extension's wheels ask for (wheels/wheels.json, see build_addon.py)."""
    import json

    record = Path(__file__).resolve().parent / "wheels" / "wheels.json"
    try:
        return json.loads(record.read_text(encoding="utf-8")).get("requires_os")
    except (OSError, ValueError):
        return None


def check_model(settings) -> None:
    """What the chosen model and device need besides the runtime: torch for official
    checkpoints and CUDA GPUs (the GPU support of the preferences)."""
    from diffsheg_core.checkpoints import is_ours  # the runtime's packages: check_runtime came first

    if torch_installed():
        return
    raw = settings.model_path.strip()
    if raw:
        path = Path(bpy.path.abspath(raw))
        if path.is_file() and not is_ours(path):
            raise DiffshegError(f"{path.name} is an official DiffSHEG checkpoint (a torch file): it needs "
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
    from .bake import check_frames  # numpy: checked above

    check_frames(options.start_frame)
    from diffsheg_core.checkpoints import stored_rig  # the runtime's packages: checked above

    rig = stored_rig(bpy.path.abspath(settings.model_path) if settings.model_path.strip() else None)
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
    return Request(path, options, generation, keep_face=settings.keep_face, range=request)


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
    from diffsheg_core.settings import parse_style

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

    from .bake import scene_fps

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
