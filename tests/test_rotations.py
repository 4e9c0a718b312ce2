"""Rotation conversions, continuity helpers and resampling (diffsheg_core.rotations)."""

from pathlib import Path

import numpy as np
import pytest

from diffsheg_core.bvh import read_bvh
from diffsheg_core.errors import DiffshegError
from diffsheg_core.rotations import (
    axis_angle_to_euler, axis_angle_to_matrix, axis_angle_to_quaternion, convert,
    euler_continuous, euler_to_axis_angle, matrix_to_axis_angle, quaternion_sequence_continuous,
    quaternion_to_axis_angle, resample_weights, slerp_resample,
)

BVH = Path(__file__).resolve().parents[2] / "shared" / "data" / "beat" / "2_scott_0_1_1.bvh"


@pytest.fixture(scope="module")
def forearm_euler() -> np.ndarray:
    """RightForeArm of the real BEAT take: Euler XYZ degrees, wrapped over several turns."""
    data = read_bvh(BVH, fps=15)
    cols, _ = data.rotation_columns("RightForeArm")
    return data.frames[1:, cols]


def _random_axis_angle(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    axis = rng.normal(size=shape + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    return axis * rng.uniform(0.0, np.pi * 0.99, size=shape + (1,))


def _geodesic(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (radians) between two sets of axis-angle rotations."""
    rel = np.swapaxes(axis_angle_to_matrix(a), -1, -2) @ axis_angle_to_matrix(b)
    return np.linalg.norm(matrix_to_axis_angle(rel), axis=-1)


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_conversions_round_trip_and_keep_leading_shape():
    aa = _random_axis_angle(np.random.default_rng(0), (20, 47))
    q = axis_angle_to_quaternion(aa)
    assert q.shape == (20, 47, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_axis_angle(q), aa, atol=1e-9)
    m = axis_angle_to_matrix(aa)
    assert m.shape == (20, 47, 3, 3)
    np.testing.assert_allclose(matrix_to_axis_angle(m), aa, atol=1e-9)
    for order in ("XYZ", "ZXY", "YZX", "xyz", "ZXZ"):
        euler = axis_angle_to_euler(aa, order)
        np.testing.assert_allclose(euler_to_axis_angle(euler, order), aa, atol=1e-9)
    np.testing.assert_allclose(convert(q, "quaternion", "matrix"), m, atol=1e-12)


@pytest.mark.parametrize("order", ["XYZ", "ZXY", "YZX", "xyz", "zyx", "ZXZ", "xzx"])
def test_euler_matches_scipy_convention(order):
    from scipy.spatial.transform import Rotation

    angles = np.random.default_rng(2).uniform(-400.0, 400.0, size=(500, 3))
    expected = Rotation.from_euler(order, angles, degrees=True).as_matrix()
    np.testing.assert_allclose(convert(angles, "euler", "matrix", order=order), expected, atol=1e-12)


def test_quaternion_is_scalar_first():
    q = axis_angle_to_quaternion(np.array([np.pi / 2, 0.0, 0.0]))
    np.testing.assert_allclose(q, [np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0], atol=1e-12)


def test_upper_case_order_is_intrinsic_lower_case_extrinsic():
    a, b, c = 30.0, -50.0, 110.0
    ra, rb, rc = np.radians([a, b, c])
    intrinsic = axis_angle_to_matrix(euler_to_axis_angle(np.array([a, b, c]), "XYZ"))
    np.testing.assert_allclose(intrinsic, _rx(ra) @ _ry(rb) @ _rz(rc), atol=1e-12)
    extrinsic = axis_angle_to_matrix(euler_to_axis_angle(np.array([a, b, c]), "xyz"))
    np.testing.assert_allclose(extrinsic, _rz(rc) @ _ry(rb) @ _rx(ra), atol=1e-12)
    radians = euler_to_axis_angle(np.array([ra, rb, rc]), "XYZ", degrees=False)
    np.testing.assert_allclose(axis_angle_to_matrix(radians), intrinsic, atol=1e-12)


@pytest.mark.blender
def test_blender_euler_xyz_is_extrinsic_xyz():
    pytest.importorskip("bpy")
    import mathutils

    euler = (0.3, -0.7, 1.1)
    ours = axis_angle_to_matrix(euler_to_axis_angle(np.array(euler), "xyz", degrees=False))
    blender = np.array(mathutils.Euler(euler, "XYZ").to_matrix())
    np.testing.assert_allclose(ours, blender, atol=1e-6)
    q = mathutils.Euler(euler, "XYZ").to_quaternion()
    ours_q = convert(np.array(euler), "euler", "quaternion", order="xyz", degrees=False)
    np.testing.assert_allclose(ours_q, [q.w, q.x, q.y, q.z], atol=1e-6)


@pytest.mark.parametrize("bad, kind", [
    (np.zeros((4, 2)), "axis_angle"),
    (np.full((2, 3), np.nan), "axis_angle"),
    (np.zeros((3, 4)), "quaternion"),
    (np.zeros((2, 3)), "rotvec"),
])
def test_bad_rotation_arrays_raise(bad, kind):
    with pytest.raises(DiffshegError):
        convert(bad, kind, "matrix")


def test_bad_euler_order_raises():
    for order in ("XXY", "XYz", "AB", None):
        with pytest.raises(DiffshegError, match="Euler order"):
            convert(np.zeros(3), "euler", "matrix", order=order)


def test_quaternion_sequence_continuous_on_real_motion(forearm_euler):
    q = convert(forearm_euler, "euler", "quaternion", order="XYZ")
    flips = np.random.default_rng(1).choice([-1.0, 1.0], size=(len(q), 1))
    smooth = quaternion_sequence_continuous(q * flips)
    assert np.all(np.sum(smooth[1:] * smooth[:-1], axis=-1) >= 0.0)
    same = np.abs(np.sum(smooth * q, axis=-1))
    np.testing.assert_allclose(same, 1.0, atol=1e-12)


def test_quaternion_sequence_continuous_per_joint():
    q = np.array([[[1.0, 0, 0, 0], [0, 1.0, 0, 0]], [[-1.0, 0, 0, 0], [0, 1.0, 0, 0]]])
    out = quaternion_sequence_continuous(q)
    np.testing.assert_array_equal(out[1], [[1.0, 0, 0, 0], [0, 1.0, 0, 0]])


def test_euler_continuous_removes_turn_jumps_and_keeps_rotations(forearm_euler):
    canonical = axis_angle_to_euler(euler_to_axis_angle(forearm_euler, "XYZ"), "XYZ")
    continuous = euler_continuous(canonical, "XYZ", reference=forearm_euler[0])
    step = np.linalg.norm(np.diff(continuous, axis=0), axis=-1).max()
    assert np.abs(np.diff(canonical, axis=0)).max() > 300.0
    # near gimbal lock (Y = 90) X and Z swing by design; the capture's own export swings more
    assert step <= np.linalg.norm(np.diff(forearm_euler, axis=0), axis=-1).max()
    assert np.abs(np.diff(continuous, axis=0)).max() < 180.0
    np.testing.assert_allclose(continuous[0], forearm_euler[0], atol=1e-6)
    before = euler_to_axis_angle(forearm_euler, "XYZ")
    after = euler_to_axis_angle(continuous, "XYZ")
    assert _geodesic(before, after).max() < 1e-9


def test_euler_continuous_proper_euler_branch():
    angles = np.array([[10.0, 40.0, -20.0], [190.0, -40.0, 160.0]])
    out = euler_continuous(angles, "ZXZ")
    np.testing.assert_allclose(out[1], angles[0], atol=1e-9)


def _reference_slerp(q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
    """Textbook slerp on scalar-first unit quaternions, shortest arc."""
    if np.dot(q0, q1) < 0:
        q1 = -q1
    theta = np.arccos(np.clip(np.dot(q0, q1), -1.0, 1.0))
    if theta < 1e-9:
        return q0
    return (np.sin((1 - w) * theta) * q0 + np.sin(w * theta) * q1) / np.sin(theta)


def test_slerp_resample_constant_rate_rotation_stays_on_geodesic():
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    t_src = np.arange(31) / 15.0
    rotations = (t_src[:, None] * 1.4 * axis)[:, None, :]
    out = slerp_resample(rotations, 15.0, 60.0)
    assert out.shape == (121, 1, 3)
    t_out = np.arange(121) / 60.0
    np.testing.assert_allclose(out[:, 0], t_out[:, None] * 1.4 * axis, atol=1e-9)


def test_slerp_resample_matches_textbook_slerp_on_real_motion(forearm_euler):
    rotations = euler_to_axis_angle(forearm_euler[:60], "XYZ")[:, None, :]
    out = slerp_resample(rotations, 15.0, 25.0)
    assert len(out) == int(np.floor(59 * 25 / 15)) + 1
    q = axis_angle_to_quaternion(rotations[:, 0])
    for i in range(len(out)):
        pos = i * 15.0 / 25.0
        k = min(int(pos), 58)
        expected = quaternion_to_axis_angle(_reference_slerp(q[k], q[k + 1], pos - k))
        assert _geodesic(out[i, 0], expected) < 1e-9


def test_slerp_resample_at_source_times_returns_source_frames(forearm_euler):
    rotations = euler_to_axis_angle(forearm_euler[:40], "XYZ")[:, None, :]
    out = slerp_resample(rotations, 15.0, 30.0)
    assert len(out) == 79
    assert _geodesic(out[::2], rotations).max() < 1e-9


def test_slerp_resample_explicit_length_holds_last_frame():
    rotations = np.array([[[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.5]]])
    out = slerp_resample(rotations, 15.0, 30.0, n_out=5)
    np.testing.assert_allclose(out[:, 0, 2], [0.0, 0.25, 0.5, 0.5, 0.5], atol=1e-12)


def test_resample_weights_pchip_does_not_overshoot_a_blink():
    blink = np.array([0, 0, 0, 0.05, 1, 1, 0.9, 0.05, 0, 0], dtype=float)[:, None]
    out = resample_weights(blink, 15.0, 60.0, kind="cubic")
    assert out.min() >= 0.0 and out.max() <= 1.0
    np.testing.assert_allclose(out[::4], blink, atol=1e-12)
    linear = resample_weights(blink, 15.0, 60.0, kind="linear")
    np.testing.assert_allclose(linear[2::4], (blink[:-1] + blink[1:]) / 2, atol=1e-12)


def test_resample_weights_rejects_bad_input():
    with pytest.raises(DiffshegError, match="interpolation"):
        resample_weights(np.zeros((5, 2)), 15, 30, kind="quadratic")
    with pytest.raises(DiffshegError, match="positive"):
        resample_weights(np.zeros((5, 2)), 15, 0)
    with pytest.raises(DiffshegError, match=r"\(T, K\)"):
        resample_weights(np.zeros(5), 15, 30)
