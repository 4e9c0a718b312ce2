"""Operators: Generate (modal, generation in a worker thread), Generate for Sound Strips
(the same, one take per sound strip of the Video Sequencer), new seed, face mesh list.

Generation never touches Blender data: it runs `diffsheg_core.generate` off the main
thread, reports progress through a `threading.Event`-cancellable job, and only when it
has finished does the main thread key the result (one undo step). Cancel and errors
therefore leave the scene as it was.
"""

from __future__ import annotations

import importlib
import random
from dataclasses import dataclass, replace
from pathlib import Path

import bpy

from diffsheg_core.errors import DiffshegError

from . import preset
from .job import GenerationJob, Request, RequestQueue
from .preferences import INSTALL_GPU_HINT, RUNTIME, missing_runtime, runtime_fix, torch_installed
from .properties import CUSTOM_PRESET, DEFAULT_STYLE, NO_MIX
from .report import MAX_LINE, REPORT_TEXT, model_label, report_details, report_line, warning_lines, write_report


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
    "Set ..." toggle means the model's default."""
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
        guidance=settings.guidance if settings.set_guidance else None,
        skip_guidance=settings.gesture_energy if settings.set_gesture_energy else None,
        device=settings.device_arg())


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
    from diffsheg_core.checkpoints import stored_layout  # the runtime's packages: checked above

    layout = stored_layout(bpy.path.abspath(settings.model_path) if settings.model_path.strip() else None)
    if options.armature is not None and layout is not None and options.preset is not None:
        options.preset.joint_map(layout)  # names the missing section before generating
    return options


def prepare(context) -> Request:
    """The panel's request, checked before anything runs (main thread): the whole clip of
    the panel's audio, or a range of the take playing (with the take's own audio). Timeline
    markers named 'style:...' change the style from their frame on."""
    settings, scene = context.scene.diffsheg, context.scene
    path, options = check_ready(settings)
    generation = generate_settings(settings)
    if settings.range_mode == "WHOLE":
        generation = replace(generation, style_at=marker_styles(scene, options.start_frame))
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
    generation = replace(generation, style_at=marker_styles(scene, request.source.start_frame))
    return Request(path, options, generation, keep_face=settings.keep_face, range=request)


STYLE_MARKER = "style:"


def marker_styles(scene, start_frame: int) -> tuple | None:
    """The style changes the scene's timeline markers name ('style:calm',
    'style:calm=0.7,animated=0.3'), as (seconds from `start_frame`, style); a marker before
    the start frame applies from the start. None where there are none."""
    import argparse

    from diffsheg_core.settings import parse_style

    from .bake import scene_fps

    changes = {}
    for marker in sorted(scene.timeline_markers, key=lambda m: m.frame):
        if not marker.name.startswith(STYLE_MARKER):
            continue
        try:
            style = parse_style(marker.name[len(STYLE_MARKER):])
        except argparse.ArgumentTypeError as exc:
            raise DiffshegError(f"timeline marker '{marker.name}' at frame {marker.frame}: {exc}") from None
        if style == "":
            raise DiffshegError(f"timeline marker '{marker.name}' at frame {marker.frame} names no style: "
                                "rename it like style:calm or style:calm=0.7,animated=0.3")
        changes[max(0.0, (marker.frame - start_frame) / scene_fps(scene))] = style  # the later of two at one time
    return tuple(changes.items()) or None


def layout_motion(generation):
    """A one-frame Motion of the model's layout (its joint and face names), for mapping a rig."""
    import numpy as np

    from diffsheg_core.checkpoints import load_model
    from diffsheg_core.motion import Motion

    bundle = load_model(generation.model)
    layout = bundle.layout
    return Motion(fps=bundle.config.fps, rig=layout.name, joint_names=list(layout.joint_names),
                  rotations=np.zeros((1, len(layout.joint_names), 3)), face_names=list(layout.face_names),
                  face=np.zeros((1, len(layout.face_names))))


def apply_result(context, settings, motion, request: Request, seconds: float) -> str:
    """Key `motion` into the scene (main thread only), write the report's details into the
    "DiffSHEG report" Text; returns the report's one line."""
    result = request.apply(context.scene, motion)
    meta = motion.meta["regenerated"][-1] if request.range is not None else motion.meta
    settings.model_label = model_label(meta)
    line = report_line(result, seconds)
    write_report(report_details(result, seconds, settings.model_label))
    settings.last_report, settings.last_failed = line, False
    return line


def error_message(exc: BaseException) -> str:
    if isinstance(exc, DiffshegError):
        return str(exc)
    return f"unexpected {type(exc).__name__}: {exc}"


class DIFFSHEG_OT_generate(bpy.types.Operator):
    """Generate body, hand, head and face animation from the audio file"""

    bl_idname = "diffsheg.generate"
    bl_label = "Generate"
    bl_options = {"REGISTER", "UNDO"}

    _job: GenerationJob | None = None
    _timer = None

    def execute(self, context):
        """Blocking run (scripts, batch): generate, then key."""
        try:
            request = prepare(context)
            job = GenerationJob(request).start()
            job.wait()
            if job.error is not None:
                raise job.error
            line = apply_result(context, context.scene.diffsheg, job.motion, request, job.elapsed)
        except Exception as exc:
            return self._failed(context, error_message(exc))
        self.report({"INFO"}, line)
        return {"FINISHED"}

    def _failed(self, context, message: str, level: str = "ERROR") -> set[str]:
        """Report a run that keyed nothing, in the status bar and in the panel in place of
        the previous run's report."""
        settings = context.scene.diffsheg
        settings.last_report, settings.last_failed = message, True
        self.report({level}, message)
        return {"CANCELLED"}

    def invoke(self, context, event):
        try:
            self._request = prepare(context)
        except Exception as exc:  # a message in the status bar, never a traceback
            return self._failed(context, error_message(exc))
        self._job = GenerationJob(self._request).start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        self._status(context, "Generating motion 0% - Esc to cancel")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel.set()
        if event.type != "TIMER":
            return {"RUNNING_MODAL"}
        if not job.done:
            context.window_manager.progress_update(int(100 * job.fraction))
            label = "Cancelling..." if job.cancel.is_set() else \
                f"Generating motion {int(100 * job.fraction)}% - Esc to cancel"
            self._status(context, label)
            return {"RUNNING_MODAL"}
        self._finish(context)
        if job.error is not None:
            if job.cancel.is_set():
                return self._failed(context, "generation cancelled: the scene is unchanged", "WARNING")
            return self._failed(context, error_message(job.error))
        try:
            line = apply_result(context, context.scene.diffsheg, job.motion, self._request, job.elapsed)
        except Exception as exc:
            return self._failed(context, error_message(exc))
        self.report({"INFO"}, line)
        return {"FINISHED"}

    def _finish(self, context) -> None:
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        self._status(context, None)

    @staticmethod
    def _status(context, text) -> None:
        if context.workspace is not None:
            context.workspace.status_text_set(text)


# --- Generate for Sound Strips --------------------------------------------------------------

def strip_audio(strip) -> Path:
    """The audio file a sound strip plays; DiffshegError when there is none to read (no sound,
    packed into the .blend, file missing or unreadable). The report names the strip."""
    from diffsheg_core.audio import check_audio_path

    sound = strip.sound
    if sound is None or not sound.filepath:
        raise DiffshegError("it plays no sound file")
    if sound.packed_file is not None:
        raise DiffshegError("its sound is packed into the .blend: unpack it (File > External Data > "
                            "Unpack Resources) to generate from it")
    path = Path(bpy.path.abspath(sound.filepath, library=sound.library))
    if not path.is_file():
        raise DiffshegError(f"its file {path.name} is missing: restore it to {path.parent} or relink "
                            "the strip")
    return check_audio_path(path)


@dataclass
class StripTake:
    """One sound strip of a Generate for Sound Strips: its request, or why it has none, and
    what keying it gave."""

    name: str
    start: int
    request: Request | None = None
    error: str | None = None         # refused before generating, or failed generating or keying
    result: object | None = None     # the BakeResult, once keyed
    cancelled: bool = False          # under way when Esc was pressed: nothing keyed
    seconds: float = 0.0


class StripsRun:
    """One Generate for Sound Strips: every sound strip of the scene's Video Sequencer (or
    the selected ones) generated from its own sound file and keyed onto the panel's
    character from the strip's start frame, one take per strip. The strips' requests are
    made here on the main thread; a `RequestQueue` generates them one after another off it,
    and `step` (main thread) keys each as soon as it is made. A strip that cannot be
    generated or keyed fails alone, with its own message; the others go on.

    Kept simple: every strip uses the panel's style (timeline markers 'style:...' are not
    read), the whole sound file from the strip's start (a trimmed strip's hidden part too,
    so the keys stay in step with the sound), never 'Start from pose', and adds no sound
    strip (the strip is there). The frame range covers all keyed strips, where the panel's
    'Set frame range' asks for it, once all have run."""

    def __init__(self, context, selected_only: bool = False):
        from .bake import check_frames
        from .sound import sound_strips

        scene, settings = context.scene, context.scene.diffsheg
        strips = [s for s in sound_strips(scene) if s.select or not selected_only]
        if not strips:
            raise DiffshegError("no selected sound strips in the Video Sequencer: select some, or untick "
                                "'Selected only'" if selected_only else
                                "no sound strips in the Video Sequencer: add the speech there first")
        check_runtime()
        options = replace(check_targets(settings), add_sound=False, set_frame_range=False)
        generation = generate_settings(settings)
        self.set_frame_range = settings.set_frame_range
        self.takes: list[StripTake] = []
        for strip in sorted(strips, key=lambda s: (s.frame_start, s.channel, s.name)):
            take = StripTake(strip.name, int(round(strip.frame_start)))
            try:
                path = strip_audio(strip)
                check_frames(take.start)
                take.request = Request(path, replace(options, start_frame=take.start), generation)
            except Exception as exc:
                take.error = error_message(exc)
            self.takes.append(take)
        self.queued = [t for t in self.takes if t.request is not None]
        self.queue = RequestQueue([t.request for t in self.queued])
        self.cancelled = False

    @property
    def current(self) -> StripTake | None:
        return self.queued[self.queue.index] if 0 <= self.queue.index < len(self.queued) else None

    def status(self) -> str:
        if self.queue.cancel.is_set():
            return "Cancelling..."
        job = self.queue.job
        percent = int(100 * job.fraction) if job is not None else 0
        return f"Strip {self.queue.index + 1}/{len(self.queued)}: generating {percent}% - Esc to cancel"

    def step(self, context) -> bool:
        """Key the strip just generated and start the next (main thread); True once all have
        run or the run was cancelled. Call again only after the job under way is done."""
        job = self.queue.job
        if job is not None:
            if not job.done:
                return False
            self._key(context, self.current, job)
        return self.queue.advance() is None

    def _key(self, context, take: StripTake, job) -> None:
        if job.error is not None:
            if self.queue.cancel.is_set():
                self.cancelled = take.cancelled = True
            else:
                take.error = error_message(job.error)
            return
        try:
            take.result = take.request.apply(context.scene, job.motion)
        except Exception as exc:  # this strip only: bake_motion left the scene as it was
            take.error = error_message(exc)
            return
        take.seconds = job.elapsed
        context.scene.diffsheg.model_label = model_label(job.motion.meta)

    def run(self, context) -> None:
        """All strips, blocking (scripts, batch)."""
        while not self.step(context):
            self.queue.job.wait()

    def finish(self, context) -> tuple[str, bool]:
        """After the last strip (main thread): the frame range, the report in the panel and the
        "DiffSHEG report" Text. Returns the report's line and whether any strip was keyed."""
        scene, settings = context.scene, context.scene.diffsheg
        if self.queue.cancel.is_set():
            self.cancelled = True
        keyed = [t for t in self.takes if t.result is not None]
        if keyed and self.set_frame_range:
            scene.frame_start = min(t.start for t in keyed)
            scene.frame_end = max(t.start + t.result.n_frames - 1 for t in keyed)
        line = self.report_line(keyed)
        write_report(self.report_details(line, settings.model_label if keyed else "none (nothing keyed)"))
        settings.last_report, settings.last_failed = line, not keyed
        return line, bool(keyed)

    def failed(self) -> list[StripTake]:
        return [t for t in self.takes if t.error is not None]

    def report_line(self, keyed: list[StripTake]) -> str:
        """How many strips were keyed, which failed and why (short: the Text has the rest)."""
        line = f"{len(keyed)} of {len(self.takes)} sound strips keyed"
        if keyed:
            line += f" ({', '.join(t.result.take for t in keyed)}), {self.queue.elapsed:.1f} s"
        if self.cancelled:
            line = "cancelled: " + line
        failed = self.failed()
        if failed:
            line += f"; {len(failed)} failed: " + ", ".join(f"'{t.name}' ({short_reason(t.error)})" for t in failed)
            line += f"; see {REPORT_TEXT}"
        if len(line) > 2 * MAX_LINE:
            line = line[:2 * MAX_LINE - 23].rstrip() + f"... see {REPORT_TEXT}"
        return line

    def report_details(self, line: str, model: str) -> str:
        lines = [line, "", f"model: {model}", "style: the panel's for every strip (timeline style markers "
                 "are not read for strips)", ""]
        for t in self.takes:
            head = f"strip '{t.name}' at frame {t.start}: "
            if t.result is not None:
                lines.append(head + report_line(t.result, t.seconds))
                lines += [f"  - {w}" for w in warning_lines(t.result)]
            elif t.error is not None:
                lines.append(head + "FAILED: " + t.error)
            elif t.cancelled:
                lines.append(head + "cancelled while generating: nothing keyed")
            else:
                lines.append(head + "not generated (cancelled)")
        return "\n".join(lines) + "\n"


def short_reason(message: str, limit: int = 80) -> str:
    """A message's first clause (up to its first ': '), for a one-line report."""
    first = message.split(": ")[0]
    return first if len(first) <= limit else first[:limit - 3] + "..."


class DIFFSHEG_OT_generate_strips(bpy.types.Operator):
    """Generate animation for every sound strip of the Video Sequencer (or the selected ones),
    each keyed from its strip's frame as a take of its own"""

    bl_idname = "diffsheg.generate_strips"
    bl_label = "Generate for Sound Strips"
    bl_options = {"REGISTER", "UNDO"}

    selected_only: bpy.props.BoolProperty(name="Selected only", default=False,
                                          description="Only the selected sound strips")

    _run: StripsRun | None = None
    _timer = None

    def execute(self, context):
        """Blocking run (scripts, batch): generate and key each strip in turn."""
        try:
            run = StripsRun(context, self.selected_only)
            run.run(context)
            line, keyed = run.finish(context)
        except Exception as exc:
            return self._failed(context, error_message(exc))
        return self._done(run, line, keyed)

    def _failed(self, context, message: str, level: str = "ERROR") -> set[str]:
        settings = context.scene.diffsheg
        settings.last_report, settings.last_failed = message, True
        self.report({level}, message)
        return {"CANCELLED"}

    def _done(self, run: StripsRun, line: str, keyed: bool) -> set[str]:
        """FINISHED (one undo step) when any strip was keyed, though others failed."""
        if not keyed:
            self.report({"WARNING" if run.cancelled else "ERROR"}, line)
            return {"CANCELLED"}
        self.report({"WARNING"} if run.failed() or run.cancelled else {"INFO"}, line)
        return {"FINISHED"}

    def invoke(self, context, event):
        try:
            self._run = StripsRun(context, self.selected_only)
            self._run.step(context)  # starts the first strip
        except Exception as exc:  # a message in the status bar, never a traceback
            return self._failed(context, error_message(exc))
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        DIFFSHEG_OT_generate._status(context, self._run.status())
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        run = self._run
        if event.type == "ESC" and event.value == "PRESS":
            run.queue.cancel.set()
        if event.type != "TIMER":
            return {"RUNNING_MODAL"}
        try:
            done = run.step(context)
        except Exception as exc:  # keying errors are the strip's; this is unexpected
            self._end(context)
            return self._failed(context, error_message(exc))
        if not done:
            context.window_manager.progress_update(int(100 * run.queue.fraction))
            DIFFSHEG_OT_generate._status(context, run.status())
            return {"RUNNING_MODAL"}
        self._end(context)
        line, keyed = run.finish(context)
        return self._done(run, line, keyed)

    def _end(self, context) -> None:
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        DIFFSHEG_OT_generate._status(context, None)


class DIFFSHEG_OT_new_seed(bpy.types.Operator):
    """Pick a new random seed (a different motion for the same audio)"""

    bl_idname = "diffsheg.new_seed"
    bl_label = "New Seed"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        context.scene.diffsheg.seed = random.randrange(0, 2**31 - 1)
        return {"FINISHED"}


class DIFFSHEG_OT_face_add(bpy.types.Operator):
    """Add the selected meshes that have shape keys as face meshes"""

    bl_idname = "diffsheg.face_add"
    bl_label = "Add Selected Face Meshes"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        settings = context.scene.diffsheg
        present = set(settings.face_objects())
        added = 0
        for obj in context.selected_objects:
            if obj.type == "MESH" and obj.data.shape_keys is not None and obj not in present:
                settings.face_meshes.add().object = obj
                added += 1
        if not added:
            self.report({"WARNING"}, "select a mesh with shape keys first")
            return {"CANCELLED"}
        return {"FINISHED"}


class DIFFSHEG_OT_face_remove(bpy.types.Operator):
    """Remove the highlighted face mesh from the list"""

    bl_idname = "diffsheg.face_remove"
    bl_label = "Remove Face Mesh"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        settings = context.scene.diffsheg
        if not 0 <= settings.face_index < len(settings.face_meshes):
            return {"CANCELLED"}
        settings.face_meshes.remove(settings.face_index)
        settings.face_index = max(0, settings.face_index - 1)
        return {"FINISHED"}


class DIFFSHEG_OT_show_report(bpy.types.Operator):
    """Open the details of the last Generate (the "DiffSHEG report" text) in a Text Editor"""

    bl_idname = "diffsheg.show_report"
    bl_label = "Show Report"

    def execute(self, context):
        text = bpy.data.texts.get(REPORT_TEXT)
        if text is None:
            self.report({"WARNING"}, "no report yet: press Generate first")
            return {"CANCELLED"}
        area = next((a for a in context.screen.areas if a.type == "TEXT_EDITOR"), None) \
            if context.screen is not None else None
        if area is None:
            try:
                bpy.ops.wm.window_new()
            except RuntimeError:  # no window to open one from (headless): the text is there
                self.report({"INFO"}, f"the report is in the Text '{REPORT_TEXT}'")
                return {"FINISHED"}
            area = context.window_manager.windows[-1].screen.areas[0]
            area.type = "TEXT_EDITOR"
        area.spaces.active.text = text
        return {"FINISHED"}


class DIFFSHEG_OT_use_take(bpy.types.Operator):
    """Play this take on the character (body and face); the other takes stay in the file"""

    bl_idname = "diffsheg.use_take"
    bl_label = "Use Take"
    bl_options = {"REGISTER", "UNDO"}

    take: bpy.props.StringProperty(name="Take")

    def execute(self, context):
        from . import takes

        try:
            names = takes.use_take(self.take)
        except DiffshegError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"playing {self.take}: {', '.join(names)}")
        return {"FINISHED"}


CLASSES = (DIFFSHEG_OT_generate, DIFFSHEG_OT_generate_strips, DIFFSHEG_OT_new_seed, DIFFSHEG_OT_face_add,
           DIFFSHEG_OT_face_remove, DIFFSHEG_OT_use_take, DIFFSHEG_OT_show_report)

register, unregister = bpy.utils.register_classes_factory(CLASSES)
