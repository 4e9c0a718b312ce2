"""Sparse keys (diffsheg_core.keyframes) on real motion capture: the BEAT take, 15 fps,
resampled to a 24 fps scene as the add-on does."""

from __future__ import annotations

import numpy as np
import pytest

from diffsheg_core import keyframes as kf
from diffsheg_core.bvh import bvh_to_motion, read_bvh
from diffsheg_core.errors import DiffshegError
from diffsheg_core.motion import resample_motion
from diffsheg_core.rotations import axis_angle_to_quaternion, convert, quaternion_sequence_continuous


@pytest.fixture(scope="module")
def capture(data_dir):
    motion = bvh_to_motion(read_bvh(data_dir / "beat" / "2_scott_0_1_1.bvh", fps=15.0))
    motion = resample_motion(motion, 24.0)
    n = 24 * 20  # 20 s
    return {name: quaternion_sequence_continuous(axis_angle_to_quaternion(motion.rotations[:n, j]))
            for j, name in enumerate(motion.joint_names)}


def test_hermite_keys_hold_the_bound_on_every_frame_of_real_capture(capture):
    """Every joint of 20 s of capture within 1 degree on every frame, at a few keys per second."""
    rates = []
    for name, q in capture.items():
        error = kf.rotation_error(q, "QUATERNION")
        keys = kf.fit_keys(q, error, 1.0)
        n = len(q)
        assert keys.frames[0] == 0 and keys.frames[-1] == n - 1 and np.all(np.diff(keys.frames) > 0)
        np.testing.assert_array_equal(keys.values, q[keys.frames])  # each key is the pose at its frame
        assert error(kf.evaluate(keys, n), np.arange(n)).max() <= 1.0, name
        rates.append(len(keys) / 20.0)
    assert np.mean(rates) < 3.0, np.mean(rates)


def test_a_tighter_bound_takes_more_keys(capture):
    q = capture["RightForeArm"]
    counts = [len(kf.fit_keys(q, kf.rotation_error(q, "QUATERNION"), b)) for b in (4.0, 1.0, 0.25)]
    assert counts[0] < counts[1] < counts[2]


def test_euler_and_axis_angle_channels_are_measured_as_rotations(capture):
    """A bone in Euler XYZ (Blender's: extrinsic) or axis-angle mode: the angle error is that
    of the rotation, the same as for its quaternions."""
    q = capture["LeftArm"]
    euler = convert(q, "quaternion", "euler", order="xyz", degrees=False)
    np.testing.assert_allclose(np.abs(np.sum(kf.to_quaternions(euler, "XYZ") * q, axis=1)), 1.0, atol=1e-9)
    vec = convert(q, "quaternion", "axis_angle")
    angle = np.linalg.norm(vec, axis=1, keepdims=True)
    blender = np.concatenate([angle, vec / np.maximum(angle, 1e-12)], axis=1)
    np.testing.assert_allclose(np.abs(np.sum(kf.to_quaternions(blender, "AXIS_ANGLE") * q, axis=1)), 1.0,
                               atol=1e-9)
    keys = kf.fit_keys(euler, kf.rotation_error(euler, "XYZ"), 1.0)
    assert kf.rotation_error(euler, "XYZ")(kf.evaluate(keys, len(q)), np.arange(len(q))).max() <= 1.0


def test_handles_are_a_third_along_the_slope_and_aligned():
    keys = kf.Keys(np.array([0, 6, 9]), np.array([[0.0], [1.0], [0.5]]), np.array([[0.3], [0.0], [-0.2]]))
    left, right = kf.handles(keys)
    np.testing.assert_allclose(right[0, 0], [2.0, 0.6])
    np.testing.assert_allclose(left[1, 0], [4.0, 1.0])
    np.testing.assert_allclose(right[1, 0], [7.0, 1.0])
    np.testing.assert_allclose(left[2, 0], [8.0, 0.7])
    # the Bezier through these handles is the Hermite curve: at a third of the way, exactly
    s = 1 / 3
    bezier = (1 - s) ** 3 * 0 + 3 * (1 - s) ** 2 * s * 0.6 + 3 * (1 - s) * s ** 2 * 1.0 + s ** 3 * 1.0
    assert kf.evaluate(keys, 10)[2, 0] == pytest.approx(bezier)


def test_shape_key_weights_within_their_bound_and_keys_on_the_extremes():
    t = np.arange(240) / 24.0
    weight = (0.5 + 0.5 * np.sin(2 * np.pi * 1.3 * t) * np.exp(-0.1 * t))[:, None]
    keys = kf.fit_keys(weight, kf.value_error(weight), 0.02)
    assert np.abs(kf.evaluate(keys, 240) - weight).max() <= 0.02
    extremes = kf.turning_points(weight)
    assert all(np.abs(extremes - f).min() <= 1 for f in keys.frames[1:-1])


@pytest.mark.parametrize("values,bound,match", [
    (np.full((10, 1), np.nan), 1.0, "finite"),
    (np.zeros(10), 1.0, "finite"),
    (np.zeros((10, 1)), 0.0, "above 0"),
    (np.zeros((10, 1)), float("inf"), "above 0"),
])
def test_bad_input_is_refused(values, bound, match):
    with pytest.raises(DiffshegError, match=match):
        kf.fit_keys(values, lambda v, f: np.zeros(len(v)), bound)


def test_short_and_still_channels():
    assert len(kf.fit_keys(np.ones((1, 2)), lambda v, f: np.zeros(len(v)), 1.0)) == 1
    still = np.ones((500, 1))
    keys = kf.fit_keys(still, kf.value_error(still), 0.01)
    np.testing.assert_array_equal(keys.frames, [0, 499])  # a hold: its first and last frame
