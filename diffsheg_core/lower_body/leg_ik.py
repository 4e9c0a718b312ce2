"""Planting a foot: pins over contact spans and two-bone IK, in rotation matrices.

One implementation for both places a foot is planted: the canonical body's legs
(`lower_body.feet`), and a rig's own legs after keying (the add-on's scene/feet.py). A pin holds
the ankle at a spot and the foot at an orientation over [first, last] frames, eased in and
out over `ease` frames; a frame between two pins' eases follows the nearer span. A pin may
start before the frames or end after them (a live stream solves a hop of frames at a time).
numpy only: it runs inside Blender.
"""

from __future__ import annotations

import numpy as np

from ..rotations import axis_angle_to_matrix, matrix_to_axis_angle

Pin = tuple[int, int, np.ndarray, np.ndarray]
"""(first, last, ankle position (3,), foot rotation (3, 3)) held over frames first..last."""


def pin_goals(ankle: np.ndarray, foot: np.ndarray, pins: list[Pin], ease: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame where the ankle and the foot should be ((T, 3), (T, 3, 3)) and how much
    a pin holds them there (T,) (1 inside a span, easing to 0 over `ease` frames beside it):
    the free ankle `ankle` and foot `foot` where no pin holds."""
    n = len(ankle)
    weight = np.zeros(n)
    target, target_rot = ankle.copy(), foot.copy()
    for first, last, spot, rotation in pins:
        lo, hi = max(0, first - ease), min(n - 1, last + ease)
        if hi < lo:  # the pin and its ease lie outside these frames
            continue
        frames = np.arange(lo, hi + 1)
        ramp = np.clip(np.minimum(frames - first + ease + 1, last + ease + 1 - frames) / (ease + 1), 0.0, 1.0)
        held = ramp > weight[lo:hi + 1]  # a neighbour's own span wins
        target[frames[held]], target_rot[frames[held]] = spot, rotation
        weight[frames[held]] = ramp[held]
    step = matrix_to_axis_angle(np.transpose(foot, (0, 2, 1)) @ target_rot) * weight[:, None]
    return ankle + weight[:, None] * (target - ankle), foot @ axis_angle_to_matrix(step), weight


def two_bone(hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray, goal: np.ndarray, thigh: float, shin: float,
             straight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3, 3) world rotations `swing` and `bend` that put the ankle at `goal`: the shin
    turns by `bend` about the knee's hinge so that hip-to-ankle is as long as hip-to-goal
    (within the leg's reach), then the whole leg turns by `swing` about the hip onto the
    goal. New thigh = swing @ thigh, new shin = swing @ bend @ shin (world rotations).
    `straight` (T, 3): the hinge of a straight leg (the body's left: it bends forward)."""
    reach = np.clip(np.linalg.norm(goal - hip, axis=-1), abs(thigh - shin) + 1e-6, 0.9999 * (thigh + shin))
    now = _angle(hip - knee, ankle - knee)
    wanted = np.arccos(np.clip((thigh ** 2 + shin ** 2 - reach ** 2) / (2 * thigh * shin), -1.0, 1.0))
    hinge = np.cross(knee - hip, ankle - knee)
    norm = np.linalg.norm(hinge, axis=-1, keepdims=True)
    hinge = np.where(norm > 1e-9, hinge / np.maximum(norm, 1e-12), straight)
    bend = axis_angle_to_matrix(hinge * (now - wanted)[:, None])
    bent = knee + np.einsum("tij,tj->ti", bend, ankle - knee)
    return swing(bent - hip, goal - hip), bend


def swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the smallest rotation turning direction `a` onto direction `b` (..., 3)
    (half a turn about a perpendicular where they are opposite)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    c = np.sum(a * b, axis=-1, keepdims=True)
    other = np.where(np.abs(a[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    perp = np.cross(a, other)
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    vector = np.where(s > 1e-9, axis / np.maximum(s, 1e-12) * np.arctan2(s, c), np.where(c > 0, 0.0, np.pi * perp))
    return axis_angle_to_matrix(vector)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1) + 1e-12)
    return np.arccos(np.clip(cos, -1.0, 1.0))
