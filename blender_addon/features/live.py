"""Live: speech from a microphone, a file played as if spoken, or a socket drives the panel's
character in the viewport as it arrives, and Record keeps the performance as a take.

`LiveRun` is one session on Blender's side. It is resolved once from the panel on the main
thread (the same generation settings, character, preset and checks as Generate), matches
the rig once with keying's own mapping (bake.resolve_preset / map_targets) and starts a
`diffsheg_core.live.LiveSession`, which generates off the main thread. On every tick (the
modal operator's timer, ~60 per second) `step` poses the newest frame due through the
channels keying would write for it (bake.body_pose / rotation_channels / face_channels: the bone's own
rotation mode, the shape keys' slider ranges): nothing is keyed and no Action changes
while live. On Stop (or when the source ends) the session finishes in a background job;
`end` then puts the pose back as it was (the Action's, where one plays), and with Record
writes the performance's audio as a WAV file and keys the performance as a new take with
the same path as Generate (bake_motion: GENERATED keys, the source Motion, audio and start
frame stored for regenerating ranges, the audio as a sound strip), from the scene's frame
at Start. Errors are reports, never tracebacks; a failed keying leaves the scene as it was.

Only one session runs at a time (`current()`). Undo, Redo and opening a file end a session
at once without touching Blender data (the data it points at are about to be replaced); a
frame change while live (the timeline played or scrubbed) poses the live frame again over
the Action's.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import bpy
from bpy.app.handlers import persistent

from diffsheg_core.errors import DiffshegError

from .generate import BackgroundJob

MIC, FILE, SOCKET = "MIC", "FILE", "SOCKET"
SOCKET_HOST = "127.0.0.1"  # the socket listens on this computer only: whoever reaches it speaks
SOCKET_RATE = 16000        # the socket's PCM: 16-bit mono at this rate (TcpSource's default)
RECORDINGS = "live"        # the folder beside the .blend that holds the recordings' audio
DISCARD_WAIT_S = 5.0       # the most a discarded session's threads are waited for

_current: "LiveRun | None" = None


def current() -> "LiveRun | None":
    """The live session running, if any."""
    return _current


# ---------------------------------------------------------------- posing

class Poser:
    """Poses the character from single frames of the model's layout (with `legs`, the lower
    body's joints after them and the hips' translation), through the channels keying writes
    (bake.py), and remembers each value it changes to put it back. A frame at a time there
    are no contact spans to pin the feet over: a foot the stream says is down is pinned on
    the rig where it lands (feet.LiveFeet)."""

    def __init__(self, bundle, options, legs: bool = False):
        import numpy as np

        from diffsheg_core.lower_body import JOINTS, with_lower_body
        from diffsheg_core.motion import Motion

        from ..scene.bake import map_targets, resolve_preset
        from ..scene.feet import LiveFeet

        layout = bundle.rig_layout
        self.template = Motion(fps=bundle.config.fps, rig=layout.name, joint_names=list(layout.joint_names),
                               rotations=np.zeros((1, len(layout.joint_names), 3)),
                               face_names=list(layout.face_names), face=np.zeros((1, len(layout.face_names))))
        if legs:
            self.template = with_lower_body(self.template, np.zeros((1, len(JOINTS), 3)), np.zeros((1, 3)),
                                            {"right": [], "left": []})
        options, notes = resolve_preset(layout.name, options)
        self.targets = map_targets(self.template, options, notes)
        self.options = self.targets.options
        self.feet = LiveFeet(bundle.config.fps)
        self._owners: dict[tuple[int, str], tuple[object, str]] = {}  # (datablock's pointer, path) -> owner
        self.saved = [(id_data, path, self._read(id_data, path)) for id_data, path, _ in self._values(self.template)]

    def _values(self, motion, frame=None) -> list[tuple[object, str, tuple]]:
        """(datablock, data path, values by array index) of the first frame of `motion`, the
        stream's `frame` (a LiveFrame) when it is one, with its feet pinned."""
        from ..scene.bake import body_pose, face_channels, location_channels, rotation_channels

        out = []
        mapping = self.targets.armature
        if mapping is not None:
            armature = self.options.armature
            quaternions, location = body_pose(mapping, motion)
            if frame is not None and frame.feet_down and location is not None and mapping.legs:
                displacement = mapping.root.displacement(location)
                legs, lowered = self.feet.solve(mapping.legs, displacement, quaternions, mapping.root.bone,
                                                frame.feet_down, frame.index)
                quaternions.update(legs)
                if lowered is not displacement:  # the hips came down for a pinned foot to reach
                    location = mapping.root.location(lowered)
            groups = [rotation_channels(bone, armature.pose.bones[bone].rotation_mode, quats)
                      for bone, quats in quaternions.items()]
            if location is not None:
                groups.append(location_channels(mapping.root.bone, location))
            for channels in groups:
                out.append((armature, channels[0].data_path,
                            tuple(float(ch.values[0]) for ch in sorted(channels, key=lambda c: c.index))))
        for mesh, keys in self.targets.faces:
            for ch in face_channels(mesh, keys, motion.face):
                out.append((mesh.data.shape_keys, ch.data_path, (float(ch.values[0]),)))
        return out

    def _owner(self, id_data, path: str) -> tuple[object, str]:
        key = (id_data.as_pointer(), path)
        if key not in self._owners:
            owner_path, attr = path.rsplit(".", 1)
            self._owners[key] = (id_data.path_resolve(owner_path), attr)
        return self._owners[key]

    def _read(self, id_data, path: str) -> tuple:
        owner, attr = self._owner(id_data, path)
        value = getattr(owner, attr)
        return tuple(value) if hasattr(value, "__len__") else (float(value),)

    def _write(self, id_data, path: str, values: tuple) -> None:
        owner, attr = self._owner(id_data, path)
        setattr(owner, attr, values[0] if len(values) == 1 else values)

    def pose(self, frame, passed: tuple = ()) -> None:
        """Pose one LiveFrame (its rotations, face weights and hips' translation); `passed`:
        the frames made since the last one posed that are not shown (their feet still count)."""
        for skipped in passed:
            if skipped.feet_down:
                self.feet.passed(skipped.feet_down)
        root = None if frame.root_translation is None else frame.root_translation[None]
        motion = replace(self.template, rotations=frame.rotations[None], face=frame.face[None], root_translation=root)
        for id_data, path, values in self._values(motion, frame):
            self._write(id_data, path, values)

    def restore(self, scene) -> None:
        """Every value back as it was before the first pose, then the animation playing
        evaluated again at the current frame (so the Action's keys show where there are any)."""
        for id_data, path, values in self.saved:
            self._write(id_data, path, values)
        if any(_animated(id_data) for id_data in {i.as_pointer(): i for i, _, _ in self.saved}.values()):
            scene.frame_set(scene.frame_current)


def _animated(id_data) -> bool:
    anim = getattr(id_data, "animation_data", None)
    return anim is not None and (anim.action is not None or len(anim.nla_tracks) > 0)


# ---------------------------------------------------------------- sources

def make_source(settings):
    """The panel's live source (not started). DiffshegError when it cannot be used."""
    from diffsheg_core.live.sources import FileSource, MicSource, TcpSource

    if settings.live_source == FILE:
        raw = settings.live_file.strip() or settings.audio_path.strip()
        if not raw:
            raise DiffshegError("no file for Live: pick a speech file in the Live panel (or Audio in the main panel)")
        return FileSource(bpy.path.abspath(raw), speed=settings.live_speed)
    if settings.live_source == SOCKET:
        return TcpSource(SOCKET_HOST, settings.live_port, sample_rate=SOCKET_RATE)
    device = settings.live_mic.strip()
    return MicSource(int(device) if device.isdigit() else (device or None))


def _vmc_sender(settings, bundle, legs: bool):
    try:
        from diffsheg_core.live.vmc import VmcSender, parse_address
    except ImportError:
        raise DiffshegError("VMC out needs the Python package python-osc, which is not installed: "
                            "turn VMC out off, or install the add-on's dependencies again") from None
    host, port = parse_address(settings.live_vmc_address)
    return VmcSender(host, port, bundle.rig_layout, legs=legs)


# ---------------------------------------------------------------- recordings

def recording_folder() -> Path:
    """Where recordings' audio goes: a 'live' folder beside the saved .blend, else the
    system's temporary folder (the report says so)."""
    if bpy.data.filepath:
        return Path(bpy.path.abspath("//")) / RECORDINGS
    return Path(tempfile.gettempdir()) / "diffsheg_live"


def recording_path(folder: Path) -> Path:
    """live_001.wav, live_002.wav, ...: the first name neither on disk nor a take's audio."""
    from ..scene import takes

    used = {a.get(takes.AUDIO) for a in bpy.data.actions if takes.is_take(a)}
    n = 1
    while (folder / f"live_{n:03d}.wav").exists() or f"live_{n:03d}" in used:
        n += 1
    return folder / f"live_{n:03d}.wav"


def write_recording(audio, path: Path) -> None:
    import soundfile as sf

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        sf.write(str(path), audio.samples, audio.sample_rate, format="WAV", subtype="FLOAT")
    except (OSError, RuntimeError) as exc:  # soundfile raises RuntimeError subclasses
        path.unlink(missing_ok=True)
        raise DiffshegError(f"could not write the recording's audio to {path} ({exc}): free some disk space "
                            "or save the .blend in a folder you can write to") from None


# ---------------------------------------------------------------- the run

class _Finish(BackgroundJob):
    """The session stopped and its recording made, off the main thread (the generator
    finishes the audio heard so far)."""

    def __init__(self, session):
        super().__init__()
        self.session = session
        self.result = None
        self.error: BaseException | None = None

    def work(self) -> None:
        try:
            self.session.stop()
            self.result = self.session.finish()
        except BaseException as exc:  # handed to the main thread, which reports it
            self.error = exc


@dataclass
class LiveOutcome:
    """How a session ended, for the status bar and the panel: the line, its level (INFO,
    WARNING, ERROR) and the take it recorded, if any."""

    line: str
    level: str
    take: str | None = None


class LiveRun:
    """One live session on Blender's side (see the module's docstring). Made on the main
    thread from the panel; raises DiffshegError, with nothing changed, when it cannot run."""

    def __init__(self, context):
        from diffsheg_core.checkpoints import load_model
        from diffsheg_core.live.engine import LiveConfig
        from diffsheg_core.live.session import LiveSession

        from ..environment import check_runtime
        from .generate import check_targets, generate_settings

        if _current is not None:
            raise DiffshegError("a live session is running already: press Stop (or Esc) first")
        scene, settings = context.scene, context.scene.diffsheg
        check_runtime()
        options = check_targets(settings)
        generation = generate_settings(settings)  # the panel's emotion too (its markers need a whole take)
        self.scene = scene
        self.record = settings.live_record
        self.start_frame = scene.frame_current
        bundle = load_model(generation.model)
        self.vmc = None
        self.source = make_source(settings)
        try:
            self.session = LiveSession(self.source, generation, LiveConfig.chosen(settings.live_hop), bundle=bundle)
            legs = self.session.legs is not None
            self.poser = Poser(bundle, replace(options, start_frame=self.start_frame, add_sound=True), legs)
            self.vmc = _vmc_sender(settings, bundle, legs) if settings.live_vmc else None
        except BaseException:
            self.source.stop()
            raise
        self.emotion = generation.emotion  # the panel's, as Live last applied it
        self.shown = 0
        self.last = None  # the frame posed last
        self.stop_requested = False
        self.discarded = False
        self.finishing: _Finish | None = None
        self.started = time.monotonic()

    # --- running (main thread) -----------------------------------------------------
    def start(self) -> "LiveRun":
        global _current
        if _current is not None:
            raise DiffshegError("a live session is running already: press Stop (or Esc) first")
        try:
            self.session.start()
        except BaseException:
            self.source.stop()
            self._close_vmc()
            raise
        _current = self
        self.started = time.monotonic()
        return self

    def step(self, now: float | None = None) -> bool:
        """One tick: pose the newest frame due (every frame due goes out over VMC); once the
        source has ended or Stop was asked for, let the session finish. True once it has
        finished and `end` can run."""
        if self.finishing is None:
            self._follow_the_panels_emotion()
            frames = self.session.frames_due(now)
            if frames:
                self.last = last = frames[-1]
                self.poser.pose(last, passed=frames[:-1])
                self.shown += len(frames)
                if self.vmc is not None:
                    for frame in frames:
                        self.vmc.send(frame.rotations, frame.face, frame.time, frame.root_translation)
            if self.stop_requested or self.session.done:
                self.finishing = _Finish(self.session).start()
        return self.finishing is not None and self.finishing.done

    def _follow_the_panels_emotion(self) -> None:
        """The performer changed the panel's Emotion or Intensity while live: it eases in from
        the next frames made (the recording notes when)."""
        from .generate import panel_emotion

        wanted = panel_emotion(self.scene.diffsheg)
        if wanted != self.emotion:
            self.session.set_emotion(wanted)
            self.emotion = wanted

    def repose(self) -> None:
        """Pose the frame shown last again: the animation playing was evaluated over it (the
        timeline played or scrubbed while live)."""
        if self.last is not None and self.finishing is None:
            self.poser.pose(self.last)

    def request_stop(self) -> None:
        """End the session at the next tick (Stop, Esc)."""
        self.stop_requested = True

    def run(self, context, poll_s: float = 0.01) -> LiveOutcome:
        """The whole session, blocking (scripts; a file source, which ends by itself)."""
        self.start()
        try:
            while not self.step():
                time.sleep(poll_s)
        except BaseException:
            self.discard(restore=True)
            raise
        return self.end(context)

    def status(self) -> str:
        """One line for the status bar and the panel."""
        if self.finishing is not None:
            return "Live: stopping, finishing the audio heard so far..."
        line = f"Live, {self.source.description}: {self.session.status().strip()}"
        if self.vmc is not None and self.vmc.last_error:
            line += f"; VMC: {self.vmc.errors} frames not sent"
        return line

    # --- ending ----------------------------------------------------------------------
    def discard(self, restore: bool = False) -> None:
        """End at once, keeping nothing. `restore`: put the pose back (not when the data are
        about to be replaced: undo, opening a file). The session's threads are given up to
        DISCARD_WAIT_S to end (a fraction of a second: the last hop), so that Blender quitting
        right after never tears down the runtime under them (that aborted the process)."""
        global _current
        if _current is self:
            _current = None
        self.discarded = True
        if self.finishing is None:
            self.finishing = _Finish(self.session).start()
        self.finishing.wait(DISCARD_WAIT_S)
        self._close_vmc()
        if restore:
            try:
                self.poser.restore(self.scene)
            except (ReferenceError, RuntimeError):
                pass  # the character was deleted meanwhile

    def end(self, context) -> LiveOutcome:
        """After `step` said so (main thread): the pose back, and with Record the take."""
        global _current
        if _current is self:
            _current = None
        self._close_vmc()
        job = self.finishing
        problems = []
        try:
            self.poser.restore(context.scene)
        except (ReferenceError, RuntimeError) as exc:
            problems.append(f"the pose could not be put back ({exc})")
        if job is None or job.error is not None or job.result is None:
            from .generate import error_message

            why = error_message(job.error) if job is not None and job.error is not None else "it did not finish"
            return LiveOutcome(f"live session failed: {why}", "ERROR")
        result = job.result
        heard = len(result.audio.samples) / result.audio.sample_rate
        summary = _summary(result)
        if result.error:
            problems.insert(0, result.error)
        if not result.motion.n_frames:
            line = "live: no speech came, nothing recorded" + (f": {result.error}" if result.error else "")
            return LiveOutcome(line, "ERROR" if result.error else "WARNING")
        if not self.record:
            line = f"live: {heard:.1f} s, {summary}; not recorded (Record is off)"
            return LiveOutcome(_with(line, problems), "WARNING" if problems else "INFO")
        try:
            take = self._record(context, result, summary, problems)
        except Exception as exc:
            from .generate import error_message

            line = f"live: {heard:.1f} s, {summary}; the recording could not be keyed: {error_message(exc)}"
            return LiveOutcome(line, "ERROR")
        return take

    def _record(self, context, result, summary: str, problems: list[str]) -> LiveOutcome:
        from ..scene.bake import bake_motion
        from ..scene.report import model_label, report_details, warning_lines, write_report

        scene, settings = context.scene, context.scene.diffsheg
        motion, audio = result.motion, result.audio  # as long as each other (LiveEngine.heard_frames)
        path = recording_path(recording_folder())
        write_recording(audio, path)
        motion = replace(motion, meta={**motion.meta, "audio_file": str(path)})
        try:
            baked = bake_motion(scene, motion, str(path), self.poser.options)
        except BaseException:
            path.unlink(missing_ok=True)  # nothing of the take is left: nor its audio
            raise
        if not bpy.data.filepath:
            problems.append(f"its audio is in the temporary folder ({path}): save the .blend, then record, "
                            f"to keep recordings beside it in //{RECORDINGS}/")
        try:
            scene.frame_set(scene.frame_current)  # the new take shows at once
        except RuntimeError:
            pass
        settings.model_label = model_label(motion.meta)
        warnings = len(warning_lines(baked)) + len(problems)
        line = (f"{baked.take}: recorded live, {audio.duration:.1f} s, {baked.n_frames} frames, "
                f"{baked.n_keys:,} keys; {summary}")
        if warnings:
            line += f"; {warnings} warning{'s' if warnings > 1 else ''}, see DiffSHEG report"
        details = report_details(baked, time.monotonic() - self.started, settings.model_label, motion.meta,
                                 problems)
        write_report("\n".join([line, "", f"live: {self.source.description}", f"audio: {path}", summary, ""])
                     + details)
        return LiveOutcome(line, "WARNING" if warnings else "INFO", baked.take)

    def _close_vmc(self) -> None:
        if getattr(self, "vmc", None) is not None:
            self.vmc.close()
            self.vmc = None


def _summary(result) -> str:
    from diffsheg_core.live.session import latency_summary

    parts = []
    if result.latencies:
        lat = latency_summary(result.latencies)
        parts.append(f"latency {lat['p50']:.2f} s (p95 {lat['p95']:.2f})")
    if result.underrun_seconds:
        parts.append(f"{result.underrun_seconds:.1f} s without audio")
    if result.dropped_seconds:
        parts.append(f"{result.dropped_seconds:.1f} s of audio dropped (it came faster than this computer generates)")
    return ", ".join(parts) or "no frame shown"


def _with(line: str, problems: list[str]) -> str:
    return line + "".join(f"; {p}" for p in problems)


# ---------------------------------------------------------------- handlers

@persistent
def _data_replaced(*_args) -> None:
    """Undo, Redo or a file opened: the session's datablocks are about to be replaced."""
    run = current()
    if run is not None:
        run.discard()


@persistent
def _frame_changed(*_args) -> None:
    """The timeline moved while live: the Action's pose was evaluated over the live one."""
    run = current()
    if run is not None:
        try:
            run.repose()
        except (ReferenceError, RuntimeError):
            pass  # the character is gone: the next tick ends the session and says so


_HANDLERS = (("undo_pre", _data_replaced), ("redo_pre", _data_replaced), ("load_pre", _data_replaced),
             ("frame_change_post", _frame_changed))


def register() -> None:
    for name, handler in _HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if handler not in handlers:
            handlers.append(handler)


def unregister() -> None:
    run = current()
    if run is not None:
        run.discard(restore=True)
    for name, handler in _HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if handler in handlers:
            handlers.remove(handler)
