"""The lower body live, a hop of frames at a time, each frame final as it comes:
`LowerBodyStream` cuts it from the capture to go with a `beat` model's upper body (as
`capture.add_lower_body`), `PlantStream` plants a whole-body model's own legs (as
`capture.plant`). numpy only: it runs inside Blender.
"""

from __future__ import annotations

import numpy as np

from ..kinematics import wrist_positions
from ..motion import Motion
from ..rotations import axis_angle_to_quaternion, quaternion_sequence_continuous, quaternion_to_axis_angle
from .body import JOINTS, LEGS, MIN_CONTACT, _check_whole_body, _down, _feet, _lowest, _runs, _world, lower_rotations
from .capture import (DRIFT_S, ENERGY_S, GROUND_S, MODEL_SMOOTH_S, LowerBodyLibrary, _library_at, _on_floor,
                      _Planner)
from .feet import EASE, FootSteps, _leg_pins, _pin_goals, _pinned, _solve, _step

LIVE_LEASH = 0.5        # live: the share of the hips' distance from the capture's centre each segment takes back


def _no_frames() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """What a live lower-body stream returns for a hop of no frames."""
    return np.zeros((0, len(JOINTS), 3)), np.zeros((0, 3)), {side: np.zeros(0, bool) for side in LEGS}


class LowerBodyStream:
    """The lower body of a live upper body, a hop of frames at a time, with no frame waiting
    for it: the hips and legs are planned about two seconds ahead (a cross-fade, the floor's
    smoothing and a contact's ease), so a hop's frames are final when its upper body arrives.

    As offline (`add_lower_body`): segments of the capture cut by motion matching and
    cross-faded, the translation kept within the capture's range, the body on the floor
    and each contact foot pinned where it landed with two-bone IK. What differs, because
    the future is unknown: a segment matches the arms' energy over the last 2 * ENERGY_S
    seconds emitted (so the legs follow the arms about a segment late), and the hips' drift
    is taken back at each segment (LIVE_LEASH of the way to the capture's centre) instead of
    filtered out afterwards. Work per hop is bounded: the IK solves only the hop's frames."""

    def __init__(self, fps: float, seed: int, library: LowerBodyLibrary | None = None):
        self.library = _library_at(fps, library)
        self.fps = fps
        self._planner = _Planner(self.library, seed)
        self._speed: list[float] = []            # wrist speed of every frame emitted
        self._wrists: np.ndarray | None = None   # the last frame's wrists
        self._floored = np.zeros((0, 3))        # the hips' translation, on the floor, for final planned frames
        # per foot, over the same frames: ankle and hip positions, foot quaternions, and
        # whether the foot is low and slow (a contact)
        self._feet = {side: {"ankle": np.zeros((0, 3)), "hip": np.zeros((0, 3)), "foot": np.zeros((0, 4)),
                             "down": np.zeros(0, bool)} for side in LEGS}
        self.lower = np.zeros((0, len(JOINTS), 3))  # what was emitted
        self.trans = np.zeros((0, 3))

    def add(self, upper: Motion) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """(n, 9, 3) lower-body rotations, (n, 3) hips translation and per foot (n,) whether
        it is pinned (in contact) for the next n frames, whose upper body is `upper` (the
        stream's next n frames)."""
        first, n = len(self.lower), upper.n_frames
        if not n:
            return _no_frames()
        self._hear_arms(upper)
        energy = float(np.mean(self._speed[-int(2 * ENERGY_S * self.fps):]))
        margin = int(np.ceil(3 * GROUND_S * self.fps))  # smooth_frames' reach at the floor's sigma
        need = first + n + EASE + MIN_CONTACT  # a span starting within EASE of the hop eases in over it
        while len(self._planner.rotations) - self._planner.fade - margin < need:
            self._planner.add(lambda t0, span: energy, leash=LIVE_LEASH)
        self._floor(len(self._planner.rotations) - self._planner.fade, margin)
        hop = slice(first, first + n)
        lower = quaternion_to_axis_angle(self._planner.rotations[hop])
        world = _world(lower, self._floored[hop])
        pins = {side: self._pins(side, first) for side in LEGS}
        lower = _solve(lower, world, _pin_goals(world, pins))
        self.lower = np.concatenate([self.lower, lower])
        self.trans = np.concatenate([self.trans, self._floored[hop]])
        return lower, self._floored[hop].copy(), _pinned(pins, n)

    def contacts(self) -> dict[str, list[tuple[int, int]]]:
        """Per foot the [first, last] spans pinned so far (frames emitted)."""
        n = len(self.lower)
        return {side: [(a, min(b, n - 1)) for a, b, _, _ in self._pins(side, 0) if a < n] for side in LEGS}

    def _hear_arms(self, upper: Motion) -> None:
        wrists = wrist_positions(upper)
        before = wrists[:1] if self._wrists is None else self._wrists[None]
        steps = np.diff(np.concatenate([before, wrists]), axis=0)
        self._speed += list(np.linalg.norm(steps, axis=-1).mean(axis=-1) * self.fps)
        self._wrists = wrists[-1]

    def _floor(self, planned: int, margin: int) -> None:
        """Set the planned frames on the floor up to `planned` - `margin` (the floor's
        smoothing then reaches only planned frames, so it is final) and find their contacts."""
        done, end = len(self._floored), planned - margin
        if end <= done:
            return
        lo = max(0, done - margin)
        raw = np.clip(self._planner.trans[lo:planned], self.library.translation_low, self.library.translation_high)
        lower = quaternion_to_axis_angle(self._planner.rotations[lo:planned])
        floored = _on_floor(lower, raw, self.fps)[done - lo:end - lo]
        self._floored = np.concatenate([self._floored, floored])
        world = _world(lower[done - lo:end - lo], floored)
        for side, (ankle, sole) in _feet(world).items():
            up, _, foot = LEGS[side]
            track = self._feet[side]
            new = {"ankle": ankle, "hip": world[up][1], "foot": world[foot][0],
                   "down": _down(ankle, sole, self.fps, track["ankle"][-1:] if len(track["ankle"]) else None)}
            self._feet[side] = {key: np.concatenate([track[key], new[key]]) for key in track}

    def _pins(self, side: str, first: int) -> list:
        """The foot's pins that reach frame `first` - EASE or later, in frames from `first`."""
        track = self._feet[side]
        spans = [(a, b) for a, b in _runs(track["down"]) if b - a + 1 >= MIN_CONTACT and b + EASE >= first]
        return [(a - first, b - first, spot, rotation)
                for a, b, spot, rotation in _leg_pins(side, track["ankle"], track["hip"], track["foot"], spans)]


class PlantStream:
    """`plant` live: a whole-body model's own hips and legs, a hop of frames at a time, each
    frame final as it comes (no frame waits for later ones).

    As offline: low-passed, the hips' drift taken out about the capture's centre and kept
    within its range, the body on the floor, the feet standing or stepping by offline's rule
    (`FootSteps`, which looks back only) with two-bone IK. What differs, because the future
    is unknown: the filters look back only (the legs' Gaussian, offline's MODEL_SMOOTH_S, is
    centred two sigma back, so the legs follow the arms 0.4 s late; DRIFT_S and GROUND_S are
    one-pole time constants)."""

    def __init__(self, fps: float, library: LowerBodyLibrary | None = None):
        self.library = _library_at(fps, library)
        self.fps = fps
        # the legs' low-pass: offline's Gaussian over the frames up to the newest, centred 2
        # sigma back (so the legs follow the arms that late); one-pole gains per frame for the
        # hips' drift and the floor
        sigma = MODEL_SMOOTH_S * fps
        lags = np.arange(int(np.ceil(4 * sigma)) + 1)[::-1]  # oldest first
        self._window = np.exp(-0.5 * ((lags - 2 * sigma) / sigma) ** 2)
        self._gain = {name: 1.0 - np.exp(-1.0 / (tau * fps)) for name, tau in (("drift", DRIFT_S), ("floor", GROUND_S))}
        self._q: list[np.ndarray] = []       # the last frames' (9, 4) quaternions, as the model made them
        self._t: list[np.ndarray] = []       # ... and (3,) translations
        self._drift: np.ndarray | None = None  # the hips' slow wander over the floor (x, z)
        self._floor: float | None = None       # the lowest foot point's smoothed height
        self._steps = FootSteps(fps)
        self._emitted: list[tuple[np.ndarray, np.ndarray]] = []  # each hop's legs and translation

    @property
    def lower(self) -> np.ndarray:
        """(T, 9, 3) every frame's hips and legs emitted so far."""
        return np.concatenate([lower for lower, _ in self._emitted]) if self._emitted else np.zeros((0, len(JOINTS), 3))

    @property
    def trans(self) -> np.ndarray:
        """(T, 3) every frame's hips translation emitted so far."""
        return np.concatenate([trans for _, trans in self._emitted]) if self._emitted else np.zeros((0, 3))

    def add(self, part: Motion) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """(n, 9, 3) hips and legs, (n, 3) hips translation and per foot (n,) whether it
        stands, for the next n frames `part` holds as the model made them (its hips, legs and
        root translation)."""
        if not part.n_frames:
            return _no_frames()
        _check_whole_body(part)
        lower, trans = _step(self._steps, *self._smoothed(lower_rotations(part),
                                                          part.root_translation.astype(np.float64)))
        self._emitted.append((lower, trans))
        return lower, trans, {side: flags[-1] for side, flags in self._steps.down.items()}

    def contacts(self) -> dict[str, list[tuple[int, int]]]:
        """Per foot the [first, last] spans it stood, of the frames emitted."""
        return self._steps.contacts()

    def _smoothed(self, lower: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The hop's hips and legs low-passed, drift taken out, within range and on the floor."""
        g, weights = self._gain, self._window
        out_q, out_t = np.zeros(lower.shape[:2] + (4,)), np.zeros_like(trans)
        # each frame's quaternions in the hemisphere of the frame before (across hops too)
        before = np.array(self._q[-1:]).reshape(-1, len(JOINTS), 4)
        quats = quaternion_sequence_continuous(np.concatenate([before, axis_angle_to_quaternion(lower)]))[len(before):]
        for i, (q, t) in enumerate(zip(quats, trans)):
            self._q, self._t = (self._q + [q])[-len(weights):], (self._t + [t])[-len(weights):]
            w = weights[-len(self._q):] / weights[-len(self._q):].sum()
            mixed = np.einsum("k,kjc->jc", w, np.array(self._q))
            out_q[i] = mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)
            out_t[i] = w @ np.array(self._t)
            self._drift = out_t[i, [0, 2]].copy() if self._drift is None else \
                self._drift + g["drift"] * (out_t[i, [0, 2]] - self._drift)
            out_t[i, [0, 2]] += self.library.centre - self._drift
        smoothed = quaternion_to_axis_angle(out_q)
        out_t = np.clip(out_t, self.library.translation_low, self.library.translation_high)
        for i, height in enumerate(_lowest(_world(smoothed, out_t))):
            self._floor = height if self._floor is None else self._floor + g["floor"] * (height - self._floor)
            out_t[i, 1] -= self._floor
        return smoothed, out_t
