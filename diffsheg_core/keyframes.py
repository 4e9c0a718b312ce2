"""Sparse keys an animator can edit: poses on a motion's turning points, Bezier between.

A dense motion (one value per frame) becomes a few keys per channel group (a bone's
rotation channels, or one shape key) that share their frames, each key with a slope,
so that the cubic curve through them stays within an error bound on every frame.
Keys go where the group's motion turns or holds (local minima of its speed), so each
one is a pose an animator recognises; where no turning point fits, at the frame of the
largest error.

The curve between two keys is the cubic Hermite through their values and slopes. It is
exactly what Blender evaluates for Bezier keys whose handles sit a third of the way to
the neighbouring key along the slope (`handles`), so the bound checked here holds for
the F-curves. Errors are measured by the caller's `ErrorFn`: the rotation angle in
degrees for a bone (`rotation_error`), the largest difference of weights for a shape key
(`value_error`). Plain numpy; the add-on writes the keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from .errors import DiffshegError

ErrorFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(N, C) evaluated channel values at (N,) frames -> (N,) error per frame against the motion."""

ROTATION_MODES = ("QUATERNION", "AXIS_ANGLE", "XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


@dataclass(frozen=True)
class Keys:
    """Keys of one channel group: frames (K,) from 0, values (K, C), slopes (K, C) per frame."""

    frames: np.ndarray
    values: np.ndarray
    slopes: np.ndarray

    def __len__(self) -> int:
        return len(self.frames)


def evaluate(keys: Keys, n_frames: int) -> np.ndarray:
    """(n_frames, C) values of the Hermite curve through `keys` at frames 0..n_frames-1
    (held constant outside the keys, as Blender extrapolates)."""
    if len(keys) == 1:
        return np.repeat(keys.values, n_frames, axis=0)
    seg, w = _basis(keys.frames, np.arange(n_frames))
    return (w[0][:, None] * keys.values[seg] + w[1][:, None] * keys.values[seg + 1]
            + w[2][:, None] * keys.slopes[seg] + w[3][:, None] * keys.slopes[seg + 1])


def _basis(frames: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For frames `t`: the segment of keys `frames` each lies in and the (4, N) weights of
    that segment's start value, end value, start slope and end slope."""
    seg = np.clip(np.searchsorted(frames, t, side="right") - 1, 0, len(frames) - 2)
    a = frames[seg]
    h = (frames[seg + 1] - a).astype(np.float64)
    s = np.clip((t - a) / h, 0.0, 1.0)
    s2, s3 = s * s, s * s * s
    return seg, np.stack([2 * s3 - 3 * s2 + 1, -2 * s3 + 3 * s2, (s3 - 2 * s2 + s) * h, (s3 - s2) * h])


def handles(keys: Keys) -> tuple[np.ndarray, np.ndarray]:
    """Left and right Bezier handles (K, C, 2) as (frame, value), a third of the way to
    the neighbouring key along each key's slope: collinear, so Blender's ALIGNED type
    keeps them (the first and last keys mirror their one real handle)."""
    f = keys.frames.astype(np.float64)
    if len(f) == 1:
        gap_left = gap_right = np.ones(1)
    else:
        gaps = np.diff(f)
        gap_left = np.concatenate([gaps[:1], gaps]) / 3.0
        gap_right = np.concatenate([gaps, gaps[-1:]]) / 3.0
    left = np.stack([np.broadcast_to((f - gap_left)[:, None], keys.values.shape),
                     keys.values - keys.slopes * gap_left[:, None]], axis=-1)
    right = np.stack([np.broadcast_to((f + gap_right)[:, None], keys.values.shape),
                      keys.values + keys.slopes * gap_right[:, None]], axis=-1)
    return left, right


def turning_points(values: np.ndarray) -> np.ndarray:
    """Frames where a channel group's motion turns or holds: local minima of its speed
    (the norm of the per-frame change over all its channels), ends excluded."""
    speed = np.linalg.norm(np.gradient(values, axis=0), axis=1) if len(values) > 1 else np.zeros(len(values))
    if len(speed) < 3:
        return np.zeros(0, dtype=np.int64)
    inner = speed[1:-1]
    minima = (inner <= speed[:-2]) & (inner < speed[2:])
    return np.flatnonzero(minima) + 1


NON_TURNING_COST = 3.0  # a key off the turning points costs as much as three on them
MAX_GAP = 96  # the longest segment the search tries (4 s at 24 fps); merging keys may join longer ones


End = tuple[np.ndarray, np.ndarray]
"""A key that is given: its (C,) values and (C,) slopes per frame."""


def fit_keys(values: np.ndarray, error: ErrorFn, bound: float, max_gap: int = MAX_GAP,
             ends: Optional[tuple[End, End]] = None) -> Keys:
    """The fewest keys of one channel group (values (T, C), one row per frame) whose curve
    stays within `bound` of the motion on every frame, by `error`, preferring turning points.
    `ends` gives the first and last keys (value and slope) instead of the motion's, as where
    keys are fitted into a range of curves that go on beyond it: their slopes are kept.

    Each key holds the motion's value and its central-difference slope at its frame, so
    whether the curve between two frames keeps the bound depends on those two frames alone:
    every segment up to `max_gap` frames long is checked (all segments of one length at
    once), and a shortest path over the frames picks the keys, a key on a turning point
    costing 1 and one elsewhere NON_TURNING_COST: keys go to the poses, at a few more keys
    (on 60 s of generated motion 83 % of a bone's keys lie within a frame of a turning
    point, against 47 % of all frames, for 6 % more keys). Then keys are dropped where
    fitting their neighbours' slopes keeps the bound (`_merge`).
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2 or not np.isfinite(values).all():
        raise DiffshegError("keys can only be fitted to finite (frames, channels) values")
    if not (bound > 0 and np.isfinite(bound)):
        raise DiffshegError(f"the key error bound must be a number above 0, got {bound!r}")
    n = len(values)
    slopes = np.gradient(values, axis=0) if n > 1 else np.zeros_like(values)
    key_values = values.copy()  # what a key at each frame holds: the motion's, or a given end's
    if ends is not None:
        for i, (value, slope) in zip((0, n - 1), ends):
            key_values[i], slopes[i] = value, slope
    if n <= 2:
        return Keys(np.arange(n), key_values, slopes)
    cost = np.full(n, NON_TURNING_COST)
    cost[turning_points(values)] = 1.0
    best = np.full(n, np.inf)
    best[0] = 1.0
    previous = np.zeros(n, dtype=np.int64)
    fits = _segments_within(key_values, slopes, error, bound, min(max_gap, n - 1))
    for b in range(1, n):
        gaps = np.arange(1, min(b, len(fits)) + 1)
        a = b - gaps
        ok = fits[gaps - 1, a]
        if not ok.any():
            continue
        totals = np.where(ok, best[a], np.inf)
        pick = int(np.argmin(totals))
        best[b], previous[b] = totals[pick] + cost[b], a[pick]
    frames = [n - 1]
    while frames[-1] > 0:
        frames.append(int(previous[frames[-1]]))
    keys = Keys(np.array(frames[::-1]), key_values[frames[::-1]], slopes[frames[::-1]])
    turning = cost == 1.0
    locked = (0, n - 1) if ends is not None else ()
    keys = _merge(keys, values, error, bound, lambda f: not turning[f], locked)  # keys off the turning points first
    return _merge(keys, values, error, bound, lambda f: True, locked)


def fit_span(values: np.ndarray, error: ErrorFn, bound: float, fixed: dict[int, End]) -> Keys:
    """Keys for frames 0..T-1 of `values` (T, C) through the keys `fixed` gives ({frame:
    (values, slopes)}, the first and last frame among them), which stay as given: between
    each two of them, the fewest keys that keep `bound` by `error` (`fit_keys`)."""
    values = np.asarray(values, dtype=np.float64)
    at = sorted(fixed)
    if not at or at[0] != 0 or at[-1] != len(values) - 1:
        raise DiffshegError(f"fit_span needs given keys at its first and last frame (0 and {len(values) - 1}), "
                            f"got {at}")
    parts = [Keys(np.zeros(1, dtype=np.int64), np.asarray(fixed[0][0], dtype=np.float64)[None],
                  np.asarray(fixed[0][1], dtype=np.float64)[None])]
    for a, b in zip(at, at[1:]):
        keys = fit_keys(values[a: b + 1], lambda v, f, a=a: error(v, f + a), bound, ends=(fixed[a], fixed[b]))
        parts.append(Keys(keys.frames[1:] + a, keys.values[1:], keys.slopes[1:]))
    return Keys(np.concatenate([k.frames for k in parts]), np.concatenate([k.values for k in parts]),
                np.concatenate([k.slopes for k in parts]))


def _merge(keys: Keys, values: np.ndarray, error: ErrorFn, bound: float, may_drop,
           locked: tuple[int, ...] = ()) -> Keys:
    """Drop keys (those `may_drop` allows, left to right) where fitting the slopes of the
    two keys beside one, by least squares over the three segments they shape, keeps every
    frame there within the bound: the handles are fitted to the motion, not only its slope.
    Keys at the `locked` frames keep their slopes."""
    frames, vals, slopes = list(keys.frames), keys.values, keys.slopes.copy()
    keep = np.ones(len(frames), dtype=bool)
    i = 1
    while i < len(frames) - 1:
        idx = np.flatnonzero(keep)
        k = int(np.searchsorted(idx, i))
        if not may_drop(frames[i]) or k == 0 or k >= len(idx) - 1:
            i += 1
            continue
        near = idx[max(k - 2, 0): k + 3]
        near = near[near != i]  # the keys that shape the frames around key i once it is gone
        j = int(np.searchsorted(near, i))  # near[j - 1] and near[j]: the keys beside i
        free = tuple(m for m in (j - 1, j) if frames[near[m]] not in locked)
        fitted = _fit_slopes(np.array(frames)[near], vals[near], slopes[near], free, values, error, bound)
        if fitted is not None:
            for m, slope in zip(free, fitted):
                slopes[near[m]] = slope
            keep[i] = False
        i += 1
    idx = np.flatnonzero(keep)
    return Keys(keys.frames[idx], vals[idx], slopes[idx])


def _fit_slopes(frames: np.ndarray, vals: np.ndarray, slopes: np.ndarray, free: tuple[int, ...],
                values: np.ndarray, error: ErrorFn, bound: float):
    """Least-squares slopes of keys `free` (indices into these few keys; none: the slopes as
    they are) for the frames the keys span; those slopes if every frame then keeps the
    bound, else None."""
    t = np.arange(frames[0], frames[-1] + 1)
    seg, w = _basis(frames, t)
    fixed = slopes.copy()
    fixed[list(free)] = 0.0
    known = (w[0][:, None] * vals[seg] + w[1][:, None] * vals[seg + 1]
             + w[2][:, None] * fixed[seg] + w[3][:, None] * fixed[seg + 1])
    curve, solution = known, np.zeros((0, vals.shape[1]))
    if free:
        design = np.stack([w[2] * (seg == f) + w[3] * (seg + 1 == f) for f in free], axis=1)  # a slope moves every channel alike
        solution = np.linalg.lstsq(design, values[t] - known, rcond=None)[0]  # (len(free), C)
        curve = known + design @ solution
    if error(curve, t).max() > bound:
        return None
    return tuple(solution)


PATIENCE = 4  # a start frame whose segments failed this many lengths running is dropped


def _segments_within(values: np.ndarray, slopes: np.ndarray, error: ErrorFn, bound: float,
                     max_gap: int) -> np.ndarray:
    """fits[d - 1, a]: whether the curve from frame a to a + d, between keys holding `values`
    and `slopes` there, keeps the bound by `error` (d <= max_gap).
    Lengths are tried in turn for every start at once; a start whose last PATIENCE lengths
    all broke the bound is not tried further (a longer segment almost never fits again)."""
    n, channels = values.shape
    fits = np.zeros((max_gap, n), dtype=bool)
    fits[0, : n - 1] = True  # neighbouring keys: no frame between
    last_fit = np.ones(n, dtype=np.int64)
    for d in range(2, max_gap + 1):
        a = np.flatnonzero(last_fit[: n - d] >= d - PATIENCE)
        if not len(a):
            break
        s = np.arange(1, d) / d                                  # (d - 1,) positions inside
        s2, s3 = s * s, s * s * s
        weights = np.stack([2 * s3 - 3 * s2 + 1, -2 * s3 + 3 * s2, (s3 - 2 * s2 + s) * d, (s3 - s2) * d])
        ends = np.stack([values[a], values[a + d], slopes[a], slopes[a + d]], axis=1)  # (A, 4, C)
        curve = np.matmul(weights.T, ends)                       # (A, d - 1, C)
        frames = a[:, None] + np.arange(1, d)[None, :]
        err = error(curve.reshape(-1, channels), frames.ravel()).reshape(len(a), d - 1)
        ok = err.max(axis=1) <= bound
        fits[d - 1, a] = ok
        last_fit[a[ok]] = d
    return fits


# ---------------------------------------------------------------- errors

def to_quaternions(values: np.ndarray, mode: str) -> np.ndarray:
    """(T, 4) unit quaternions (w, x, y, z) of a bone's rotation channels in Blender's
    `rotation_mode`: quaternion (normalised, as Blender poses it), axis-angle
    (angle, x, y, z) or Euler (Blender's orders are extrinsic: 'XYZ' is 'xyz' here)."""
    if mode == "QUATERNION":
        q = values
    elif mode == "AXIS_ANGLE":
        axis = values[:, 1:]
        norm = np.linalg.norm(axis, axis=1, keepdims=True)
        unit = np.where(norm > 1e-12, axis / np.where(norm > 1e-12, norm, 1.0), [[0.0, 1.0, 0.0]])
        q = np.concatenate([np.cos(values[:, :1] / 2), np.sin(values[:, :1] / 2) * unit], axis=1)
    elif mode in ROTATION_MODES:
        return _euler_quaternions(values, mode)
    else:
        raise DiffshegError(f"unknown rotation mode {mode!r}: expected one of {', '.join(ROTATION_MODES)}")
    return q / np.maximum(np.sqrt(np.sum(q * q, axis=1, keepdims=True)), 1e-12)


def _euler_quaternions(angles: np.ndarray, mode: str) -> np.ndarray:
    """(T, 4) unit quaternions of Blender Euler angles (radians) in `mode`: extrinsic, so
    'XYZ' turns about X, then Y, then Z (q = qz qy qx). The same as rotations.convert with
    order 'xyz' up to sign, written out because keys are fitted with it millions of times."""
    half = 0.5 * angles
    c, s = np.cos(half), np.sin(half)
    q = None
    for k in reversed(range(3)):
        axis = "XYZ".index(mode[k])
        e = np.zeros(angles.shape[:1] + (4,))
        e[:, 0], e[:, 1 + axis] = c[:, k], s[:, k]
        q = e if q is None else _product(q, e)
    return q


def _product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (T, 4) quaternions, scalar first."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return np.column_stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                            aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T,) angle in degrees between unit quaternions a and b (either sign): 4 asin(c / 2)
    with c the chord to the nearer of b and -b, |a -+ b|^2 = 2 - 2 |a . b|."""
    chord = np.sqrt(np.maximum(2.0 - 2.0 * np.abs(np.sum(a * b, axis=1)), 0.0))
    return np.degrees(4.0 * np.arcsin(np.minimum(chord / 2.0, 1.0)))


def rotation_error(target: np.ndarray, mode: str) -> ErrorFn:
    """Angle in degrees between the evaluated rotation and the motion's (`target`: the
    bone's channel values in `mode`, one row per frame)."""
    reference = to_quaternions(np.asarray(target, dtype=np.float64), mode)
    return lambda evaluated, frames: rotation_angle(to_quaternions(evaluated, mode), reference[frames])


def value_error(target: np.ndarray) -> ErrorFn:
    """Largest absolute difference over the channels (shape-key weights)."""
    target = np.asarray(target, dtype=np.float64)
    return lambda evaluated, frames: np.abs(evaluated - target[frames]).max(axis=1)
