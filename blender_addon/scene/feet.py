"""Foot contact on the rig: the keyed legs solved again so a contact foot stays put.

The motion plants its feet on the canonical body; on a rig whose legs, hips width or ankle
height differ, the same turns move the feet a little. Over each contact span of the motion
(meta "contacts") the rig's ankle is pinned where it is at the span's middle frame and the
foot keeps that frame's orientation (eased in and out), and each leg is solved with two-bone
IK on the rig's own bone lengths (diffsheg_core.lower_body.leg_ik, as the canonical body's). Live
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


def plant_foot(leg: LegRig, displacement: np.ndarray, quaternions: dict[str, np.ndarray],
               spans: list[tuple[int, int]], fps: float) -> dict[str, np.ndarray]:
    """New local quaternions of the leg's thigh, shin and foot (by bone name) that pin the
    ankle and the foot's orientation over each span (diffsheg_core.lower_body.leg_ik). `quaternions`:
    local (T, 4) of "hips" and of the leg's bones."""
    worlds, heads = _pose(leg, displacement, quaternions)
    ankle, foot = heads[3], worlds[3]
    pins = [(a, b, ankle[(a + b) // 2], foot[(a + b) // 2]) for a, b in spans]
    return _solve(leg, worlds, heads, pins, max(1, int(round(EASE_S * fps))))


def _solve(leg: LegRig, worlds: list, heads: list, pins: list, ease: int) -> dict[str, np.ndarray]:
    """The leg's thigh, shin and foot local quaternions with its ankle and foot held by `pins`."""
    (hips, thigh, shin, foot), (_, hip, knee, ankle) = worlds, heads
    goal, goal_rot, weight = pin_goals(ankle, foot, pins, ease)
    turn, bend = two_bone(hip, knee, ankle, goal, float(np.linalg.norm(leg.heads[2] - leg.heads[1])),
                          float(np.linalg.norm(leg.heads[3] - leg.heads[2])), hips @ leg.left)
    held = (weight > 0)[:, None, None]
    new_thigh = np.where(held, turn @ thigh, thigh)
    new_shin = np.where(held, turn @ bend @ shin, shin)
    new_foot = np.where(held, goal_rot, foot)
    thigh_bone, shin_bone, foot_bone = leg.bones
    return {thigh_bone: _local(leg.rest[1], new_thigh, hips),
            shin_bone: _local(leg.rest[2], new_shin, new_thigh),
            foot_bone: _local(leg.rest[3], new_foot, new_shin)}


MAX_DROP = 0.05
"""The most Live lowers the hips for a pinned foot to stay within its leg's reach, as a share of
the leg's length (thigh and shin)."""

REACH = 0.999
"""The share of a leg's length (thigh and shin) Live lets a pinned foot lie from the hip joint."""


def _up(legs: list[LegRig]) -> np.ndarray:
    """The rig's up in armature space: from the ankles to the hip joints at rest."""
    up = sum(leg.heads[1] - leg.heads[3] for leg in legs)
    return up / np.linalg.norm(up)


def _reach_drop(leg: LegRig, heads: list, pins: list, worlds: list, ease: int, up: np.ndarray) -> float:
    """How far along `up` (armature units, at most MAX_DROP of the leg) the hips must come down
    for the leg's hip joint to lie within REACH of the ankle's pinned goal this frame. Easing
    out (the pin's weight w under 1) the goal comes down with the hips by 1 - w of the drop."""
    goal, _, weight = pin_goals(heads[3], worlds[3], pins, ease)
    length = leg_length(leg)
    reach = REACH * length
    apart = heads[1][0] - goal[0]
    if np.linalg.norm(apart) <= reach or weight[0] <= 0:
        return 0.0
    along = float(apart @ up)
    inside = along ** 2 - float(apart @ apart) + reach ** 2
    closer = along - np.sqrt(inside) if inside >= 0 else along  # how much nearer the goal the hip must come
    return float(np.clip(closer / weight[0], 0.0, MAX_DROP * length))


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
        a few millimetres short, and the foot would slide towards the hips)."""
        pose = {"hips": quaternions[hips], **{b: quaternions[b] for leg in legs for b in leg.bones}}
        pinned = []
        for leg in legs:
            worlds, heads = _pose(leg, displacement, pose)
            pin = self._pins.get(leg.side)
            if down.get(leg.side):
                landed = pin is None or self._shown is None or pin[1] < self._shown or leg.side in self._lifted
                pin = (index, index, heads[3][0], worlds[3][0]) if landed else (pin[0], index, pin[2], pin[3])
                self._pins[leg.side] = pin
            elif pin is not None and index - pin[1] > self.ease:
                del self._pins[leg.side]
                pin = None
            if pin is not None:
                pinned.append((leg, [(pin[0] - index, pin[1] - index, pin[2], pin[3])], worlds, heads))
        up = _up(legs)
        drop = max([_reach_drop(leg, heads, pins, worlds, self.ease, up) for leg, pins, worlds, heads in pinned],
                   default=0.0)
        if drop > 0:
            displacement = displacement - drop * up
        out = {}
        for leg, pins, worlds, heads in pinned:
            if drop > 0:
                worlds, heads = _pose(leg, displacement, pose)
            out.update(_solve(leg, worlds, heads, pins, self.ease))
        self._shown = index
        self._lifted.clear()
        return out, displacement
