"""The low-latency streaming sampler: FOPPAS with a hop of a few frames.

Offline FOPPAS adds `clip_len - overlap` frames per window (30 of 34 for the bundled model,
2 s): a frame waits up to that long for its window. Here every window adds only `hop` new
frames at its end; the `clip_len - hop` frames before them are the motion already emitted
(less the lookahead's with `through_lookahead`, below), held as FOPPAS holds its overlap
(painted in at every step, the gap at the seam carried into the new frames' x0). A window is
sampled as soon as the audio of its new frames (and `lookahead` frames past them) has
arrived, to the end of what the last one's mel frame reads, over speech features computed
from the last `context` seconds of audio (the phonetic encoder's level from all of the session
heard so far); with `through_lookahead` (the default) it ends at the lookahead's last frame
instead, whose motion is thrown away. So at 15 fps a frame is emitted about (hop + lookahead
- 1) / fps + 57 ms + one window's compute after its audio arrived (without a lookahead, once
its hop's last frame is heard: hop / fps), and the compute per second of speech is fps / hop
windows' worth. bench/bench_live.py measures both, and the cost in quality against offline
generation, for each hop tried.

The first window has nothing to continue and is sampled in full from noise; the ones
after it run FOPPAS's shorter later-window schedule. Each window's known frames stay
exactly as emitted (no cross-fade, `blend` off): they are on screen already; its new
gestures are moved to continue them in velocity too (`continue_velocity`). The
refining pass is off: run on every hop it left the wrists at 0.65x offline's speed and
1.6x its jitter (bundled model, 30 s of real speech, hop 4); without it 0.87x and 1.08x,
for a third less compute.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from ..audio import MIN_SAMPLE_RATE, Audio, n_motion_frames, samples_for_mel_frame
from ..checkpoints import ModelBundle
from ..conditioning import Conditioning, SpeechFeatures
from ..errors import DiffshegError
from ..foppas import Foppas, FoppasConfig, sampling_settings
from ..guidance import Guidance
from ..pipeline import (add_posture, build_sampling, calibrated_posture, check_finite, generation_meta, make_plan,
                        to_motion)
from ..motion import Motion
from ..runtime.backends import live_network
from ..settings import GenerateSettings
from ..speech_features import RunningLevel, frame_features, margin_frames
from ..validate import CANDIDATES, check_number

HOPS = (1, 16)  # new frames per window: below 1 nothing moves, above 16 (>1 s at 15 fps) it is not live
LOOKAHEADS = (0, 15)
LIVE_STEPS = 25  # the schedule `LiveConfig.later_start` counts in (rescaled to the steps sampled)


@dataclass(frozen=True)
class LiveConfig:
    """How the stream is sampled. Each default was chosen by measurement (bench/bench_live.py;
    the figures, and the box they came from, are on docs/live.md, "Hop 2 and lookahead 1" and
    "The defaults, measured").
    A frame waits for the audio of its hop and lookahead, to the end of what the last lookahead
    frame's mel reads ((hop + lookahead - 1) / fps + 57 ms at 15 fps; without a lookahead until
    the hop's last frame is heard), then a window's compute.
    - hop 2, lookahead 1: 0.19 s of audio, against 0.33 s at hop 3 and lookahead 2 (live's
      defaults until 2026-12-06, when a window waited for whole frames); smaller hops cost
      compute and jitter at the seams (brought back by match_velocity), a frame of lookahead
      less cost the lip-sync (brought back by through_lookahead with face_scale).
    - through_lookahead: each window ends at its lookahead frame (its motion thrown away), so
      the new frames are not the window's last. With face_scale 1.5 (the face's
      classifier-free guidance, times the settings'), the jaw opens at open vowels over
      bilabials as offline's does (0.99x; at lookahead 1 without either, 0.87x).
    - match_velocity: each window's new gestures are moved so that the seam's change of velocity
      is shared with the first new frame (`continue_velocity`). With a seam every other frame
      the wrists jittered 1.14-1.20x offline's (the best of two samplings a window, 2.2x skip
      guidance, seeds 0-3); with it (one sampling a window, 2.7x, the same seeds) 0.97-1.00x and
      their jerk 0.88-0.92x, for less speed (0.81-0.84x), which the skip guidance buys back. So
      one sampling a window does (candidates).
    - skip_scale 3.8: live's new frames are painted against the known ones without the refining
      pass, so they need more skip guidance to move like offline's. Over seeds 0-7 (the take,
      its held-out 20 s, unseen speech) the wrists move 0.93-0.96x offline's speed, jitter
      1.12-1.14x and jerk 1.01-1.04x (bars 0.9x, 1.2x); at 3.4x (seeds 0-3) 0.85-0.90x. With
      the gesture prior's draws 1.2x as wide and live's int8 graphs (2026-12-07): 0.91-0.94x,
      jitter 1.09-1.12x.
    - later_start 14 of 25 steps (FOPPAS's published value): 15 network calls a window instead
      of 18, the same figures against offline.
    - legs_eta None (the model's eta): less noise sways the hips more, but the first foot
      comes down late and a rig's planted foot strays.
    - legs_skip_scale 3.5: the hips sway 0.89x offline's and a foot is down in 91-97 % of frames
      (seeds 0-7, the take, with the gesture prior's draws 1.2x as wide and live's int8 graphs,
      2026-12-07; the lower branch's channels of the same passes: no more compute); at 4x 0.97x
      but 88-96 %, one seed under issue 40's 90 %. More sways more but sets a foot down less
      often.
    - candidates None: the settings' (one, unless a job asks for more).
    - max_hop 12: a machine too slow for the hop does not fall behind: when more than a hop of
      audio waits, the next window takes it all (a window costs about the same for any hop),
      so the latency stays bounded and no audio is dropped; the status line and the recording
      say so. `max_hop` = `hop` turns that off."""

    hop: int = 2                       # new frames per window
    max_hop: int = 12                  # frames a window may take when more are waiting: a slow machine keeps up
    lookahead: int = 1                 # frames of audio a window waits for past its new frames
    context: float = 3.0               # seconds of audio the speech features of a window are computed over
    later_start: Optional[int] = 14    # schedule index later windows start from, at 25 steps (None: the model's)
    legs_eta: Optional[float] = None   # eta of a whole-body model's legs (None: the model's eta)
    skip_scale: float = 3.8            # the fast sampling's gesture skip guidance live, times the settings'
    legs_skip_scale: float = 3.5       # ... and that of a whole-body model's hips and legs
    face_scale: float = 1.5            # ... and its face's classifier-free guidance, times the settings'
    through_lookahead: bool = True     # a window runs on through its lookahead frames (their motion thrown away)
    candidates: Optional[int] = None   # best of this many samplings of each window (None: the settings')
    match_velocity: bool = True        # a window's new gestures continue the frames shown in velocity too

    @classmethod
    def chosen(cls, hop: Optional[int] = None, lookahead: Optional[int] = None) -> "LiveConfig":
        """The defaults with a user's hop and lookahead when given (a hop wider than the
        default's widest is its own widest)."""
        given = {name: value for name, value in (("hop", hop), ("lookahead", lookahead)) if value is not None}
        if hop is not None and isinstance(hop, int) and hop > cls.max_hop:
            given["max_hop"] = hop
        return cls(**given)

    def check(self, clip_len: int) -> None:
        for name, value, (lo, hi) in (("hop", self.hop, HOPS), ("lookahead", self.lookahead, LOOKAHEADS)):
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise DiffshegError(f"live {name} must be a whole number of frames from {lo} to {hi}, "
                                    f"got {value!r}")
        if self.hop >= clip_len:
            raise DiffshegError(f"live hop must be shorter than the model's {clip_len}-frame window, "
                                f"got {self.hop}")
        if isinstance(self.max_hop, bool) or not isinstance(self.max_hop, int) \
                or not self.hop <= self.max_hop <= min(HOPS[1], clip_len - 1):
            raise DiffshegError(f"live max_hop must be a whole number of frames from the hop ({self.hop}) to "
                                f"{min(HOPS[1], clip_len - 1)} (the hop: never wider), got {self.max_hop!r}")
        if self.later_start is not None and (isinstance(self.later_start, bool)
                                             or not isinstance(self.later_start, int)
                                             or not 0 <= self.later_start < LIVE_STEPS):
            raise DiffshegError(f"live later_start must be None (the model's) or a step index from 0 to "
                                f"{LIVE_STEPS - 1}, got {self.later_start!r}")
        if self.legs_eta is not None and (isinstance(self.legs_eta, bool) or not isinstance(self.legs_eta, (int, float))
                                          or not 0 <= self.legs_eta <= 1):
            raise DiffshegError(f"live legs_eta must be None (the model's eta) or a number from 0 to 1, "
                                f"got {self.legs_eta!r}")
        for name in ("skip_scale", "legs_skip_scale"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 10:
                raise DiffshegError(f"live {name} must be a number from 0 to 10, got {value!r}")
        if isinstance(self.face_scale, bool) or not isinstance(self.face_scale, (int, float)) \
                or not 0 < self.face_scale <= 10:
            raise DiffshegError(f"live face_scale must be a number from 0 to 10 (above 0: at 0 the face hears no "
                                f"speech), got {self.face_scale!r}")
        for name in ("through_lookahead", "match_velocity"):
            if not isinstance(getattr(self, name), bool):
                raise DiffshegError(f"live {name} must be True or False, got {getattr(self, name)!r}")
        if self.through_lookahead and self.max_hop + self.lookahead >= clip_len:
            raise DiffshegError(f"live windows run through their lookahead must hold a frame shown: the widest hop "
                                f"({self.max_hop}) plus the lookahead ({self.lookahead}) must be under the model's "
                                f"{clip_len}-frame window; choose a smaller hop or lookahead")
        if self.candidates is not None:
            check_number("live candidates (None: the settings')", self.candidates, CANDIDATES, whole=True)
        if not isinstance(self.context, (int, float)) or not 0 < self.context <= 60:
            raise DiffshegError(f"live context must be a number of seconds above 0 and at most 60, "
                                f"got {self.context!r}")


class LiveEngine:
    """Audio in, as it arrives; final motion frames out, a hop at a time.

    `push(samples)` adds mono float32 samples at `sample_rate`; `ready()` says whether the
    next hop can be sampled; `step()` samples it and returns its (hop, D) normalised
    frames; `finish()` samples what is left after the last audio. `motion()` is
    everything emitted so far as a Motion, `audio()` everything heard."""

    def __init__(self, bundle: ModelBundle, network, settings: GenerateSettings, sample_rate: int,
                 live: LiveConfig = LiveConfig()):
        cfg = bundle.config
        if not float(cfg.fps).is_integer():
            raise DiffshegError(f"live generation needs a whole motion frame rate, model {bundle.model_id} "
                                f"runs at {cfg.fps:g} fps")
        if cfg.has_speech_input and not cfg.phonetic_input:
            raise DiffshegError(f"model {bundle.model_id} takes HuBERT features, which need the whole "
                                "recording: live generation runs models with the phonetic encoder (the "
                                "bundled model) or mel only")
        if settings.style_at:
            raise DiffshegError("a style over time (--style-at, style_at) needs the whole recording: live, "
                                "choose one style (--style NAME, style=...)")
        if settings.emotion_at:
            raise DiffshegError("an emotion over time given beforehand (--emotion-at, emotion_at, timeline "
                                "markers) needs the whole recording: live, start with one (--emotion sad, "
                                "emotion=...) and change it while it runs (a line on the CLI's standard input, "
                                "the panel's menu, LiveSession.set_emotion)")
        if isinstance(sample_rate, bool) or not isinstance(sample_rate, int) or sample_rate < MIN_SAMPLE_RATE:
            raise DiffshegError(f"live audio must come at {MIN_SAMPLE_RATE} Hz or more, got {sample_rate!r}")
        live.check(cfg.clip_len)
        opened, network = network, live_network(bundle, network)  # on onnxruntime, the model's int8 live graphs
        self.int8 = network is not opened
        self.bundle, self.network, self.settings, self.live = bundle, network, settings, live
        self.sample_rate = sample_rate
        self.fps = int(cfg.fps)
        sampling = sampling_settings(bundle.sampling, settings.sampling)
        # the plan's style covers one window's frames: live, one style holds throughout (style_at is refused above)
        plan = make_plan(bundle, settings, replace(_live_sampling(sampling, live), blend=False, refine=None),
                         n_frames=cfg.clip_len)
        self.plan = replace(plan, sampling=settings.sampling, guidance=_live_guidance(plan.guidance, settings, live,
                                                                                   cfg.lower_dim))
        self.config: FoppasConfig = self.plan.config
        self.sampler: Foppas
        self.sampler, self._make_eps_fn = build_sampling(bundle, network, self.plan)
        self.noise = self.sampler.noise(settings.seed, settings.face_seed)
        # the fast sampling's posture as calibrated for live (training.calibrate, at the model's own steps and
        # guidance scales; any hop, lookahead or live scale), added to the frames going out
        calibrated = settings.sampling == "fast" and settings.steps is None and settings.guidance is None \
            and settings.skip_guidance is None
        self.posture = calibrated_posture(bundle, live=True) if calibrated else None
        # a window's features are computed over `_context` frames of audio up to its end (at
        # least its frames and their margin): `_before` frames before its first
        context = max(int(math.ceil(live.context * self.fps)), cfg.clip_len + margin_frames(bundle, self.fps))
        self._before = context - cfg.clip_len
        # the phonetic encoder's level over the session heard so far (not each window's own: see RunningLevel)
        phonetic = bundle.phonetic if cfg.phonetic_input else None  # none with phonetic input: frame_features says so
        self._level = RunningLevel(phonetic.n_mels) if phonetic is not None and phonetic.normalise == "utterance" \
            else None
        self._buffer = np.zeros(self.sample_rate * 10, np.float32)  # every sample heard, in [: _n]
        self._n = 0
        self._frames: list[np.ndarray] = []  # emitted (k, D) normalised frames, in order
        self.emitted = 0
        self.widest_hop = 0  # the most frames one window took

    # --- audio in --------------------------------------------------------------------
    def push(self, samples: np.ndarray) -> None:
        samples = np.asarray(samples, np.float32)
        end = self._n + len(samples)
        if end > len(self._buffer):  # grown by doubling: a chunk costs its own length, not the session's
            grown = np.zeros(max(end, 2 * len(self._buffer)), np.float32)
            grown[: self._n] = self._buffer[: self._n]
            self._buffer = grown
        self._buffer[self._n: end] = samples
        self._n = end

    @property
    def n_samples(self) -> int:
        """Samples heard so far."""
        return self._n

    @property
    def heard_frames(self) -> int:
        """Motion frames of the audio heard so far, as `generate` counts them for a recording
        of that length (`audio.n_motion_frames`): so a recording's motion and audio always
        agree, and a range of it can be regenerated from that audio."""
        return n_motion_frames(Audio(self._buffer[: self._n], self.sample_rate), self.fps)

    @property
    def readable_frames(self) -> int:
        """Frames whose mel frames the audio heard so far holds whole (`samples_for_mel_frame`,
        57 ms past a frame's centre): at 15 fps every frame heard, and the next one 10 ms before
        it is heard (at the next frame's start); above 17.6 fps a mel frame reaches past that."""
        frames = self.heard_frames + 1
        while frames and samples_for_mel_frame(frames - 1, self.sample_rate, self.fps) > self._n:
            frames -= 1
        return frames

    def ready(self) -> bool:
        """Whether the audio of the next hop and its lookahead has arrived."""
        return self.waiting >= self.live.hop

    @property
    def waiting(self) -> int:
        """Frames not emitted yet whose audio and lookahead have arrived (frames heard: without a
        lookahead the frame not heard yet is not one of the recording's)."""
        return min(self.readable_frames - self.live.lookahead, self.heard_frames) - self.emitted

    # --- frames out ------------------------------------------------------------------
    def step(self, hop: Optional[int] = None) -> np.ndarray:
        """Sample the next `hop` frames (default the live hop; at most `waiting`); (hop, D)
        normalised frames, final."""
        hop = self.live.hop if hop is None else hop
        widest = self.bundle.config.clip_len - 1 - (self.live.lookahead if self.live.through_lookahead else 0)
        if isinstance(hop, bool) or not isinstance(hop, int) or not 1 <= hop <= widest:
            raise DiffshegError(f"live: a window takes 1 to {widest} new frames (the model's window holds a frame "
                                f"shown{' and the lookahead' if self.live.through_lookahead else ''}), got {hop!r}")
        if not self.ready() or hop > self.waiting:
            raise DiffshegError(f"live: the audio of the next {hop} frames has not arrived yet")
        return self._window(self.emitted + hop)

    def next_hop(self) -> int:
        """How many frames the next window takes: all that wait, at least the live hop and at
        most `max_hop`. A machine that keeps up finds a hop waiting; one that fell behind finds
        more, and a window costs about the same whatever its hop, so wider ones catch up."""
        return max(self.live.hop, min(self.waiting, self.live.max_hop))

    def finish(self) -> np.ndarray:
        """Sample the frames of the audio left after the last full hop (possibly none, or
        more than a hop: the lookahead's), so that every frame heard is emitted."""
        parts = [np.zeros((0, self.bundle.config.dim), np.float32)]
        while self.emitted < self.heard_frames:
            parts.append(self._window(min(self.heard_frames, self.emitted + self.live.hop)))
        return np.concatenate(parts)

    def _window(self, end: int) -> np.ndarray:
        """Sample the new frames up to frame `end`, holding the emitted frames before them: a window
        ending there, or with `through_lookahead` at the last readable frame of the lookahead's
        (never before `end`)."""
        last = max(end, min(end + self.live.lookahead, self.readable_frames)) if self.live.through_lookahead else end
        first = max(0, last - self.bundle.config.clip_len)
        n_known = self.emitted - first
        cond = Conditioning(self._features(first, last, end), self.plan.style.frames(0, last - first))
        known = self._known(first) if n_known else None
        window = self.sampler.sample_window(self._make_eps_fn(cond), last - first, known, self.noise)
        new = window[0, n_known: n_known + end - self.emitted]
        if self.live.match_velocity and self.emitted >= 2:
            new = continue_velocity(new, self._known(self.emitted - 2)[0], self.sampler.upper)
        check_finite(self.bundle, new)
        self._frames.append(new)
        self.emitted = end
        self.widest_hop = max(self.widest_hop, len(new))
        return new

    def _known(self, first: int) -> np.ndarray:
        """(1, emitted - first, D): the emitted frames from `first` on."""
        need, parts = self.emitted - first, []
        for part in reversed(self._frames):
            parts.insert(0, part)
            need -= len(part)
            if need <= 0:
                break
        return np.concatenate(parts)[None, -(self.emitted - first):]

    def _features(self, first: int, last: int, end: int) -> SpeechFeatures:
        """The speech features of frames [first, last), computed over the audio
        from `_before` frames before `first` (the window's `context`, back to a whole sample) to the
        end of what the mel frame `lookahead` frames after the new frames' last reads, never more: so
        they do not depend on how much audio has arrived when the window is sampled, and the same
        speech gives the same frames on any machine."""
        stop = samples_for_mel_frame(end - 1 + self.live.lookahead, self.sample_rate, self.fps)  # arrived: ready()
        return frame_features(self.bundle, self.network, Audio(self._buffer[: self._n], self.sample_rate), first, last,
                              before=self._before, stop=stop, running=self._level)

    # --- what was made ---------------------------------------------------------------
    def audio(self) -> Audio:
        return Audio(self._buffer[: self._n].copy(), self.sample_rate)

    def motion(self, meta: Optional[dict] = None) -> Motion:
        """Every frame emitted so far, as a Motion."""
        frames = np.concatenate(self._frames) if self._frames else np.zeros((0, self.bundle.config.dim), np.float32)
        return self.to_motion(frames, 0, meta or {})

    def to_motion(self, frames: np.ndarray, start: int, meta: dict) -> Motion:
        """(n, D) normalised frames as `step` returns them, the session's from frame `start`, as
        a Motion in the calibrated posture (`pipeline.add_posture`; the frames given stay as they are)."""
        if self.posture is not None:
            frames = add_posture(frames.copy(), start, self.posture, self.bundle.config.clip_len)
        return to_motion(self.bundle, frames, meta=meta)

    def meta(self) -> dict:
        """What a recording records of how it was made (as `generate`, plus the live settings)."""
        meta = generation_meta(self.bundle, self.settings, self.plan, self.network, self.audio())
        meta["live"] = {"hop": self.live.hop, "max_hop": self.live.max_hop, "widest_hop": self.widest_hop,
                        "lookahead": self.live.lookahead, "context": self.live.context, "skip_scale": self.live.skip_scale,
                        "face_scale": self.live.face_scale, "through_lookahead": self.live.through_lookahead,
                        "match_velocity": self.live.match_velocity,
                        "posture_calibrated": self.posture is not None, "int8_graphs": self.int8,
                        "legs_skip_scale": self.live.legs_skip_scale if self.sampler.branch else None,
                        "legs_eta": self.sampler.branch_eta if self.sampler.branch else None}
        return meta


def continue_velocity(new: np.ndarray, shown: np.ndarray, channels: int) -> np.ndarray:
    """`new` (k, D) frames with their first `channels` channels (the gestures a lower branch
    does not make) moved by one offset, so that the step from the last of the two frames `shown`
    (2, D) to the first new one is the mean of the velocity it arrived with and the new frames'
    own next step (a single new frame: the step it was sampled with): the seam's change of
    velocity is shared between the seam and the first new frame, and the new frames keep their
    shape.

    Why: a live window's new frames continue the known ones in position (the sampler carries the
    gap at the seam into their x0, `foppas.carry_overlap`) but not in velocity, and at a hop of
    two frames every other frame is a seam. There the wrists accelerated 1.2-1.3x as hard as
    between a hop's own frames (1.5-1.6x at a hop of three), most of live's jitter above
    offline's. Matching the velocity at the seam exactly left all the change at the first new
    frame: the jitter fell, but the wrists' jerk doubled (1.9x offline's, motion in straight
    pieces two frames long); shared, it is offline's. Carried into x0 at every step instead, a
    velocity term fed back through the network and ran away (the wrists 2.8x offline's speed)."""
    arrived = shown[1, :channels] - shown[0, :channels]
    step = new[1, :channels] - new[0, :channels] if len(new) > 1 else new[0, :channels] - shown[1, :channels]
    out = new.copy()
    out[:, :channels] += shown[1, :channels] + (arrived + step) / 2 - new[0, :channels]
    return out


def _live_guidance(guidance: Guidance, settings: GenerateSettings, live: LiveConfig, lower: int) -> Guidance:
    """The guidance scales with the fast sampling's live ones: its gesture skip guidance (a lower
    branch's `lower` channels at their own) and the face's classifier-free guidance, times live's
    (with skip guidance off the classifier-free guidance is the gestures' too, and stays)."""
    if settings.sampling != "fast" or guidance.skip is None:
        return guidance
    return replace(guidance, skip=guidance.skip * live.skip_scale, legs_skip=guidance.skip * live.legs_skip_scale,
                   lower=lower, scale=None if guidance.scale is None else guidance.scale * live.face_scale)


def _live_sampling(sampling: FoppasConfig, live: LiveConfig) -> FoppasConfig:
    """The sampling settings with later windows starting at `live.later_start` (of LIVE_STEPS
    evenly spaced steps, rescaled to the sampling's; the fast sampling's own steps keep their
    start), a lower branch's channels stepped with `live.legs_eta` and `live.candidates`
    (the settings' candidates, when they give them, replace these in `make_plan`)."""
    if live.legs_eta is not None:
        sampling = replace(sampling, branch_eta=live.legs_eta)
    if live.candidates is not None:
        sampling = replace(sampling, candidates=live.candidates)
    if live.later_start is None or sampling.timesteps is not None:
        return sampling
    return replace(sampling.with_steps(LIVE_STEPS), later_start=live.later_start).with_steps(sampling.steps)
