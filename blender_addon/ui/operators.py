"""Operators: Generate (modal, generation in a worker thread), Generate for Sound Strips
(the same, one take per sound strip of the Video Sequencer), Live (Start and Stop), new
seed, face mesh list, takes and the report. What they run is resolved from the panel in
features/ (generate.py; strips.py; Live: live.py).

Generation never touches Blender data: it runs off the main thread in a cancellable job
(features/generate.py), and only when it has finished does the main thread key the result
(one undo step). Cancel and errors therefore leave the scene as it was.
"""

from __future__ import annotations

import random
import time

import bpy

from diffsheg_core.errors import DiffshegError

from ..features import live
from ..features.generate import GenerationJob, apply_result, error_message, prepare
from ..features.strips import StripsRun
from ..scene.report import REPORT_TEXT


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


LIVE_TICK_S = 1 / 60     # the live timer: the viewport shows each frame within this of its time
LIVE_STATUS_S = 0.25     # the status bar and the panel's line are refreshed this often
UNDO_KEYS = {"Z", "Y"}   # Ctrl-Z, Ctrl-Shift-Z, Ctrl-Y: held back while live (see DIFFSHEG_OT_live_start.modal)


class DIFFSHEG_OT_live_start(bpy.types.Operator):
    """Animate the character live from the Live panel's source (microphone, file or socket):
    posed in the viewport as the speech arrives, kept as a take on Stop when Record is on"""

    bl_idname = "diffsheg.live_start"
    bl_label = "Live"
    bl_options = {"REGISTER", "UNDO"}

    _run = None
    _timer = None

    @classmethod
    def poll(cls, context):
        return live.current() is None

    def execute(self, context):
        """Blocking run (scripts): a file source to its end, then the take where Record asks."""
        if context.scene.diffsheg.live_source != live.FILE:
            return self._report(context, live.LiveOutcome(
                "a script runs Live from a file only (a microphone or socket never ends by itself): choose "
                "File, or press Start in the panel", "ERROR"))
        try:
            outcome = live.LiveRun(context).run(context)
        except Exception as exc:
            return self._report(context, live.LiveOutcome(f"live: {error_message(exc)}", "ERROR"))
        return self._report(context, outcome)

    def invoke(self, context, event):
        try:
            self._run = live.LiveRun(context).start()
        except Exception as exc:  # a message in the status bar, never a traceback
            return self._report(context, live.LiveOutcome(f"live: {error_message(exc)}", "ERROR"))
        wm = context.window_manager
        self._timer = wm.event_timer_add(LIVE_TICK_S, window=context.window)
        self._next_status = 0.0
        wm.modal_handler_add(self)
        self._status(context)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        run = self._run
        if run.discarded:  # undo, redo or a file opened: the data it posed are gone
            self._end(context)
            self.report({"WARNING"}, "live session ended (undo or a file opened): nothing recorded")
            return {"CANCELLED"}
        if event.type == "ESC" and event.value == "PRESS":
            run.request_stop()
            return {"RUNNING_MODAL"}
        if event.type in UNDO_KEYS and event.value == "PRESS" and (event.ctrl or event.oskey):
            self.report({"WARNING"}, "undo is held back while live: press Stop (or Esc) first")
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}  # the viewport, the timeline and the rest of Blender stay usable
        try:
            finished = run.step()
        except Exception as exc:  # e.g. the character deleted while live
            run.discard(restore=True)
            self._end(context)
            return self._report(context, live.LiveOutcome(f"live session ended: {error_message(exc)}", "ERROR"))
        if finished:
            self._end(context)
            return self._report(context, run.end(context))
        self._status(context)
        return {"PASS_THROUGH"}

    def cancel(self, context):
        """Blender ends the operator (a file opened, the window closed): the session ends too."""
        if self._run is not None and live.current() is self._run:
            self._run.discard()
        try:
            context.window_manager.event_timer_remove(self._timer)
        except (ReferenceError, RuntimeError, ValueError):
            pass

    def _status(self, context) -> None:
        now = time.monotonic()
        if now < self._next_status:
            return
        self._next_status = now + LIVE_STATUS_S
        DIFFSHEG_OT_generate._status(context, self._run.status() + " - Esc or Stop ends")
        _redraw_panels(context)

    def _end(self, context) -> None:
        context.window_manager.event_timer_remove(self._timer)
        DIFFSHEG_OT_generate._status(context, None)
        _redraw_panels(context)

    def _report(self, context, outcome) -> set[str]:
        settings = context.scene.diffsheg
        settings.last_report = outcome.line
        settings.last_failed = outcome.take is None and outcome.level == "ERROR"
        self.report({outcome.level}, outcome.line)
        return {"FINISHED"} if outcome.take is not None else {"CANCELLED"}


def _redraw_panels(context) -> None:
    """The 3D views' sidebars, which show the Live panel's status line (only them: the
    viewport itself redraws when the pose changes)."""
    for window in context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                for region in area.regions:
                    if region.type == "UI":
                        region.tag_redraw()


class DIFFSHEG_OT_live_stop(bpy.types.Operator):
    """End the live session (with Record on, the performance becomes a take)"""

    bl_idname = "diffsheg.live_stop"
    bl_label = "Stop Live"

    @classmethod
    def poll(cls, context):
        return live.current() is not None

    def execute(self, context):
        run = live.current()
        if run is None:
            return {"CANCELLED"}
        run.request_stop()
        return {"FINISHED"}


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
    """Play this take (body and face): a sound strip's take with the other lines, any other over them all"""

    bl_idname = "diffsheg.use_take"
    bl_label = "Use Take"
    bl_options = {"REGISTER", "UNDO"}

    take: bpy.props.StringProperty(name="Take")

    def execute(self, context):
        from ..scene import takes

        try:
            names = takes.use_take(self.take, context.scene)
        except DiffshegError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"playing {self.take}: {', '.join(names)}")
        return {"FINISHED"}


CLASSES = (DIFFSHEG_OT_generate, DIFFSHEG_OT_generate_strips, DIFFSHEG_OT_live_start, DIFFSHEG_OT_live_stop,
           DIFFSHEG_OT_new_seed, DIFFSHEG_OT_face_add, DIFFSHEG_OT_face_remove, DIFFSHEG_OT_use_take,
           DIFFSHEG_OT_show_report)

_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register() -> None:
    _register_classes()
    live.register()


def unregister() -> None:
    live.unregister()
    _unregister_classes()
