"""Foot contact on the rig: the keyed legs solved again so a contact foot stays put.

The motion plants its feet on the canonical body; on a rig whose legs, hips width or ankle
height differ, the same turns move the feet a little. Over each contact span of the motion
(meta "contacts") the rig's ankle is pinned where it is at the span's middle frame and the
foot keeps that frame's orientation (eased in and out), and each leg is solved with two-bone
IK on the rig's own bone lengths (diffsheg_core.lower_body.leg_ik, as the canonical body's).
The motion's hips sway over the canonical body's legs; where a rig's straightened leg cannot
reach its pinned foot (a few millimetres), the hips come down as far as it needs. Live
(`LiveFeet`) pins a foot a frame at a time, where it lands. numpy only, fed with the rig's
rest matrices (retarget.LegRig): bones between the keyed ones are taken at rest.
"""

from __future__ import annotations

import numpy as np

from diffsheg_core.lower_body.leg_ik import pin_goals, two_bone
from diffsheg_core.rotations import convert, quaternion_sequence_continuous

from .retarget import LegRig, leg_length

EASE_S = 0.08  # seconds over which a pin eases in and out: the motion's own feet already land on the spot, the pin only takes out what the rig's proportions change, so a longer ease would drag a stepping foot over the floor


def scene_spans(contacts: list, source_fps: float, fps: float, n_frames: int) -> list[tuple[int, int]]:
    """Contact spans [first, last] in model frames at `source_fps` as frames at `fps`."""
    ratio = fps / source_fps
    out = []
    for first, last in contacts:
        a, b = int(np.ceil(first * ratio)), min(int(np.floor(last * ratio)), n_frames - 1)
        if a <= b:
            out.append((a, b))
    return out


def _matrices(quaternions: np.ndarray) -> np.ndarray:
    return convert(np.asarray(quaternions, dtype=np.float64), "quaternion", "matrix")


def _local(rest: np.ndarray, world: np.ndarray, parent_world: np.ndarray) -> np.ndarray:
    """(T, 4) local quaternions of a bone whose rest-relative armature rotation is `world`."""
    local = rest.T @ np.transpose(parent_world, (0, 2, 1)) @ world @ rest
    return quaternion_sequence_continuous(convert(local, "matrix", "quaternion"))


def _pose(leg: LegRig, displacement: np.ndarray, quaternions: dict[str, np.ndarray]):
    """Rest-relative armature rotations of hips, thigh, shin and foot, and the heads of hips,
    thigh, knee and ankle, per frame."""
    hips_rest = leg.rest[0]
    hips = hips_rest @ _matrices(quaternions["hips"]) @ hips_rest.T
    worlds, heads = [hips], [leg.heads[0] + displacement]
    for k, bone in enumerate(leg.bones):
        rest = leg.rest[k + 1]
        heads.append(heads[-1] + worlds[-1] @ (leg.heads[k + 1] - leg.heads[k]))
        worlds.append(worlds[-1] @ rest @ _matrices(quaternions[bone]) @ rest.T)
    return worlds, heads


def plant_feet(legs: list[LegRig], displacement: np.ndarray, quaternions: dict[str, np.ndarray], hips: str,
               spans: dict[str, list[tuple[int, int]]], fps: float) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """New local quaternions of the legs' thigh, shin and foot (by bone name) that pin the
    ankle and the foot's orientation over each leg's `spans` (by side) where they are at the
    span's middle frame (diffsheg_core.lower_body.leg_ik), and the hips' (T, 3) `displacement`,
    lowered (eased in and out) where a pinned foot lies beyond its straight leg's reach.
    `quaternions`: local (T, 4) per bone, `hips` the hips bone's."""
    pose = {"hips": quaternions[hips], **{b: quaternions[b] for leg in legs for b in leg.bones}}
    posed = {leg.side: _pose(leg, displacement, pose) for leg in legs}
    pins = {side: [(a, b, heads[3][(a + b) // 2], worlds[3][(a + b) // 2]) for a, b in spans.get(side, [])]
            for side, (worlds, heads) in posed.items()}
    ease = max(1, int(round(EASE_S * fps)))
    goals = _goals(posed, pins, ease)
    drop = _eased(_reach_drop(legs, posed, goals), max(1, int(round(DROP_EASE_S * fps))))
    return _solve_legs(legs, displacement, drop, pose, posed, goals)


def _goals(posed: dict[str, tuple[list, list]], pins: dict[str, list], ease: int) -> dict[str, tuple]:
    """Per side, where the ankle and the foot should be and how much the pins hold them there
    (leg_ik.pin_goals), from the leg as posed (`posed`: per side its worlds and heads)."""
    return {side: pin_goals(heads[3], worlds[3], pins.get(side, []), ease) for side, (worlds, heads) in posed.items()}


def _eased(drop: np.ndarray, frames: int) -> np.ndarray:
    """`drop` spread over time so the hips ease down and up over about 4 x `frames` frames
    instead of in a frame, and never less than `drop`: its maximum over 2 x `frames` either
    side, averaged twice over `frames` either side."""
    spread = np.lib.stride_tricks.sliding_window_view(np.pad(drop, 2 * frames, mode="edge"), 4 * frames + 1).max(1)
    box = np.full(2 * frames + 1, 1.0 / (2 * frames + 1))
    for _ in range(2):
        spread = np.convolve(np.pad(spread, frames, mode="edge"), box, mode="valid")
    return np.maximum(spread, drop)  # only rounding can leave the averages under it


def _solve_legs(legs: list[LegRig], displacement: np.ndarray, drop: np.ndarray, pose: dict[str, np.ndarray],
                posed: dict[str, tuple[list, list]], goals: dict[str, tuple]
                ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The legs' bones (`posed` at `displacement`: per side its worlds and heads) solved so each
    ankle and foot are at their `goals` (by side) where a pin holds them and, where the hips come
    down by `drop` along the rig's up, elsewhere where they were before (a free foot is not
    dragged down with the hips); and the lowered displacement (the same array where `drop` is
    all 0)."""
    lowered = displacement - np.reshape(drop, (-1, 1)) * _up(legs) if np.any(drop) else displacement
    out = {}
    for leg in legs:
        goal, goal_rot, weight = goals[leg.side]
        held = (weight > 0) | (drop > 0)
        if np.any(held):
            worlds, heads = posed[leg.side] if lowered is displacement else _pose(leg, lowered, pose)
            out.update(_solve(leg, worlds, heads, goal, goal_rot, held))
    return out, lowered


def _solve(leg: LegRig, worlds: list, heads: list, goal: np.ndarray, goal_rot: np.ndarray,
           held: np.ndarray) -> dict[str, np.ndarray]:
    """The leg's thigh, shin and foot local quaternions with, in the `held` frames, its ankle at
    `goal` and its foot turned to `goal_rot` (armature space)."""
    (hips, thigh, shin, foot), (_, hip, knee, ankle) = worlds, heads
    turn, bend = two_bone(hip, knee, ankle, goal, float(np.linalg.norm(leg.heads[2] - leg.heads[1])),
                          float(np.linalg.norm(leg.heads[3] - leg.heads[2])), hips @ leg.left)
    held = held[:, None, None]
    new_thigh = np.where(held, turn @ thigh, thigh)
    new_shin = np.where(held, turn @ bend @ shin, shin)
    new_foot = np.where(held, goal_rot, foot)
    thigh_bone, shin_bone, foot_bone = leg.bones
    return {thigh_bone: _local(leg.rest[1], new_thigh, hips),
            shin_bone: _local(leg.rest[2], new_shin, new_thigh),
            foot_bone: _local(leg.rest[3], new_foot, new_shin)}


MAX_DROP = 0.05
"""The most the hips come down for a pinned foot to stay within its leg's reach, as a share of
the leg's length (thigh and shin)."""

DROP_EASE_S = 0.12
"""Offline, the hips ease down and up for a pinned foot over about four times this (seconds)."""

REACH = 0.999
"""The share of a leg's length (thigh and shin) a pinned foot may lie from the hip joint."""


def _up(legs: list[LegRig]) -> np.ndarray:
    """The rig's up in armature space: from the ankles to the hip joints at rest."""
    up = sum(leg.heads[1] - leg.heads[3] for leg in legs)
    return up / np.linalg.norm(up)


def _reach_drop(legs: list[LegRig], posed: dict[str, tuple[list, list]], goals: dict[str, tuple]) -> np.ndarray:
    """Per frame, how far along the rig's up (armature units, at most MAX_DROP of the leg) the
    hips must come down for each leg's hip joint (as `posed`) to lie within REACH of where a pin
    holds its ankle (`goals`); 0 where no pin holds."""
    up, drop = _up(legs), 0.0
    for leg in legs:
        goal, _, weight = goals[leg.side]
        length = leg_length(leg)
        reach = REACH * length
        apart = posed[leg.side][1][1] - goal
        along = apart @ up
        apart2 = np.einsum("ti,ti->t", apart, apart)
        inside = along ** 2 - apart2 + reach ** 2
        # how much nearer the goal the hip must come along up
        closer = np.where(inside >= 0, along - np.sqrt(np.clip(inside, 0.0, None)), along)
        short = (apart2 > reach ** 2) & (weight > 0)
        drop = np.maximum(drop, np.where(short, np.clip(closer, 0.0, MAX_DROP * length), 0.0))
    return drop


class LiveFeet:
    """Contact feet pinned on the rig a frame at a time (Live posing, live.py). Live cannot
    see a span's middle: a foot is pinned where it is on the frame it lands, held while the
    stream says it is down, and eased out over EASE_S once it lifts."""

    def __init__(self, fps: float):
        self.ease = max(1, int(round(EASE_S * fps)))
        self._pins: dict[str, tuple[int, int, np.ndarray, np.ndarray]] = {}  # side: (landed, last down, ankle, foot)
        self._shown: int | None = None  # the stream's frame posed last
        self._lifted: set[str] = set()  # sides up in a frame made since then that was not posed

    def passed(self, down: dict[str, bool]) -> None:
        """A frame of the stream the rig did not show (a session catching up poses only the
        newest frame due): a foot up in it has stepped, so it lands anew when next posed down
        rather than being held where it stood before the step."""
        self._lifted.update(side for side in self._pins if not down.get(side))

    def solve(self, legs: list[LegRig], displacement: np.ndarray, quaternions: dict[str, np.ndarray], hips: str,
              down: dict[str, bool], index: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """New local quaternions (1, 4) of the legs' bones for the stream's frame `index`,
        posed as `quaternions` ((1, 4) per bone, `hips` the hips bone's) and `displacement`
        (1, 3); `down`: per side whether that foot is planted in this frame. Also returns the
        displacement, lowered as far as a pinned foot needs to be within its leg's reach (the
        stream's hips sway over the canonical body's legs; on a rig's, a straight leg can fall
        a few millimetres short, and the foot would slide towards the hips); a foot not pinned
        stays where the stream put it while the hips come down."""
        pose = {"hips": quaternions[hips], **{b: quaternions[b] for leg in legs for b in leg.bones}}
        posed = {leg.side: _pose(leg, displacement, pose) for leg in legs}
        pins = {}
        for leg in legs:
            pin = self._pins.get(leg.side)
            if down.get(leg.side):
                landed = pin is None or self._shown is None or pin[1] < self._shown or leg.side in self._lifted
                worlds, heads = posed[leg.side]
                pin = (index, index, heads[3][0], worlds[3][0]) if landed else (pin[0], index, pin[2], pin[3])
                self._pins[leg.side] = pin
            elif pin is not None and index - pin[1] > self.ease:
                del self._pins[leg.side]
                pin = None
            if pin is not None:
                pins[leg.side] = [(pin[0] - index, pin[1] - index, pin[2], pin[3])]
        goals = _goals(posed, pins, self.ease)
        out, displacement = _solve_legs(legs, displacement, _reach_drop(legs, posed, goals), pose, posed, goals)
        self._shown = index
        self._lifted.clear()
        return out, displacement
