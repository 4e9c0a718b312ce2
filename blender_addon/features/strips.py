"""Generate for Sound Strips: one Request per sound strip of the Video Sequencer (its sound
file, keyed from its own frame onto the panel's character, a take of its own), run one
after another as one background job (generate.RequestQueue), and the report of the run.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import bpy

from diffsheg_core.errors import DiffshegError

from ..environment import check_runtime
from ..scene.report import MAX_LINE, REPORT_TEXT, model_label, report_line, warning_lines, write_report
from .generate import Request, RequestQueue, check_targets, error_message, generate_settings, with_markers


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
    character from the strip's start frame, one take per strip, each playing from the
    "DiffSHEG sound strips" NLA track at its own frames (named after its sound strip, in
    place of an earlier run's take of that strip), so every line plays. The strips' requests are
    made here on the main thread; a `RequestQueue` generates them one after another off it,
    and `step` (main thread) keys each as soon as it is made. A strip that cannot be
    generated or keyed fails alone, with its own message; the others go on.

    Each strip takes the panel's style and emotion, changed by the timeline's 'style:' and
    'emotion:' markers from their frames (those before the strip's start set how it starts).
    Kept simple: the whole sound file from the strip's start (a trimmed strip's hidden part too,
    so the keys stay in step with the sound), never 'Start from pose', and adds no sound
    strip (the strip is there). The frame range covers all keyed strips, where the panel's
    'Set frame range' asks for it, once all have run."""

    def __init__(self, context, selected_only: bool = False):
        from ..scene.bake import check_frames
        from ..scene.sound import sound_strips

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
            changes = with_markers(generation, scene, take.start)  # a bad marker stops the run here
            try:
                path = strip_audio(strip)
                check_frames(take.start)
                take.request = Request(path, replace(options, start_frame=take.start, nla_strip=strip.name),
                                       changes)
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
        lines = [line, "", f"model: {model}", "style and emotion: the panel's, changed from their frames by "
                 "the timeline's style: and emotion: markers", ""]
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
