"""A live session: a source's audio through the engine to frames shown at a steady pace.

Three parts run together:
- the source's own thread puts audio into an `AudioFeed`;
- the session's generation thread takes it, samples a hop of frames whenever its audio
  has arrived (`engine.LiveEngine`) and hands each hop to the `Pacer`;
- whoever shows the frames (the CLI's loop, Blender's timer) asks the pacer for the
  frames due now (`LiveSession.frames_due`), one per 1/fps, and sends them on (VMC, the
  viewport). That is where the latency is measured: from the audio of a frame's time
  arriving to the frame being shown.

A producer slower than real time (a socket that stalls) leaves the engine without audio:
after `underrun_after` seconds the session fills the gap with silence as time passes, so
the avatar eases to rest, and goes on when audio comes again; the filled seconds are
reported and are part of the recording. A producer faster than the engine fills the
feed, which drops what does not fit and counts it. When the source ends (end of file,
socket closed, device gone) or `stop()` is called, the audio heard so far is finished
and the recording (`LiveResult`) holds every frame made and the audio they were made from.
"""

from __future__ import annotations

import bisect
import collections
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np

from ..audio import Audio
from ..checkpoints import ModelBundle
from ..emotion import EmotionStream
from ..errors import DiffshegError
from ..lower_body import (JOINTS as LEG_JOINTS, LowerBodyStream, PlantStream, legs_source, upper_body,
                          with_lower_body)
from ..motion import Motion
from ..pipeline import job_model
from ..runtime.backends import cpu_threads, open_network
from ..settings import GenerateSettings
from .engine import LiveConfig, LiveEngine
from .feed import AudioFeed, FeedClosed
from .sources import Source

UNDERRUN_AFTER_S = 0.3  # no audio for this long: the gap is filled with silence (far above a 20-50 ms chunk)
CUSHION_S = 0.02  # the pacer shows frames this much after the earliest it could, against compute jitter
TIGHTEN_S = 0.01  # ... and takes back at most this much waiting per hop once compute is faster again
JUDGED_AFTER_S = 2.0  # speech made before the session says whether the machine keeps up with it


@dataclass(frozen=True)
class LiveFrame:
    """One frame of the stream: its index and time in the audio, the joint rotations (J, 3)
    and face weights (C,) as a Motion holds them, when the engine made it, and with legs
    (`LiveSession.joint_names` ends with lower_body.JOINTS) the hips' translation (3,) and
    which feet are planted ({"right": bool, "left": bool})."""

    index: int
    time: float
    rotations: np.ndarray
    face: np.ndarray
    made: float
    root_translation: Optional[np.ndarray] = None
    feet_down: Optional[dict] = None


class Pacer:
    """Frames handed over a hop at a time, shown one per 1/fps at a steady delay.

    Frame i is due at offset + i / fps. The offset starts from the first hop and only
    moves when it must: a hop whose first frame is ready after its due time pushes it
    later (a slip: the delay grows by what the hop was late), and a hop ready well before
    its due time pulls it earlier by at most TIGHTEN_S, so the delay follows the compute
    down without the motion jumping."""

    def __init__(self, fps: float):
        self.fps = fps
        self.offset: Optional[float] = None
        self._queue: collections.deque[LiveFrame] = collections.deque()
        self._lock = threading.Lock()

    def add(self, frames: list[LiveFrame]) -> None:
        if not frames:
            return
        first = frames[0]
        with self._lock:
            due = None if self.offset is None else self.offset + first.index / self.fps
            if due is None:
                self.offset = first.made + CUSHION_S - first.index / self.fps
            elif first.made + CUSHION_S > due:
                self.offset += first.made + CUSHION_S - due
            else:
                self.offset -= min(due - first.made - CUSHION_S, TIGHTEN_S)
            self._queue.extend(frames)

    def due(self, now: float) -> list[LiveFrame]:
        """The frames due by `now`, oldest first, taken out of the queue."""
        out = []
        with self._lock:
            while self._queue and self.offset + self._queue[0].index / self.fps <= now:
                out.append(self._queue.popleft())
        return out

    def next_due(self) -> Optional[float]:
        """When the next queued frame is due (None: nothing queued)."""
        with self._lock:
            return None if not self._queue else self.offset + self._queue[0].index / self.fps

    def __len__(self) -> int:
        return len(self._queue)


@dataclass
class LiveResult:
    """What a session made: the recording (every frame, and the audio they came from),
    each shown frame's (time in the audio, latency), and what went wrong on the way."""

    motion: Motion
    audio: Audio
    latencies: list[tuple[float, float]]
    compute: float            # seconds spent sampling (and adding the legs)
    underrun_seconds: float   # silence filled in while the source gave no audio
    dropped_seconds: float    # audio the full feed dropped
    error: Optional[str] = None  # why the source or the engine stopped, when it was not the end of the audio
    load: Optional[float] = None  # LiveSession.load() at the end: None when too little speech was heard to judge


def latency_summary(latencies: list[tuple[float, float]]) -> dict[str, float]:
    """p50, p95 and max of the latencies (s); zeros with no frames."""
    values = np.array([lat for _, lat in latencies]) if latencies else np.zeros(1)
    return {"p50": float(np.percentile(values, 50)), "p95": float(np.percentile(values, 95)),
            "max": float(values.max()), "frames": len(latencies)}


@dataclass
class _Clock:
    """When each stretch of the audio arrived: sample offsets and their arrival times."""

    starts: list[int] = field(default_factory=list)
    arrived: list[float] = field(default_factory=list)

    def add(self, start: int, arrived: float) -> None:
        self.starts.append(start)
        self.arrived.append(arrived)

    def arrival(self, sample: int) -> float:
        return self.arrived[max(0, bisect.bisect_right(self.starts, sample) - 1)]


class LiveSession:
    """One source, one model, one stream of frames. `start()`, then `frames_due()` from the
    showing loop until `done`, then `finish()`; or `run_to_end()` for all of it."""

    def __init__(self, source: Source, settings: GenerateSettings = GenerateSettings(),
                 live: LiveConfig = LiveConfig(), underrun_after: float = UNDERRUN_AFTER_S,
                 bundle: Optional[ModelBundle] = None, network=None):
        self.source = source
        self.bundle = job_model(settings, bundle)
        self.network = network or open_network(self.bundle, settings.backend, settings.device,
                                               settings.precision, settings.threads)
        self.engine = LiveEngine(self.bundle, self.network, settings, source.sample_rate, live)
        # the emotion and the hips and legs laid over what the model makes, as `generate` lays them
        self.emotion = EmotionStream(settings.emotion, self.bundle.config.fps)  # set_emotion changes it
        self._emotional: list[Motion] = []  # the frames made, with the emotion (the recording's)
        # a whole-body model's own hips and legs, planted as they come (PlantStream); for a model
        # whose layout stops at the waist, legs cut from the capture to go with the arms
        # (LowerBodyStream); none with upper_body_only
        fps, rig = self.bundle.config.fps, self.bundle.rig_layout.name
        self.legs_source = (None if settings.upper_body_only
                            else legs_source(rig, bool(self.bundle.layout.root_translation)))
        self.legs = (PlantStream(fps) if self.legs_source == "model"
                     else LowerBodyStream(fps, settings.seed) if self.legs_source == "capture" else None)
        self.feed = AudioFeed(source.sample_rate)
        # a file played faster than real time for a demo (its `speed`) is shown that much faster too
        self.pacer = Pacer(self.bundle.config.fps * getattr(source, "speed", 1.0))
        self.underrun_after = underrun_after
        self.latencies: list[tuple[float, float]] = []
        self.compute = 0.0
        self.underrun_seconds = 0.0
        self.error: Optional[str] = None
        self.interrupted = False
        self._clock = _Clock()
        self._thread: Optional[threading.Thread] = None
        self._stopping = threading.Event()

    def set_emotion(self, emotion) -> None:
        """Change the emotion while live (any thread; e.g. the panel's menu): it eases in from
        the next hop over emotion.SWITCH_S, and the recording notes when ("emotion_at").
        A DiffshegError for a bad one, with nothing changed."""
        self.emotion.set(emotion)

    @property
    def joint_names(self) -> list[str]:
        """The joints of every frame's rotations: the model's layout, then the legs'."""
        return list(self.bundle.rig_layout.joint_names) + (list(LEG_JOINTS) if self.legs else [])

    # --- running -----------------------------------------------------------------------
    def start(self) -> None:
        self.source.start(self.feed)
        self._thread = threading.Thread(target=self._generate, name="diffsheg-live", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the session: the source stops, the audio heard so far is finished."""
        self._stopping.set()
        self.source.stop()

    @property
    def done(self) -> bool:
        """The generation thread has ended and every frame has been shown."""
        return self._thread is not None and not self._thread.is_alive() and not len(self.pacer)

    def frames_due(self, now: Optional[float] = None) -> list[LiveFrame]:
        """The frames due now, oldest first; each one's latency is logged as shown now."""
        now = time.monotonic() if now is None else now
        frames = self.pacer.due(now)
        rate = self.engine.sample_rate
        for frame in frames:
            self.latencies.append((frame.time, now - self._clock.arrival(int(frame.time * rate))))
        return frames

    def finish(self, timeout: Optional[float] = None) -> LiveResult:
        """Wait for the generation thread (after `stop()` or the source's end) and return the
        recording. Frames never shown are still in it."""
        if self._thread is not None:
            self._thread.join(timeout)
        self.source.stop()
        engine = self.engine
        meta = engine.meta()
        meta["emotion_at"] = [[t, e] for t, e in self.emotion.changes]
        meta["warnings"] = meta["warnings"] + self._warnings()
        motion = upper_body(engine.motion(meta=meta))
        if self._emotional:
            motion = replace(motion, rotations=np.concatenate([m.rotations for m in self._emotional]),
                             face=np.concatenate([m.face for m in self._emotional]))
        if self.legs is not None:
            motion = with_lower_body(motion, self.legs.lower, self.legs.trans, self.legs.contacts())
            motion = replace(motion, meta={**motion.meta, "lower_body": self.legs_source})
        return LiveResult(motion, engine.audio(), list(self.latencies), self.compute,
                          self.underrun_seconds, self.feed.dropped_seconds, self.error, self.load())

    def load(self) -> Optional[float]:
        """Seconds of compute per second of speech made so far, for the source's pace (a file
        played at `speed` x real time counts that many times): above 1 the machine falls
        behind and the latency grows. None before JUDGED_AFTER_S of speech."""
        made = self.engine.emitted / self.engine.fps
        if made < JUDGED_AFTER_S:
            return None
        return self.compute / made * getattr(self.source, "speed", 1.0)

    def _behind(self) -> Optional[str]:
        load = self.load()
        if load is None or load <= 1.0:
            return None
        return f"falling behind: {load:.1f} s of compute a second (a larger hop or fewer steps helps)"

    def _widened(self) -> Optional[str]:
        """What the session did to keep up, once it had to."""
        engine = self.engine
        if engine.widest_hop <= engine.live.hop:
            return None
        return f"hops up to {engine.widest_hop} frames to keep up (too slow for {engine.live.hop})"

    def _warnings(self) -> list[str]:
        """What the recording should say about how it was heard."""
        behind, widened = self._behind(), self._widened()
        out = [] if behind is None else [f"the machine was {behind}"]
        if widened is not None:
            out.append(f"the session sampled {widened}")
        if self.underrun_seconds:
            out.append(f"{self.underrun_seconds:.1f} s without audio from the source were filled with silence")
        if self.feed.dropped:
            out.append(f"{self.feed.dropped_seconds:.1f} s of audio were dropped: it came faster than real time")
        return out

    def run_to_end(self, on_frame: Callable[[LiveFrame], None] = lambda frame: None,
                   on_status: Optional[Callable[[str], None]] = None, status_every: float = 0.5,
                   on_start: Callable[[], None] = lambda: None) -> LiveResult:
        """Start, show every frame at its time (`on_frame`) until the source ends, and return
        the recording. Ctrl-C (KeyboardInterrupt) ends the session as the source's end would:
        the audio heard so far is finished and recorded. `on_status` gets `status()` every
        `status_every` seconds; `on_start` is called once the source has started (a TCP
        source's `port` is then the one it listens on)."""
        self.start()
        next_status = time.monotonic()
        try:
            on_start()
            while not self.done:
                for frame in self.frames_due():
                    on_frame(frame)
                if on_status is not None and time.monotonic() >= next_status:
                    on_status(self.status())
                    next_status += status_every
                due = self.pacer.next_due()
                time.sleep(0.005 if due is None else min(max(due - time.monotonic(), 0.0), 0.05))
        except KeyboardInterrupt:
            self.interrupted = True
        finally:
            self.stop()
        return self.finish()

    def status(self) -> str:
        """One line for a status bar: time heard, latency, underruns, drops and whether the
        machine keeps up."""
        recent = latency_summary(self.latencies[-150:])
        parts = [f"{self.engine.emitted / self.engine.fps:5.1f} s",
                 f"latency {recent['p50']:.2f} s (p95 {recent['p95']:.2f})" if self.latencies else "waiting for audio"]
        if self.underrun_seconds:
            parts.append(f"{self.underrun_seconds:.1f} s without audio")
        if self.feed.dropped:
            parts.append(f"{self.feed.dropped_seconds:.1f} s dropped (audio came faster than real time)")
        widened, behind = self._widened(), self._behind()
        parts += [text for text in (widened, behind) if text is not None]
        return ", ".join(parts)

    # --- the generation thread ---------------------------------------------------------
    def _generate(self) -> None:
        with cpu_threads(self.engine.settings.threads):  # numpy's threads too, as generate holds them
            self._sample_until_done()

    def _sample_until_done(self) -> None:
        engine, rate = self.engine, self.engine.sample_rate
        played = None  # when the audio heard so far has played out at real time (None: nothing heard yet)
        try:
            while True:
                try:
                    chunk = self.feed.get(timeout=0.0 if engine.ready() else 0.05)
                except FeedClosed:
                    break
                now = time.monotonic()
                if chunk is not None:
                    self._hear(chunk.samples, chunk.arrived)
                    played = max(played + len(chunk.samples) / rate if played is not None else 0.0, chunk.arrived)
                    if engine.waiting < engine.live.max_hop:
                        continue  # what is queued, up to the widest window, is taken before sampling (the rest
                        # stays in the bounded feed)
                # an underrun is a feed with nothing in it: audio waiting behind a busy sampler is not
                # one (filling that gap with silence gave the sampler more to make, a runaway)
                if chunk is None and played is not None and not self._stopping.is_set() \
                        and now - played > self.underrun_after:
                    gap = int((now - played) * rate)
                    self._hear(np.zeros(gap, np.float32), now)
                    self.underrun_seconds += gap / rate
                    played = now
                while engine.ready():
                    self._emit(lambda: engine.step(engine.next_hop()))
            self._emit(engine.finish)
        except DiffshegError as exc:
            self.error = str(exc)
            self.source.stop()
        if self.error is None and self.feed.error:
            self.error = self.feed.error

    def _hear(self, samples: np.ndarray, arrived: float) -> None:
        self._clock.add(self.engine.n_samples, arrived)
        self.engine.push(samples)

    def _emit(self, sample: Callable[[], np.ndarray]) -> None:
        first = self.engine.emitted
        started = time.perf_counter()
        normalised = sample()
        if not len(normalised):
            self.compute += time.perf_counter() - started
            return
        made = self.engine.to_motion(normalised, first, {})
        part = self.emotion.add(upper_body(made))  # the emotion never touches the legs
        self._emotional.append(part)
        rotations, roots, down = part.rotations, [None] * part.n_frames, [None] * part.n_frames
        if self.legs is not None:  # the model's own legs, or legs to go with the arms as shown
            lower, roots, feet = self.legs.add(made if self.legs_source == "model" else part)
            down = [{side: bool(v[k]) for side, v in feet.items()} for k in range(part.n_frames)]
            rotations = np.concatenate([rotations, lower.astype(rotations.dtype)], axis=1)
        self.compute += time.perf_counter() - started
        made_at = time.monotonic()
        fps = self.engine.fps
        self.pacer.add([LiveFrame(first + k, (first + k) / fps, rotations[k], part.face[k], made_at, roots[k], down[k])
                        for k in range(part.n_frames)])
