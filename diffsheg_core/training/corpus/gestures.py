"""The body teacher: gesture phrases cut from real motion capture and re-timed so that
their strokes land on accented syllables, with calm stretches of the same capture between
them, all joined by slerp cross-fades.

The capture (BEAT take 2_scott_0_1_1, `beat` layout, 15 fps) is cut at minima of the arms'
angular speed; a phrase's stroke is its speed peak. A timeline of clips maps every output
frame to a (fractional) source frame; neighbouring clips cross-fade over a few frames, and
since each clip reads real capture on both sides of its cut, a cross-fade blends two real
motions, never a held pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks

from ...errors import DiffshegError
from ...lower_body import LowerBodyLibrary, contacts
from ...rigs import BEAT_JOINTS
from ...rotations import axis_angle_to_quaternion, quaternion_sequence_continuous, quaternion_to_axis_angle
from .prosody import Accent

DEFAULT_MOCAP = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "beat" / "2_scott_0_1_1.bvh"
"""The real take beside the project checkout (../shared/data from the repository root)."""

MOCAP_FPS = 15.0
_ARM_JOINTS = tuple(f"{s}{j}" for s in ("Right", "Left") for j in ("Shoulder", "Arm", "ForeArm", "Hand"))
_FADE = 6
"""Half-length (frames) of the cross-fade between two clips. A short fade is the teacher's
main source of jitter: blending two poses over 2 * 3 frames made the wrists 1.37x as jerky
as the capture on 2_scott_0_1_1, 2 * 6 frames with pose-matched clips 1.00x."""
_POSE_MATCH = 6.0
"""How strongly the next clip is chosen to start near the current pose (2.0 before v2)."""
_MIN_PHRASE, _MAX_PHRASE = 6, 45
HELD_OUT_SECONDS = 20.0
"""The last seconds of the capture never go into the library, so that evaluation there is
on motion the teacher (and a model trained on it) never saw."""


@dataclass(frozen=True)
class Phrase:
    """Source frames [start, end) of the capture; `stroke` is the speed peak inside."""

    start: int
    end: int
    stroke: int
    peak_speed: float


@dataclass(frozen=True)
class GestureStyle:
    """One speaker's gesturing, drawn per utterance: `energy` scales the gestures'
    amplitude about the capture's mean pose, `min_gap` (s) spaces strokes (longer gaps are
    longer rest holds), `tempo` is the mean playback rate of the capture, `rate_jitter`
    bounds the re-timing of phrases, `nod` is the head nod (degrees) on strong accents."""

    energy: float = 1.0
    min_gap: float = 0.9
    rate_jitter: float = 0.15
    nod: float = 4.0
    tempo: float = 1.0

    @classmethod
    def random(cls, rng: np.random.Generator, name: str = "conversational") -> "GestureStyle":
        """A style drawn from the ranges of the named style (GESTURE_STYLES)."""
        ranges = GESTURE_STYLES[name]
        return cls(**{k: float(rng.uniform(*v)) for k, v in ranges.items()})


GESTURE_STYLES: dict[str, dict[str, tuple[float, float]]] = {
    # few, small, slow strokes with long rest holds between them
    "calm": {"energy": (0.55, 0.7), "min_gap": (1.8, 2.6), "rate_jitter": (0.05, 0.1),
             "nod": (1.0, 3.0), "tempo": (0.75, 0.85)},
    # the capture's own manner (its figures are what the evaluation compares with): the
    # library's first 44 s move 1.1x as fast as the whole take, hence energy below 1
    "conversational": {"energy": (0.82, 1.02), "min_gap": (0.8, 1.3), "rate_jitter": (0.08, 0.2),
                       "nod": (2.0, 6.0), "tempo": (0.95, 1.05)},
    # large, frequent, quick strokes and short holds
    "animated": {"energy": (1.3, 1.5), "min_gap": (0.5, 0.75), "rate_jitter": (0.1, 0.2),
                 "nod": (4.0, 8.0), "tempo": (1.1, 1.2)},
}
"""Named gesture styles of the corpus: each utterance draws one, and its index in this
table is the style class a model is trained with."""


def _slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per-element spherical interpolation of (..., 4) unit quaternions; w broadcasts over
    (...) and may leave [0, 1] (extrapolation)."""
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    w = np.asarray(w)[..., None]
    small = sin < 1e-6
    a = np.where(small, 1.0 - w, np.sin((1.0 - w) * theta) / np.where(small, 1.0, sin))
    b = np.where(small, w, np.sin(w * theta) / np.where(small, 1.0, sin))
    q = a * q0 + b * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _angular_speed(quats: np.ndarray, joints: list[int]) -> np.ndarray:
    """(T,) summed rotation angle per frame of `joints`, frame t to t + 1 (last repeated)."""
    dot = np.abs(np.sum(quats[1:, joints] * quats[:-1, joints], axis=-1)).clip(0, 1)
    speed = (2 * np.arccos(dot)).sum(axis=1)
    return np.append(speed, speed[-1])


class GestureLibrary:
    """Phrases and calm (idle) stretches of one take, and sampling at fractional frames.

    With `lower` (the same take's hips and legs, frame for frame: `lower_body.build` of its
    BEAT2 SMPL-X capture) the library holds the whole body: the lower-body joints follow
    the `beat` ones, and the hips' translation is read beside them (`root`)."""

    def __init__(self, rotations: np.ndarray, lower: LowerBodyLibrary | None = None):
        if rotations.ndim != 3 or rotations.shape[1:] != (len(BEAT_JOINTS), 3) or len(rotations) < 60:
            raise DiffshegError(f"gesture capture must be (T >= 60, {len(BEAT_JOINTS)}, 3) axis-angle "
                                f"in the beat layout, got {rotations.shape}")
        self.lower = lower
        self.root = self.down = None
        if lower is not None:  # the lower body's last frame held where the capture is a few frames shorter
            frames = np.minimum(np.arange(len(rotations)), len(lower.rotations) - 1)
            rotations = np.concatenate([rotations, lower.rotations[frames]], axis=1)
            self.root = lower.translation[frames]
            spans = contacts(lower.rotations, lower.translation, lower.fps)
            down = np.zeros((len(lower.rotations), len(spans)))
            for k, side in enumerate(spans.values()):
                for a, b in side:
                    down[a:b + 1, k] = 1.0
            self.down = down[frames]
        self.quats = quaternion_sequence_continuous(axis_angle_to_quaternion(rotations))
        arms = [BEAT_JOINTS.index(n) for n in _ARM_JOINTS]
        self.speed = gaussian_filter1d(_angular_speed(self.quats, arms), 1.0)
        self.mean_pose = self._mean_pose()
        self.phrases = self._cut()
        peaks = np.array([p.peak_speed for p in self.phrases])
        self.gestures = [p for p in self.phrases if p.peak_speed >= np.median(peaks)]
        self.idle = [p for p in self.phrases if p.peak_speed <= np.percentile(peaks, 40)]

    def _mean_pose(self) -> np.ndarray:
        q = self.quats * np.where(np.sum(self.quats * self.quats[:1], -1, keepdims=True) < 0, -1, 1)
        m = q.mean(axis=0)
        return m / np.linalg.norm(m, axis=-1, keepdims=True)

    def _cut(self) -> list[Phrase]:
        minima, _ = find_peaks(-self.speed, distance=_MIN_PHRASE)
        bounds = [0] + [int(b) for b in minima] + [len(self.speed)]
        phrases = []
        margin = 3 * _FADE  # clips read past their phrase; keep that inside the take
        for a, b in zip(bounds[:-1], bounds[1:]):
            if _MIN_PHRASE <= b - a <= _MAX_PHRASE and margin <= a and b <= len(self.speed) - margin:
                stroke = a + int(np.argmax(self.speed[a:b]))
                phrases.append(Phrase(a, b, stroke, float(self.speed[stroke])))
        if len(phrases) < 4:
            raise DiffshegError("the gesture capture has too few phrases; is it a real talking take?")
        return phrases

    @property
    def n_frames(self) -> int:
        return len(self.quats)

    def sample(self, pos: np.ndarray) -> np.ndarray:
        """(len(pos), J, 4) quaternions at fractional source frames (clamped to the take)."""
        i0, w = self._between(pos)
        return _slerp(self.quats[i0], self.quats[i0 + 1], np.broadcast_to(w[:, None], (len(pos), self.quats.shape[1])))

    def root_step(self, pos: np.ndarray, rate: float) -> np.ndarray:
        """(len(pos), 3) the hips at fractional source frames played at `rate` source frames
        per output frame: x and z as the step to the next output frame, y as the height."""
        i0, w = self._between(pos)
        step = (self.root[i0 + 1] - self.root[i0]) * rate
        return np.stack([step[:, 0], (1 - w) * self.root[i0, 1] + w * self.root[i0 + 1, 1], step[:, 2]], axis=1)

    def contact(self, pos: np.ndarray) -> np.ndarray:
        """(len(pos), 2) 1 where the capture's right and left foot is in contact at the
        nearest source frame, else 0."""
        return self.down[np.clip(np.rint(pos).astype(int), 0, self.n_frames - 1)]

    def _between(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The source frame before each fractional frame (clamped to the take) and the weight of the next."""
        pos = np.clip(pos, 0, self.n_frames - 1)
        i0 = np.minimum(np.floor(pos).astype(int), self.n_frames - 2)
        return i0, pos - i0


@lru_cache(maxsize=2)
def load_library(path: str | None = None) -> GestureLibrary:
    """The library of a BEAT BVH take (default: the real take 2_scott_0_1_1) with its hips
    and legs: the package's lower-body library is cut from the BEAT2 capture of that take,
    frame for frame with the BVH and with the same last HELD_OUT_SECONDS left out. Another
    take has no lower body to go with it, so its library is the upper body alone."""
    from ...bvh import bvh_to_motion, read_bvh

    bvh = Path(path) if path else DEFAULT_MOCAP
    if not bvh.is_file():
        raise DiffshegError(f"gesture capture {bvh} not found: pass the BEAT take "
                            "2_scott_0_1_1.bvh (shared/data/beat) with --mocap")
    rotations = bvh_to_motion(read_bvh(bvh, fps=MOCAP_FPS)).rotations
    lower = LowerBodyLibrary.load() if bvh.name == DEFAULT_MOCAP.name else None
    return GestureLibrary(rotations[: len(rotations) - int(HELD_OUT_SECONDS * MOCAP_FPS)], lower)


@dataclass(frozen=True)
class _Clip:
    """Output frames from `out_start` on read source frame src_start + (u - out_start) * rate."""

    out_start: float
    src_start: float
    rate: float

    def source(self, u: np.ndarray) -> np.ndarray:
        return self.src_start + (u - self.out_start) * self.rate


def _pick(rng: np.random.Generator, lib: GestureLibrary, pool: list[Phrase], pose: np.ndarray | None,
          max_prep: float | None = None) -> Phrase:
    """A phrase from `pool`, preferring those that start near `pose` and whose preparation
    (start to stroke) fits in `max_prep` frames."""
    cand = [p for p in pool if max_prep is None or p.stroke - p.start <= max_prep] or pool
    if pose is None:
        return cand[int(rng.integers(len(cand)))]
    starts = lib.quats[[p.start for p in cand]]
    dist = (1 - np.abs(np.sum(starts * pose, axis=-1))).sum(axis=1)
    weights = np.exp(-dist / (np.median(dist) + 1e-9) * _POSE_MATCH)
    return cand[int(rng.choice(len(cand), p=weights / weights.sum()))]


def _timeline(lib: GestureLibrary, strokes: list[float], n_frames: int, fps: float,
              style: GestureStyle, rng: np.random.Generator) -> list[_Clip]:
    """Clips covering frames [0, n_frames): a gesture phrase per stroke time (frames), calm
    stretches where no stroke is due. Each clip runs until the next one starts (reading on
    in the capture); a phrase still running at the next one's preparation is cut short."""
    clips: list[_Clip] = []
    cursor, pose = 0.0, None
    speed = MOCAP_FPS / fps * style.tempo
    jitter = style.rate_jitter

    def fill_idle(until: float) -> None:
        nonlocal cursor, pose
        while until - cursor > 2 * _FADE:
            p = _pick(rng, lib, lib.idle, pose)
            rate = speed * float(rng.uniform(0.7, 1.0))
            clips.append(_Clip(cursor, p.start, rate))
            cursor = min(until, cursor + max((p.end - p.start) / rate, 2 * _FADE))
            pose = lib.sample(np.array([clips[-1].source(cursor)]))[0]

    for stroke in strokes:
        p = _pick(rng, lib, lib.gestures, pose, max_prep=(stroke - cursor) * speed * (1 + jitter))
        rate = speed * float(rng.uniform(1 - jitter, 1 + jitter))
        start = stroke - (p.stroke - p.start) / rate
        if clips and start < cursor:
            cursor = max(clips[-1].out_start + 2 * _FADE, start)
        fill_idle(start)
        clips.append(_Clip(cursor, p.stroke - (stroke - cursor) * rate, rate))
        cursor = stroke + (p.end - p.stroke) / rate
        pose = lib.sample(np.array([clips[-1].source(cursor)]))[0]
    fill_idle(n_frames + _FADE)
    return clips


def _render(clips: list[_Clip], n_frames: int, read: Callable[[_Clip, np.ndarray], np.ndarray],
            mix: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """(n_frames, ...): each frame reads its clip (`read(clip, frames)`); within _FADE frames
    of a cut it is `mix(a, b, w)` of the two clips meeting there, w the smoothstep of the fade."""
    u = np.arange(n_frames, dtype=np.float64)
    starts = np.array([c.out_start for c in clips])
    k = np.clip(np.searchsorted(starts, u, side="right") - 1, 0, len(clips) - 1)
    out = None
    for i, clip in enumerate(clips):
        sel = k == i
        if sel.any():
            values = read(clip, u[sel])
            out = np.empty((n_frames,) + values.shape[1:]) if out is None else out
            out[sel] = values
    for i in range(1, len(clips)):
        cut = clips[i].out_start
        sel = np.abs(u - cut) < _FADE
        if sel.any():
            x = (u[sel] - (cut - _FADE)) / (2 * _FADE)
            out[sel] = mix(read(clips[i - 1], u[sel]), read(clips[i], u[sel]), x * x * (3 - 2 * x))
    return out


def _render_quats(lib: GestureLibrary, clips: list[_Clip], n_frames: int) -> np.ndarray:
    """(n_frames, J, 4) rotations of the clips, slerped across each cut."""
    return _render(clips, n_frames, lambda clip, u: lib.sample(clip.source(u)),
                   lambda a, b, w: _slerp(a, b, np.broadcast_to(w[:, None], a.shape[:2])))


def _mix(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    return (1 - w[:, None]) * a + w[:, None] * b


def _render_root(lib: GestureLibrary, clips: list[_Clip], n_frames: int) -> np.ndarray:
    """(n_frames, 3) the hips' translation of the clips: their steps over the floor blended
    across each cut and summed, so the hips go on from where they are at every cut, and
    their height blended."""
    step = _render(clips, n_frames, lambda clip, u: lib.root_step(clip.source(u), clip.rate), _mix)
    floor = np.cumsum(step[:, [0, 2]], axis=0)
    return np.stack([floor[:, 0], step[:, 1], floor[:, 1]], axis=1)


def _render_contacts(lib: GestureLibrary, clips: list[_Clip], n_frames: int) -> dict[str, np.ndarray]:
    """Per foot ("right", "left"), (n_frames,) whether it is in contact: in the capture frames
    the clips read (the one weighing more across a cut). A foot is planted where the capture
    had it planted, even where a cross-fade would move it."""
    down = _render(clips, n_frames, lambda clip, u: lib.contact(clip.source(u)), _mix) >= 0.5
    return {"right": down[:, 0], "left": down[:, 1]}


def _nod(quats: np.ndarray, accents: list[Accent], fps: float, degrees: float) -> np.ndarray:
    """Nod the head (Neck1, and Neck by half) forward about its X axis on accents, keeping
    the mean head pitch of the capture (nods only forward would pitch the head down 2-3
    degrees on average)."""
    times = np.arange(len(quats)) / fps
    angle = np.zeros(len(quats))
    for a in accents:
        angle += a.strength * np.exp(-0.5 * ((times - a.time - 0.08) / 0.12) ** 2)
    angle = np.radians(degrees) * np.minimum(angle, 1.5)
    angle -= angle.mean()  # nods about the capture's own head posture, which they must not shift
    out = quats.copy()
    for name, share in (("Neck1", 1.0), ("Neck", 0.5)):
        j = BEAT_JOINTS.index(name)
        half = 0.5 * share * angle
        nod = np.stack([np.cos(half), np.sin(half), np.zeros_like(half), np.zeros_like(half)], axis=-1)
        out[:, j] = _quat_mul(quats[:, j], nod)
    return out


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) (w, x, y, z) quaternions."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def choose_strokes(accents: list[Accent], min_gap: float, rng: np.random.Generator) -> list[float]:
    """Accent times (s) that get a gesture stroke: strongest first, at least `min_gap` apart;
    weak accents are skipped at random."""
    chosen: list[float] = []
    for a in sorted(accents, key=lambda a: -a.strength):
        if rng.random() < 0.4 + 0.6 * a.strength and all(abs(a.time - c) >= min_gap for c in chosen):
            chosen.append(a.time)
    return sorted(chosen)


@dataclass(frozen=True)
class GestureTrack:
    """What the body teacher made: (T, J, 3) axis-angle rotations, the beat layout's 47
    joints and, from a whole-body library, the 9 of the lower body (lower_body.JOINTS)
    after them; the stroke times (s); and from a whole-body library the hips' (T, 3)
    translation as the clips move them (before lower_body.settle) and per foot whether the
    capture has it in contact."""

    rotations: np.ndarray
    strokes: list[float]
    root: np.ndarray | None = None
    contacts: dict[str, np.ndarray] | None = None


def gesture_rotations(accents: list[Accent], n_frames: int, fps: float, style: GestureStyle,
                      rng: np.random.Generator, library: GestureLibrary | None = None) -> GestureTrack:
    """The gestures (and with a whole-body library the lower body) of an utterance; the
    style's energy scales the upper body's gestures, never the legs, which stand as captured."""
    lib = library or load_library()
    strokes = choose_strokes(accents, style.min_gap, rng)
    clips = _timeline(lib, [t * fps for t in strokes], n_frames, fps, style, rng)
    quats = _render_quats(lib, clips, n_frames)
    energy = np.full(quats.shape[:2], style.energy)
    energy[:, len(BEAT_JOINTS):] = 1.0
    quats = _slerp(np.broadcast_to(lib.mean_pose, quats.shape), quats, energy)
    quats = _nod(quats, accents, fps, style.nod)
    rotations = quaternion_to_axis_angle(quats).astype(np.float32)
    if lib.root is None:
        return GestureTrack(rotations, strokes)
    return GestureTrack(rotations, strokes, _render_root(lib, clips, n_frames), _render_contacts(lib, clips, n_frames))
