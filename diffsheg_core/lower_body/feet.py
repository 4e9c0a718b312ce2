"""The feet on the canonical body: pinned where they landed over their contact spans
(`plant_feet`: the lower body cut from the capture, offline and live), or standing and
stepping by one causal rule (`FootSteps`, `step_feet`: a whole-body model's legs, offline
and live); either way each leg solved again by two-bone IK (`leg_ik`).
numpy only: it runs inside Blender.
"""

from __future__ import annotations

import math

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..rotations import axis_angle_to_matrix, convert, matrix_to_axis_angle
from .body import JOINTS, LEGS, MIN_CONTACT, _contacts, _offsets, _runs, _world
from .leg_ik import pin_goals, two_bone

EASE = 3                # frames over which a pin eases in and out
REACH_SLACK = 0.004     # m a pinned ankle may lie beyond the straight leg (IK stops 4 mm short)
STEP_AWAY = 0.22        # m the hip may sway away from over a standing foot before the foot steps
STEP_S = 0.33           # s a step takes, lift-off to landing
STEP_LIFT = 0.09        # m the ankle rises at a step's middle (the capture's moves lift it 8.2 cm, feet_figures)
STEP_REST_S = 0.8       # s a foot stands at least between two of its steps (unless the leg cannot reach)
MAX_DROP = 0.06         # m the hips may come down for a standing foot to be reached; further, it steps
DROP_SPEED = 0.15       # m/s the hips come down or rise again at most


def plant_feet(lower: np.ndarray, trans: np.ndarray, fps: float,
               down: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, dict]:
    """`lower` with each contact foot's ankle and orientation pinned over its span (eased in
    and out over EASE frames) by two-bone IK on each leg (leg_ik); returns it and the spans
    pinned. A span is pinned where and as its foot landed (its first MIN_CONTACT frames, so
    what is pinned never depends on how long the span goes on: the live stream pins the
    same); frames where the leg cannot reach that spot split it (the foot steps there).
    The contacts are the feet's low and slow stretches, or per foot the (T,) mask `down`
    (the teacher's, from the capture it reads)."""
    world = _world(lower, trans)
    spans = _contacts(world, fps) if down is None else \
        {side: [(a, b) for a, b in _runs(down[side]) if b - a + 1 >= MIN_CONTACT] for side in LEGS}
    pins = {side: _pins(world, side, spans[side]) for side in LEGS}
    return _solve(lower, world, _pin_goals(world, pins)), {side: [(a, b) for a, b, _, _ in p] for side, p in pins.items()}


def _pins(world: dict, side: str, spans: list[tuple[int, int]]) -> list:
    """leg_ik pins (first, last, ankle spot, foot rotation matrix) of one foot's contact spans."""
    up, _, foot = LEGS[side]
    return _leg_pins(side, world[foot][1], world[up][1], world[foot][0], spans)


def _leg_pins(side: str, ankle: np.ndarray, hip: np.ndarray, foot: np.ndarray, spans: list[tuple[int, int]]) -> list:
    """Pins of one leg's contact `spans` from its ankle and hip positions and foot quaternions."""
    return [(a, b, spot, convert(foot[a + MIN_CONTACT // 2], "quaternion", "matrix"))
            for span in spans for a, b, spot in _reachable(ankle, hip, span, _reach(side))]


@lru_cache(maxsize=None)
def _reach(side: str) -> float:
    """How far from the hip a pinned ankle may lie on that leg (thigh + shin + REACH_SLACK)."""
    off = _offsets()
    _, knee, shin = LEGS[side]
    return float(np.linalg.norm(off[knee]) + np.linalg.norm(off[shin]) + REACH_SLACK)


def _pinned(pins: dict[str, list], n: int) -> dict[str, np.ndarray]:
    """Per foot (n,) whether one of its `pins` (first, last, ...), in a hop's frames, holds it."""
    down = {side: np.zeros(n, bool) for side in LEGS}
    for side, side_pins in pins.items():
        for a, b, _, _ in side_pins:
            down[side][max(a, 0):max(b + 1, 0)] = True
    return down


def _pin_goals(world: dict, pins: dict[str, list]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per foot the ankle goals and foot rotations its `pins` ask for (leg_ik.pin_goals)."""
    goals = {}
    for side, (_, _, foot) in LEGS.items():
        rotation, ankle = world[foot]
        goal, goal_rot, _ = pin_goals(ankle, convert(rotation, "quaternion", "matrix"), pins[side], EASE)
        goals[side] = (goal, goal_rot)
    return goals


def _solve(lower: np.ndarray, world: dict, goals: dict[str, tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """`lower` with each leg solved again by two-bone IK so its ankle and foot follow the
    goals ((T, 3) ankle positions, (T, 3, 3) foot world rotations per foot)."""
    matrices = {name: (convert(q, "quaternion", "matrix"), pos) for name, (q, pos) in world.items()}
    off = _offsets()
    hips = matrices["Hips"][0]
    out = lower.copy()
    for side, (up, knee, foot) in LEGS.items():
        thigh, shin = np.linalg.norm(off[knee]), np.linalg.norm(off[foot])
        (thigh_rot, hip), (shin_rot, knee_pos), (foot_rot, ankle) = matrices[up], matrices[knee], matrices[foot]
        goal, goal_rot = goals[side]
        turn, bend = two_bone(hip, knee_pos, ankle, goal, thigh, shin, hips[:, :, 0])
        thigh_rot, shin_rot = turn @ thigh_rot, turn @ bend @ shin_rot
        for joint, parent, rotation in ((up, hips, thigh_rot), (knee, thigh_rot, shin_rot), (foot, shin_rot, goal_rot)):
            out[:, JOINTS.index(joint)] = matrix_to_axis_angle(np.transpose(parent, (0, 2, 1)) @ rotation)
    return out


def _reachable(ankle: np.ndarray, hip: np.ndarray, span: tuple[int, int], reach: float
               ) -> list[tuple[int, int, np.ndarray]]:
    """(first, last, spot) pins within `span`: where the foot landed (the ankle's median over
    the span's first MIN_CONTACT frames, so a pin never moves as its span is seen to go on,
    live), split (and each part pinned where it lands) where the hip is further from the
    spot than the leg reaches."""
    todo, done = [span], []
    for _ in range(3):
        later = []
        for a, b in todo:
            spot = np.median(ankle[a:a + MIN_CONTACT], axis=0)
            near = np.linalg.norm(spot - hip[a:b + 1], axis=-1) < reach
            if near.all():
                done.append((a, b, spot))
                continue
            later += [(a + x, a + y) for x, y in _runs(near) if y - x + 1 >= MIN_CONTACT]
        todo = later
    return sorted(done, key=lambda pin: pin[0])


# ---------------------------------------------------------------- standing and stepping

@dataclass
class _Stance:
    """One foot: where its ankle stands (or lands) and the foot's rotation there; while it
    steps, the frame the step began and where from."""

    spot: np.ndarray
    rotation: np.ndarray
    step: tuple[int, np.ndarray, np.ndarray] | None = None
    landed: int = -(10 ** 9)


class FootSteps:
    """Where a whole-body model's feet go, frame by frame: a foot stands where it landed,
    flat on the floor, until the hip has swayed STEP_AWAY past that spot (and the foot has
    stood STEP_REST_S), or the leg could reach it only with the hips lowered more than
    MAX_DROP; then it steps to where the model's own ankle is: lifted STEP_LIFT at the step's middle,
    moved over the floor while up, set down over STEP_S. One foot steps at a time. Never a
    glide: a foot is still or in the air. The hips come down as far as a standing foot
    needs to be reached (the knees bend), at most DROP_SPEED, and rise again as slowly.
    Causal (a frame depends on the frames before it only), so offline `plant` and live
    `PlantStream` place the feet by the same rule, and a hop's frames are final."""

    def __init__(self, fps: float):
        self.fps = fps
        self.step_frames = max(2, int(round(STEP_S * fps)))
        self.rest_frames = int(round(STEP_REST_S * fps))
        self.feet: dict[str, _Stance] = {}
        self.down: dict[str, list[np.ndarray]] = {side: [] for side in LEGS}  # each hop's standing flags
        self.drop = 0.0  # how far the hips are lowered now (m)
        self.n = 0

    def add(self, world: dict) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], np.ndarray]:
        """Per foot (n, 3) ankle goals and (n, 3, 3) foot rotations, and (n,) how far the
        hips come down, for the next n frames of `world` (the legs as made, `_world`)."""
        n = len(world["Hips"][1])
        goals = {side: (np.zeros((n, 3)), np.zeros((n, 3, 3))) for side in LEGS}
        down = {side: np.zeros(n, bool) for side in LEGS}
        drops = np.zeros(n)
        for k in range(n):
            t = self.n + k
            for side, (up, _, foot) in LEGS.items():
                ankle, hip = world[foot][1][k], world[up][1][k]
                here = self.feet.get(side)
                if here is None:
                    here = self.feet[side] = _Stance(_on_floor_at(ankle), _flat(side, world[foot][0][k]))
                if here.step is None and self._should_step(side, here, ankle, hip, t):
                    here.step = (t, here.spot, here.rotation)
                    here.spot, here.rotation = _on_floor_at(ankle), _flat(side, world[foot][0][k])
                goals[side][0][k], goals[side][1][k], down[side][k] = self._place(here, t)
            # a stepping foot's landing spot counts already: the hips are down by the time it lands
            need = max([_drop_to_reach(side, spot, world[up][1][k]) for side, (up, _, _) in LEGS.items()
                        for spot in (goals[side][0][k], self.feet[side].spot)] + [0.0])
            limit = DROP_SPEED / self.fps
            self.drop = float(np.clip(min(need, MAX_DROP), self.drop - limit, self.drop + limit))
            drops[k] = self.drop
            for side, (up, _, _) in LEGS.items():  # a foot the leg cannot reach is not standing, only stretched for
                if down[side][k] and _drop_to_reach(side, goals[side][0][k], world[up][1][k]) > self.drop + REACH_SLACK:
                    down[side][k] = False
        for side in LEGS:
            self.down[side].append(down[side])
        self.n += n
        return goals, drops

    def contacts(self) -> dict[str, list[tuple[int, int]]]:
        """Per foot the [first, last] frame spans it stood, of the frames placed so far (those
        of MIN_CONTACT frames or more, as `contacts` counts them)."""
        return {side: [(a, b) for a, b in _runs(np.concatenate(parts)) if b - a + 1 >= MIN_CONTACT] if parts else []
                for side, parts in self.down.items()}

    def _should_step(self, side: str, here: _Stance, ankle: np.ndarray, hip: np.ndarray, t: int) -> bool:
        if any(other.step is not None for name, other in self.feet.items() if name != side):
            return False
        if _drop_to_reach(side, here.spot, hip) > MAX_DROP:
            return True
        # the foot stays while the hip sways over it; it steps once the hip has left it far behind
        away = math.hypot(hip[0] - here.spot[0], hip[2] - here.spot[2])
        return away > STEP_AWAY and t - here.landed >= self.rest_frames

    def _place(self, here: _Stance, t: int) -> tuple[np.ndarray, np.ndarray, bool]:
        """The foot's ankle goal, rotation and whether it stands, at frame `t`."""
        if here.step is None:
            return here.spot, here.rotation, True
        first, start, start_rotation = here.step
        u = (t - first + 1) / self.step_frames
        along = _smoothstep((u - 0.15) / 0.7)  # over the floor mostly while the foot is up
        ankle = start + along * (here.spot - start)
        ankle[1] += STEP_LIFT * np.sin(np.pi * min(u, 1.0))
        turn = matrix_to_axis_angle(start_rotation.T @ here.rotation)
        rotation = start_rotation @ axis_angle_to_matrix(along * turn)
        if u >= 1.0:
            here.step, here.landed = None, t
        return ankle, rotation, u >= 1.0


def _drop_to_reach(side: str, ankle: np.ndarray, hip: np.ndarray) -> float:
    """How far the hip must come down for the leg to reach `ankle` (0: it does)."""
    reach = _reach(side) - REACH_SLACK
    across = math.hypot(hip[0] - ankle[0], hip[2] - ankle[2])  # per frame and foot: plain floats are faster
    if across >= reach:
        return np.inf
    return max(0.0, float(hip[1] - ankle[1] - math.sqrt(reach ** 2 - across ** 2)))


def _lowered(world: dict, drops: np.ndarray) -> dict:
    """`world` with every joint `drops` (T,) metres lower."""
    shift = np.zeros((len(drops), 3))
    shift[:, 1] = drops
    return {name: (rotation, position - shift) for name, (rotation, position) in world.items()}


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


@lru_cache(maxsize=1)
def _ankle_height() -> float:
    """The ankle's height above the floor on the canonical body standing flat."""
    world = _world(np.zeros((1, len(JOINTS), 3)), np.zeros((1, 3)))
    return float(world["RightFoot"][1][0, 1])


def _on_floor_at(ankle: np.ndarray) -> np.ndarray:
    """Where an ankle stands over the floor below `ankle`."""
    return np.array([ankle[0], _ankle_height(), ankle[2]])


def _flat(side: str, quaternion: np.ndarray) -> np.ndarray:
    """The foot's world rotation (from its world quaternion) flat on the floor: its turn
    about the vertical alone, that of its toes (ToeBase, ahead of the sole; not the
    fore-foot, which lies straight below the ankle and says nothing of where the toes point:
    issue 40, pigeon-toed feet)."""
    forward = _offsets()[f"{'Right' if side == 'right' else 'Left'}ToeBase"]
    now = convert(quaternion, "quaternion", "matrix") @ forward
    angle = np.arctan2(now[0], now[2]) - np.arctan2(forward[0], forward[2])
    return axis_angle_to_matrix(np.array([0.0, angle, 0.0]))


def step_feet(lower: np.ndarray, trans: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """`lower` and `trans` with the feet standing and stepping (`FootSteps`), by two-bone IK
    on each leg and the hips lowered as far as a standing foot needs; and the spans each
    foot stands."""
    steps = FootSteps(fps)
    lower, trans = _step(steps, lower, trans)
    return lower, trans, steps.contacts()


def _step(steps: FootSteps, lower: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The next frames of `steps`: the legs solved onto its goals, the hips lowered."""
    world = _world(lower, trans)
    goals, drops = steps.add(world)
    lowered = trans.copy()
    lowered[:, 1] -= drops
    return _solve(lower, _lowered(world, drops), goals), lowered
