"""The lower body: hips (rotation and translation) and legs under the generated upper body,
with the feet planted.

A whole-body model (layout `beat_body`, with a lower-body branch: the bundled model) makes
the hips, legs and the hips' translation itself: `plant` low-passes them, keeps the hips
within the real capture's range and plants the contact feet (live, `PlantStream` does so as
the frames come). For a model whose layout stops at the waist (`beat`: v8 and the official
BEAT checkpoint), this module adds what a standing talker's hips and legs do: weight shifts,
sway and turns cut from the real full-body capture of BEAT2 take 2_scott_0_1_1 (SMPL-X,
with root translation), stored beside the model (`assets/lower_body.npz`, a few thousand
numbers). That flow is one way, as DiffSHEG's
expression-to-gesture flow: the upper body the model made drives the lower body, never
the reverse, so the upper body and face are the model's to the bit.

The lower body is cut from that capture as the teacher's gestures are cut from the BEAT
take: motion matching. The take is built segment by segment (1.5-4 s, drawn with the
generation's seed); each segment is the stretch of the capture (less its last 20 s, held
out as the gesture material is) whose arm energy (wrist speed, layout-free, `kinematics`)
best matches the generated arms' over the same time and whose first pose best continues
the last one, chosen at random among the few best; segments are cross-faded over half a
second and the hips' translation continues across each join. So real weight shifts,
sways, turns and steps come with the gestures that go with them.

Feet: on the BEAT skeleton's legs (the canonical body: x left, y up, z forward; legs
straight down at rest) each foot is in contact while it is low and slow; within a contact
span the ankle's position and the foot's orientation are pinned where the foot landed
(eased in and out over a few frames) and each leg is solved again with two-bone IK, so a
contact foot does not slide. The hips' translation is kept within the capture's range.

Live, `LowerBodyStream` does the same a hop of frames at a time, planned ahead so that no
frame waits for it (see its docstring for what it cannot know that offline does).
numpy only: it runs inside Blender.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Callable
from pathlib import Path

import numpy as np

from .errors import DiffshegError
from .kinematics import rest_offsets, wrist_positions
from .leg_ik import pin_goals, two_bone
from .motion import Motion, smooth_frames
from .rigs import BEAT_LOWER_JOINTS
from .rotations import (axis_angle_to_matrix, axis_angle_to_quaternion, convert, matrix_to_axis_angle,
                        quaternion_conjugate,
                        quaternion_product, quaternion_sequence_continuous, quaternion_to_axis_angle,
                        resample_positions, resample_weights, slerp_resample)

JOINTS = BEAT_LOWER_JOINTS
"""The joints added to a `beat` Motion, in its BEAT skeleton names."""
SMPLX_INDEX = (0, 2, 5, 8, 11, 1, 4, 7, 10)  # pelvis, right hip, knee, ankle, foot, then left
LEGS = {"right": ("RightUpLeg", "RightLeg", "RightFoot"), "left": ("LeftUpLeg", "LeftLeg", "LeftFoot")}
ASSET = Path(__file__).with_name("assets") / "lower_body.npz"
LAYOUTS = ("beat",)

HELD_OUT_S = 20.0    # the capture's last seconds, left out of the fit (as the gesture material)
SEGMENT = (1.5, 4.0)  # seconds: the shortest and longest segment cut from the capture
FADE_S = 0.5         # seconds of cross-fade between segments
CHOICES = 4          # a segment is drawn among this many best matches
DRIFT_S = 4.0        # Gaussian sigma (s) of the hips' slow drift across joins, taken out
GROUND_S = 0.25     # Gaussian sigma (s) of the lowest foot point the body is lowered onto the floor by
TRAVEL_M = 0.15      # metres a segment's hips travel that cost as much as a poor energy match
ENERGY_S = 1.0       # Gaussian sigma of the arms' energy the segments are matched on
CONTACT_HEIGHT = 0.03   # m above the floor a contact foot's sole may be
CONTACT_SPEED = 0.15    # m/s a contact foot's ankle may move before pinning
EASE = 3                # frames over which a pin eases in and out
MIN_CONTACT = 4         # frames: a shorter low, slow stretch is a step, not a contact
REACH_SLACK = 0.004     # m a pinned ankle may lie beyond the straight leg (IK stops 4 mm short)
LIVE_LEASH = 0.5        # live: the share of the hips' distance from the capture's centre each segment takes back
MODEL_SMOOTH_S = 0.2    # Gaussian sigma (s) a whole-body model's hips and legs are low-passed by before planting
STEP_AWAY = 0.22        # m the hip may sway away from over a standing foot before the foot steps
STEP_S = 0.33           # s a step takes, lift-off to landing
STEP_LIFT = 0.09        # m the ankle rises at a step's middle (the capture's moves lift it 8.2 cm, feet_figures)
STEP_REST_S = 0.8       # s a foot stands at least between two of its steps (unless the leg cannot reach)
MAX_DROP = 0.06         # m the hips may come down for a standing foot to be reached; further, it steps
DROP_SPEED = 0.15       # m/s the hips come down or rise again at most


@lru_cache(maxsize=None)
def _offsets() -> dict[str, np.ndarray]:
    """The BEAT skeleton's joint offsets in metres (the canonical body)."""
    return {name: offset / 100.0 for name, offset in rest_offsets("beat").items()}


def _hips_height() -> float:
    """Rest height of the hips above the floor (the sole, at the fore-foot) in metres."""
    return float(-sum(_offsets()[j][1] for j in ("RightLeg", "RightFoot", "RightForeFoot")))


def canonical_leg_length(hips_height: float) -> float:
    """Thigh and shin (hip to ankle) of the canonical body in proportion to one whose hips
    rest `hips_height` metres above the floor (a Motion's meta "hips_height")."""
    off = _offsets()
    return float(hips_height * (np.linalg.norm(off["RightLeg"]) + np.linalg.norm(off["RightFoot"])) / _hips_height())


@dataclass(frozen=True)
class LowerBodyLibrary:
    """The capture's lower body to cut segments from, at `fps`: rotations (N, 9, 3),
    hips translation (N, 3, metres about the standing hips) and arm energy (N,)."""

    rotations: np.ndarray
    translation: np.ndarray
    energy: np.ndarray
    fps: float

    def save(self, path: Path) -> Path:
        np.savez(path, rotations=self.rotations.astype(np.float32), translation=self.translation.astype(np.float32),
                 energy=self.energy.astype(np.float32), fps=np.float64(self.fps))
        return path

    @classmethod
    def load(cls, path: Path = ASSET) -> "LowerBodyLibrary":
        try:
            with np.load(path) as z:
                return cls(z["rotations"].astype(np.float64), z["translation"].astype(np.float64),
                           z["energy"].astype(np.float64), float(z["fps"]))
        except (OSError, KeyError, ValueError) as exc:
            raise DiffshegError(f"the lower-body library {path} cannot be read ({exc}): reinstall the package, "
                                "or generate with upper_body_only") from None

    @property
    def translation_low(self) -> np.ndarray:
        return self.translation.min(axis=0)

    @property
    def translation_high(self) -> np.ndarray:
        return self.translation.max(axis=0)

    @property
    def centre(self) -> np.ndarray:
        """(2,) where the capture's hips stand on average, x and z."""
        return self.translation[:, [0, 2]].mean(axis=0)


# ---------------------------------------------------------------- the capture

def read_capture(path: Path, fps: float) -> tuple[np.ndarray, np.ndarray, Motion]:
    """A BEAT2 SMPL-X take as (T, 9, 3) lower-body rotations, (T, 3) hips translation
    (metres, canonical axes, about the standing hips) and its upper body as a Motion, at
    `fps`, turned so that the speaker faces +z on average."""
    from .rigs import SMPLX_JOINTS

    with np.load(path, allow_pickle=True) as z:
        poses, trans, rate = z["poses"].astype(np.float64), z["trans"].astype(np.float64), float(z["mocap_frame_rate"])
    joints = poses.reshape(len(poses), -1, 3)
    n = len(resample_positions(len(poses), rate, fps))
    rotations = slerp_resample(joints, rate, fps, n)
    trans = resample_weights(trans, rate, fps, "linear", n)
    # face +z on average: turn the world about y by minus the pelvis's mean heading
    forward = _apply(axis_angle_to_quaternion(rotations[:, 0]), np.array([0.0, 0.0, 1.0]))
    heading = float(np.arctan2(forward[:, 0].mean(), forward[:, 2].mean()))
    turn = np.array([np.cos(-heading / 2), 0.0, np.sin(-heading / 2), 0.0])
    rotations[:, 0] = quaternion_to_axis_angle(quaternion_product(turn, axis_angle_to_quaternion(rotations[:, 0])))
    trans = _apply(np.broadcast_to(turn, (n, 4)), trans)
    lower = rotations[:, list(SMPLX_INDEX)]
    # the hips upright on average (the upper body sits on them): their mean tilt goes to the
    # thighs, whose world orientation is unchanged
    q = quaternion_sequence_continuous(axis_angle_to_quaternion(lower))
    tilt = q[:, 0].mean(axis=0)
    tilt /= np.linalg.norm(tilt)
    q[:, 0] = quaternion_product(q[:, 0], quaternion_conjugate(tilt)[None])
    for thigh in ("RightUpLeg", "LeftUpLeg"):
        q[:, JOINTS.index(thigh)] = quaternion_product(tilt[None], q[:, JOINTS.index(thigh)])
    lower = quaternion_to_axis_angle(q)
    upper = Motion(fps=fps, rig="smplx", joint_names=list(SMPLX_JOINTS[:len(rotations[0])]), rotations=rotations,
                   face_names=[], face=np.zeros((n, 0)))
    # about the standing hips: x and z about their mean; y from the floor (the soles' low
    # point over the take) less the canonical body's standing hips height
    soles = foot_positions(lower, np.zeros((n, 3)))  # with the hips at their standing height
    lowest = np.minimum(soles["right"][1][:, 1], soles["left"][1][:, 1])
    floor = np.percentile(trans[:, 1] + lowest, 5)
    trans = np.stack([trans[:, 0] - trans[:, 0].mean(), trans[:, 1] - floor,
                      trans[:, 2] - trans[:, 2].mean()], axis=1)
    return lower, trans, upper


def arm_energy(motion: Motion) -> np.ndarray:
    """(T,) the wrists' speed (arm lengths/s), smoothed: what drives the hips."""
    wrists = wrist_positions(motion)
    speed = np.linalg.norm(np.diff(wrists, axis=0, prepend=wrists[:1]), axis=-1).mean(axis=-1) * motion.fps
    return smooth_frames(speed[:, None], ENERGY_S * motion.fps)[:, 0]


def build(path: Path, fps: float = 15.0) -> LowerBodyLibrary:
    """The lower-body library of a BEAT2 SMPL-X take, less its last HELD_OUT_S seconds."""
    lower, trans, upper = read_capture(path, fps)
    keep = len(lower) - int(HELD_OUT_S * fps)
    if keep < 4 * SEGMENT[1] * fps:
        raise DiffshegError(f"{path} holds {len(lower) / fps:.1f} s: the lower body needs at least "
                            f"{4 * SEGMENT[1] + HELD_OUT_S:.0f} s of capture")
    return LowerBodyLibrary(lower[:keep], trans[:keep], arm_energy(upper)[:keep], fps)


def _apply(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors `v` (..., 3) by quaternions `q` (..., 4), broadcast."""
    v4 = np.concatenate([np.zeros(np.broadcast_shapes(q.shape[:-1], v.shape[:-1]) + (1,)),
                         np.broadcast_to(v, np.broadcast_shapes(q.shape[:-1], v.shape[:-1]) + (3,))], axis=-1)
    return quaternion_product(quaternion_product(q, v4), quaternion_conjugate(q))[..., 1:]


# ---------------------------------------------------------------- the canonical body's legs

def _world(lower: np.ndarray, trans: np.ndarray) -> dict:
    """World rotations (T, 4) and positions (T, 3) of every lower joint, the fore-foot
    (sole) and the toe's end, on the canonical body standing on the floor y = 0."""
    off = _offsets()
    q = axis_angle_to_quaternion(lower)
    hips = q[:, JOINTS.index("Hips")]
    trans = trans + np.array([0.0, _hips_height(), 0.0])  # the floor at y = 0
    out = {"Hips": (hips, trans)}
    for side, prefix in (("right", "Right"), ("left", "Left")):
        rot, pos = hips, trans
        for joint in (f"{prefix}UpLeg", f"{prefix}Leg", f"{prefix}Foot"):
            pos = pos + _apply(rot, off[joint])
            rot = quaternion_product(rot, q[:, JOINTS.index(joint)])
            out[joint] = (rot, pos)
        sole = pos + _apply(rot, off[f"{prefix}ForeFoot"])
        toe_rot = quaternion_product(rot, q[:, JOINTS.index(f"{prefix}ToeBase")])
        toe = sole + _apply(rot, off[f"{prefix}ToeBase"])
        out[f"{prefix}Sole"] = (rot, sole)
        out[f"{prefix}ToeEnd"] = (toe_rot, toe + _apply(toe_rot, off[f"{prefix}ToeBaseEnd"]))
    return out


def foot_positions(lower: np.ndarray, trans: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{"right"/"left": ((T, 3) ankle, (T, 3) sole)} world positions on the canonical body."""
    return _feet(_world(lower, trans))


def _feet(world: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {side: (world[f"{p}Foot"][1], world[f"{p}Sole"][1]) for side, p in (("right", "Right"), ("left", "Left"))}


def contacts(lower: np.ndarray, trans: np.ndarray, fps: float) -> dict[str, list[tuple[int, int]]]:
    """Per foot, the [first, last] frame spans in which it is on the floor: its sole within
    CONTACT_HEIGHT of the floor (y = 0) and its ankle slower than CONTACT_SPEED."""
    return _contacts(_world(lower, trans), fps)


def _contacts(world: dict, fps: float) -> dict[str, list[tuple[int, int]]]:
    return {side: [(a, b) for a, b in _runs(_down(ankle, sole, fps)) if b - a + 1 >= MIN_CONTACT]
            for side, (ankle, sole) in _feet(world).items()}


def _down(ankle: np.ndarray, sole: np.ndarray, fps: float, before: np.ndarray | None = None) -> np.ndarray:
    """(T,) whether the foot is on the floor: its sole within CONTACT_HEIGHT of it and its
    ankle slower than CONTACT_SPEED since the frame before (`before`: the ankle then, (1, 3);
    None, the first frame counts as still)."""
    speed = np.linalg.norm(np.diff(ankle, axis=0, prepend=ankle[:1] if before is None else before), axis=-1) * fps
    return (sole[:, 1] < CONTACT_HEIGHT) & (speed < CONTACT_SPEED)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    return [(int(a), int(b) - 1) for a, b in zip(edges[::2], edges[1::2])]


def foot_skating(lower: np.ndarray, trans: np.ndarray, fps: float, height: float = 0.05,
                 slide: float = 0.025) -> float:
    """The foot-skating ratio (as SpeechAct and GMD report it): the share of frames in which a
    foot whose sole is below `height` m moves more than `slide` m per 1/30 s on the floor."""
    ratios = []
    for ankle, sole in foot_positions(lower, trans).values():
        step = np.linalg.norm(np.diff(sole[:, [0, 2]], axis=0), axis=-1) * fps / 30.0
        low = (sole[1:, 1] < height) & (sole[:-1, 1] < height)
        ratios.append(low & (step > slide))
    return float(np.mean(np.any(ratios, axis=0)))


def figures(lower: np.ndarray, trans: np.ndarray, fps: float) -> dict[str, float]:
    """What legs are measured by against the capture: the hips' sway speed (m/s, over the
    floor) and range (m, the wider of x and z), the knees' bend range (degrees, both knees'
    mean) and the foot-skating ratio."""
    knees = np.degrees(np.linalg.norm(lower[:, [JOINTS.index("RightLeg"), JOINTS.index("LeftLeg")]], axis=-1))
    return {"sway speed": float(np.linalg.norm(np.diff(trans[:, [0, 2]], axis=0), axis=-1).mean() * fps),
            "sway range": float(np.ptp(trans[:, [0, 2]], axis=0).max()),
            "knee range": float(np.ptp(knees, axis=0).mean()),
            "skating": foot_skating(lower, trans, fps)}


FEET_LOW = 0.02        # m above its lowest height an ankle counts as low (SpeechAct's skating measure)
FEET_STILL = 0.05      # m/s under which a low ankle counts as in contact
FEET_MOVE = 0.15       # m/s over which an ankle counts as moving (a step or a glide)


def feet_figures(lower: np.ndarray, trans: np.ndarray, fps: float) -> dict[str, float]:
    """`ankle_figures` of the canonical body's ankles."""
    return ankle_figures([ankle for ankle, _ in foot_positions(lower, trans).values()], fps)


def ankle_figures(ankles: list[np.ndarray], fps: float, up: int = 1) -> dict[str, float]:
    """What a viewer sees of the feet, from each ankle's (T, 3) world positions in metres
    (`up`: the vertical axis, 1 here, 2 in Blender), averaged over the feet: `skating` the
    mean horizontal speed (m/s) of an ankle over the frames it is within FEET_LOW of its
    lowest height (SpeechAct's measure), `contact` the share of frames it is that low and
    slower than FEET_STILL, `moves per minute` the stretches it moves faster than
    FEET_MOVE, and `lift` the median of those moves' highest ankle point above its lowest (m)."""
    skating, contact, moves, lifts = [], [], 0, []
    floor = [axis for axis in range(3) if axis != up]
    for ankle in ankles:
        height = ankle[:, up] - ankle[:, up].min()
        step = np.diff(ankle, axis=0, prepend=ankle[:1]) * fps
        across, speed = np.linalg.norm(step[:, floor], axis=-1), np.linalg.norm(step, axis=-1)
        low = height < FEET_LOW
        skating.append(float(across[low].mean()) if low.any() else 0.0)
        contact.append(float(np.mean(low & (speed < FEET_STILL))))
        runs = _runs(across > FEET_MOVE)
        moves += len(runs)
        lifts += [float(height[max(a - 1, 0):b + 2].max()) for a, b in runs]
    return {"skating": float(np.mean(skating)), "contact": float(np.mean(contact)),
            "moves per minute": moves / (len(ankles[0]) / fps / 60.0),
            "lift": float(np.median(lifts)) if lifts else 0.0}


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
    flat on the floor, until the model's own ankle has wandered STEP_AWAY from that spot
    (and the foot has stood STEP_REST_S), or the leg could reach it only with the hips
    lowered more than MAX_DROP; then it steps there: lifted STEP_LIFT at the step's middle,
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
                rotation = _flat(side, convert(world[foot][0][k], "quaternion", "matrix"))
                here = self.feet.setdefault(side, _Stance(_on_floor_at(ankle), rotation))
                if here.step is None and self._should_step(side, here, ankle, hip, t):
                    here.step = (t, here.spot, here.rotation)
                    here.spot, here.rotation = _on_floor_at(ankle), rotation
                goals[side][0][k], goals[side][1][k], down[side][k] = self._place(here, t)
            # a stepping foot's landing spot counts already: the hips are down by the time it lands
            need = max([_drop_to_reach(side, spot, world[up][1][k]) for side, (up, _, _) in LEGS.items()
                        for spot in (goals[side][0][k], self.feet[side].spot)] + [0.0])
            limit = DROP_SPEED / self.fps
            self.drop = float(np.clip(min(need, MAX_DROP), self.drop - limit, self.drop + limit))
            drops[k] = self.drop
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
        away = np.linalg.norm((hip - here.spot)[[0, 2]])
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
    across = np.linalg.norm((hip - ankle)[[0, 2]])
    if across >= reach:
        return np.inf
    return max(0.0, float(hip[1] - ankle[1] - np.sqrt(reach ** 2 - across ** 2)))


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


def _flat(side: str, rotation: np.ndarray) -> np.ndarray:
    """The foot's world rotation flat on the floor: its turn about the vertical alone."""
    forward = _offsets()[f"{'Right' if side == 'right' else 'Left'}ForeFoot"]
    now = rotation @ forward
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


# ---------------------------------------------------------------- generating

class _Planner:
    """Cuts segments from the library one after another: each the stretch (SEGMENT seconds,
    drawn) whose arm energy best matches the energy asked for and whose first pose best
    continues the last, chosen at random among the CHOICES best, cross-faded over FADE_S
    with the hips going on from where they are. Offline and live lower bodies share it."""

    def __init__(self, library: LowerBodyLibrary, seed: int):
        self.library = library
        self.rng = np.random.default_rng(np.random.SeedSequence([int(seed), 29]))
        self.fade = int(round(FADE_S * library.fps))
        self.lengths = (int(SEGMENT[0] * library.fps), int(SEGMENT[1] * library.fps))
        self.q = quaternion_sequence_continuous(axis_angle_to_quaternion(library.rotations))
        self.pose = library.rotations.reshape(len(self.q), -1)
        self.rotations, self.trans = np.zeros((0, len(JOINTS), 4)), np.zeros((0, 3))

    def add(self, want: Callable[[int, int], float], leash: float = 0.0) -> None:
        """One more segment; `want(first, span)` is the arm energy it should match over its
        frames [first, first + span). `leash` (0-1): the share of the hips' distance from the
        capture's centre that the segment takes back over its length (a live stream cannot
        take out drift afterwards)."""
        library, q, fade = self.library, self.q, self.fade
        length = int(self.rng.integers(self.lengths[0], self.lengths[1] + 1))
        span = min(length + fade, len(q) - 1)
        t0 = max(0, len(self.rotations) - fade)
        starts = np.arange(len(q) - span)
        windows = np.convolve(library.energy, np.ones(span) / span, mode="valid")[:len(starts)]
        cost = np.abs(windows - want(t0, span)) / (library.energy.std() + 1e-9)
        # a talker mostly stands: a segment that walks off costs as much as a poor energy match
        travel = np.linalg.norm(library.translation[starts + span - 1][:, [0, 2]]
                                - library.translation[starts][:, [0, 2]], axis=1)
        cost = cost + travel / TRAVEL_M
        if len(self.rotations):
            last = quaternion_to_axis_angle(self.rotations[t0]).reshape(-1)
            cost = cost + np.linalg.norm(self.pose[starts] - last, axis=1) / 0.2
        s0 = int(self.rng.choice(np.argsort(cost)[:CHOICES]))
        seg_q, seg_t = q[s0:s0 + span].copy(), library.translation[s0:s0 + span].copy()
        if len(self.rotations):
            here = self.trans[t0, [0, 2]]
            seg_t[:, [0, 2]] += here - seg_t[0, [0, 2]]  # the hips go on from where they are
            if leash:
                ease = np.linspace(0.0, 1.0, span)[:, None]
                seg_t[:, [0, 2]] += leash * ease * ease * (3 - 2 * ease) * (self.library.centre - here)
            w = np.linspace(0.0, 1.0, fade + 2)[1:-1][:, None]
            old_q, old_t = self.rotations[t0:], self.trans[t0:]
            overlap = len(old_q)
            flip = np.sign(np.sum(old_q * seg_q[:overlap], axis=-1, keepdims=True))
            blended = (1 - w[:overlap, :, None]) * old_q + w[:overlap, :, None] * seg_q[:overlap] * flip
            seg_q[:overlap] = blended / np.linalg.norm(blended, axis=-1, keepdims=True)
            seg_t[:overlap] = (1 - w[:overlap]) * old_t + w[:overlap] * seg_t[:overlap]
        self.rotations = np.concatenate([self.rotations[:t0], seg_q])
        self.trans = np.concatenate([self.trans[:t0], seg_t])


def _on_floor(lower: np.ndarray, trans: np.ndarray, fps: float) -> np.ndarray:
    """`trans` lowered or raised so the lowest foot point is on the floor (smoothed over
    GROUND_S): segments stood a little higher or lower in the capture than its floor."""
    out = trans.copy()
    out[:, 1] -= smooth_frames(_lowest(_world(lower, trans))[:, None], GROUND_S * fps)[:, 0]
    return out


def _lowest(world: dict) -> np.ndarray:
    """(T,) the height of the lowest foot point (either sole or toe end)."""
    return np.min([world[f"{p}{point}"][1][:, 1] for p in ("Right", "Left") for point in ("Sole", "ToeEnd")], axis=0)


def sample(library: LowerBodyLibrary, energy: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, 9, 3) lower-body rotations and (T, 3) hips translation for the arms' `energy`
    (arm_energy of the take), cut from `library` with `seed`; the translation's slow drift
    taken out and kept within the capture's range, then the body set on the floor."""
    n, fps = len(energy), library.fps
    planner = _Planner(library, seed)
    while len(planner.rotations) < n:
        planner.add(lambda t0, span: energy[t0:t0 + span].mean() if t0 < n else energy[-1])
    lower = quaternion_to_axis_angle(planner.rotations[:n])
    return lower, settle(lower, planner.trans[:n], library)


def settle(lower: np.ndarray, trans: np.ndarray, library: LowerBodyLibrary) -> np.ndarray:
    """`trans` (T, 3) of the hips under `lower` (T, 9, 3) wandering no further than the
    capture did: its slow drift (DRIFT_S) taken out about the capture's centre, kept within
    the capture's range, then lowered or raised so the feet are on the floor."""
    fps = library.fps
    trans = trans.copy()
    trans[:, [0, 2]] -= smooth_frames(trans[:, [0, 2]], DRIFT_S * fps) - library.centre
    trans = np.clip(trans, library.translation_low, library.translation_high)
    return _on_floor(lower, trans, fps)


def legs_source(rig: str, whole_body: bool) -> str | None:
    """Where generated motion's hips and legs come from: "model" (a whole-body model's own,
    planted), "capture" (cut from the capture to go with the arms, for a model whose layout
    stops at the waist on the BEAT skeleton), or None (a layout legs cannot be added to)."""
    if whole_body:
        return "model"
    return "capture" if rig in LAYOUTS else None


def add_lower_body(motion: Motion, seed: int, library: LowerBodyLibrary | None = None) -> Motion:
    """`motion` (a `beat` upper body) with the hips and legs (JOINTS) after its joints,
    `root_translation` (metres about the standing hips), and in its meta the hips' rest
    height ("hips_height", metres) and the contact spans ("contacts", model frames)."""
    library = _library_for(motion, library)
    lower, trans = sample(library, arm_energy(motion), seed)
    lower, spans = plant_feet(lower, trans, motion.fps)
    return with_lower_body(motion, lower, trans, spans)


def plant(motion: Motion, library: LowerBodyLibrary | None = None) -> Motion:
    """`motion` (a `beat` Motion whose hips, legs and root translation a whole-body model
    made) with the hips and legs low-passed (MODEL_SMOOTH_S: the network's frame-to-frame
    wobble would read as feet that never stand still), the hips settled as the capture's are
    (`settle`) and the feet standing or stepping (`FootSteps`); the spans each foot stands
    and the hips' rest height go into its meta."""
    library = _library_for(motion, library)
    _check_whole_body(motion)
    sigma = MODEL_SMOOTH_S * motion.fps
    q = quaternion_sequence_continuous(axis_angle_to_quaternion(lower_rotations(motion)))
    q = smooth_frames(q, sigma)
    lower = quaternion_to_axis_angle(q / np.linalg.norm(q, axis=-1, keepdims=True))
    trans = settle(lower, smooth_frames(motion.root_translation.astype(np.float64), sigma), library)
    lower, trans, spans = step_feet(lower, trans, motion.fps)
    return with_lower_body(upper_body(motion), lower, trans, spans)


def _check_whole_body(motion: Motion) -> None:
    """Planting needs what a whole-body model makes: the hips, legs and root translation."""
    if motion.root_translation is None or not set(JOINTS) <= set(motion.joint_names):
        raise DiffshegError("planting the feet needs a motion with the hips, legs and root translation "
                            "of a whole-body model")


def _no_frames() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """What a live lower-body stream returns for a hop of no frames."""
    return np.zeros((0, len(JOINTS), 3)), np.zeros((0, 3)), {side: np.zeros(0, bool) for side in LEGS}


def lower_rotations(motion: Motion) -> np.ndarray:
    """(T, 9, 3) the rotations of `motion`'s hips and legs (JOINTS, in that order), float64."""
    return motion.rotations[:, [motion.joint_names.index(j) for j in JOINTS]].astype(np.float64)


def with_lower_body(motion: Motion, lower: np.ndarray, trans: np.ndarray, spans: dict) -> Motion:
    """`motion` with (T, 9, 3) `lower` after its joints, `trans` as its root translation and
    the contact `spans` and the hips' rest height in its meta."""
    return replace(motion, joint_names=list(motion.joint_names) + list(JOINTS),
                   rotations=np.concatenate([motion.rotations, lower.astype(motion.rotations.dtype)], axis=1),
                   root_translation=trans.astype(np.float32),
                   meta={**motion.meta, "hips_height": _hips_height(),
                         "contacts": {side: [list(s) for s in v] for side, v in spans.items()}})


def _library_for(motion: Motion, library: LowerBodyLibrary | None) -> LowerBodyLibrary:
    if motion.rig not in LAYOUTS:
        raise DiffshegError(f"the lower body is known for the {', '.join(LAYOUTS)} layout, not '{motion.rig}': "
                            "generate with upper_body_only")
    return _library_at(motion.fps, library)


def _library_at(fps: float, library: LowerBodyLibrary | None) -> LowerBodyLibrary:
    library = library or _bundled_library()
    if abs(library.fps - fps) > 1e-6:
        raise DiffshegError(f"the lower-body library runs at {library.fps:g} fps, the motion at {fps:g}")
    return library


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


@lru_cache(maxsize=1)
def _bundled_library() -> LowerBodyLibrary:
    """The library shipped with the package, read once per process (batches generate many takes)."""
    return LowerBodyLibrary.load()


def upper_body(motion: Motion) -> Motion:
    """`motion` without the lower body (its model layout's joints only)."""
    keep = [i for i, n in enumerate(motion.joint_names) if n not in JOINTS]
    return replace(motion, joint_names=[motion.joint_names[i] for i in keep], rotations=motion.rotations[:, keep],
                   root_translation=None)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m diffsheg_core.lower_body",
                                     description="Build the lower-body library from a BEAT2 SMPL-X take.")
    parser.add_argument("--capture", required=True, type=Path, help="a BEAT2 smplxflame_30 .npz with trans")
    parser.add_argument("--out", type=Path, default=ASSET)
    args = parser.parse_args(argv)
    print(build(args.capture).save(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
