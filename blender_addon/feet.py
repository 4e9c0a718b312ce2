"""Foot contact on the rig: the keyed legs solved again so a contact foot stays put.

The motion plants its feet on the canonical body; on a rig whose legs, hips width or ankle
height differ, the same turns move the feet a little. Over each contact span of the motion
(meta "contacts") the rig's ankle is pinned where it is at the span's middle frame and the
foot keeps that frame's orientation (eased in and out), and each leg is solved with two-bone
IK on the rig's own bone lengths. numpy only, fed with the rig's rest matrices (retarget.LegRig):
bones between the keyed ones are taken at rest.
"""

from __future__ import annotations

import numpy as np

from diffsheg_core.rotations import convert, quaternion_sequence_continuous

from .retarget import LegRig, swing

EASE_S = 0.2   # seconds over which a pin eases in and out


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


def ankle_positions(leg: LegRig, displacement: np.ndarray, quaternions: dict[str, np.ndarray]) -> np.ndarray:
    """(T, 3) armature-space ankle (the foot bone's head) for the hips' `displacement`
    (T, 3 armature space) and the local quaternions of the hips and the leg's bones."""
    return _pose(leg, displacement, quaternions)[1][-1]


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
    ankle and the foot's orientation over each span. `quaternions`: local (T, 4) of "hips"
    and of the leg's bones."""
    (hips, thigh, shin, foot), (_, hip, knee, ankle) = _pose(leg, displacement, quaternions)
    n = len(hips)
    ease = max(1, int(round(EASE_S * fps)))
    weight = np.zeros(n)
    goal, goal_rot = ankle.copy(), foot.copy()
    for a, b in spans:
        mid = (a + b) // 2
        lo, hi = max(0, a - ease), min(n - 1, b + ease)
        frames = np.arange(lo, hi + 1)
        ramp = np.clip(np.minimum(frames - a + ease + 1, b + ease + 1 - frames) / (ease + 1), 0.0, 1.0)
        take = ramp >= weight[lo:hi + 1]
        goal[frames[take]] = ankle[mid]
        goal_rot[frames[take]] = foot[mid]
        weight[lo:hi + 1] = np.maximum(weight[lo:hi + 1], ramp)
    moving = weight > 0
    goal = ankle + weight[:, None] * (goal - ankle)
    goal_rot = _blend(foot, goal_rot, weight)
    thigh_len = np.linalg.norm(leg.heads[2] - leg.heads[1])
    shin_len = np.linalg.norm(leg.heads[3] - leg.heads[2])
    new_thigh, new_shin = thigh.copy(), shin.copy()
    for t in np.flatnonzero(moving):
        new_thigh[t], new_shin[t] = _two_bone(hip[t], knee[t], ankle[t], goal[t], thigh[t], shin[t],
                                              thigh_len, shin_len, hips[t] @ leg.left)
    new_foot = np.where(moving[:, None, None], goal_rot, foot)
    thigh_bone, shin_bone, foot_bone = leg.bones
    return {thigh_bone: _local(leg.rest[1], new_thigh, hips),
            shin_bone: _local(leg.rest[2], new_shin, new_thigh),
            foot_bone: _local(leg.rest[3], new_foot, new_shin)}


def _blend(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per frame the rotation `w` of the way from rotation matrix `a` to `b`."""
    step = convert(np.transpose(a, (0, 2, 1)) @ b, "matrix", "axis_angle") * w[:, None]
    return a @ convert(step, "axis_angle", "matrix")


def _two_bone(hip, knee, ankle, goal, thigh, shin, thigh_len: float, shin_len: float, left) -> tuple:
    """Thigh and shin rotations (rest-relative, armature space) putting the ankle at `goal`:
    the knee bent about its hinge to the hip-goal distance, then the leg swung onto the goal."""
    reach = np.clip(np.linalg.norm(goal - hip), abs(thigh_len - shin_len) + 1e-6, 0.9999 * (thigh_len + shin_len))
    now = _angle(hip - knee, ankle - knee)
    wanted = np.arccos(np.clip((thigh_len ** 2 + shin_len ** 2 - reach ** 2) / (2 * thigh_len * shin_len), -1, 1))
    hinge = np.cross(knee - hip, ankle - knee)
    hinge = hinge / np.linalg.norm(hinge) if np.linalg.norm(hinge) > 1e-9 else left  # straight: bend forward
    bend = convert(hinge * (now - wanted), "axis_angle", "matrix")
    turn = swing(knee + bend @ (ankle - knee) - hip, goal - hip)
    return turn @ thigh, turn @ bend @ shin


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0)))
