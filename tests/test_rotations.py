"""Rotation conversions, continuity helpers and resampling (diffsheg_core.rotations)."""

import itertools
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
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation

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


# ------------------------------------------------------------------------------------
# The module is plain numpy (it runs inside Blender, which has no scipy); scipy is the
# reference here only.

ORDERS = ["".join(p) for p in itertools.product("XYZ", repeat=3)
          if p[0] != p[1] and p[1] != p[2]]
ALL_ORDERS = ORDERS + [o.lower() for o in ORDERS]
assert len(ALL_ORDERS) == 24


@pytest.fixture(scope="module")
def Rotation():
    return pytest.importorskip("scipy.spatial.transform").Rotation


def _sp_quat(rot) -> np.ndarray:
    """scipy's canonical quaternion, reordered to (w, x, y, z)."""
    return np.roll(rot.as_quat(canonical=True), 1, axis=-1)


def _to_sp(q: np.ndarray):
    from scipy.spatial.transform import Rotation
    return Rotation.from_quat(np.roll(q, -1, axis=-1))


def _wrapped_diff(a: np.ndarray, b: np.ndarray, period: float = 360.0) -> np.ndarray:
    return np.abs((a - b + period / 2) % period - period / 2)


def _edge_axis_angles(rng: np.random.Generator) -> np.ndarray:
    """Random rotation vectors plus angles 0, tiny, at the Taylor switch, near pi,
    exactly pi, past pi and several turns, about random and coordinate axes."""
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    axes = np.concatenate([axes, np.eye(3), -np.eye(3), [[1.0, 1.0, 0.0] / np.sqrt(2)]])
    angles = np.array([0.0, 1e-300, 1e-15, 1e-9, 1e-6, 1e-3, 1e-3 + 1e-12, 0.3, 2.0,
                       np.pi - 1e-6, np.pi - 1e-12, np.pi, np.pi + 1e-9, 4.0, 2 * np.pi,
                       7.5, -1.0])
    edge = (axes[:, None, :] * angles[None, :, None]).reshape(-1, 3)
    return np.concatenate([edge, rng.normal(scale=2.0, size=(500, 3))])


def _random_quaternions(rng: np.random.Generator) -> np.ndarray:
    """Unnormalised quaternions of both signs, plus half turns (w == 0, both signs of
    every component), the identity as -1 and w = -tiny."""
    q = rng.normal(size=(500, 4)) * rng.uniform(0.1, 10.0, size=(500, 1))
    special = [[1, 0, 0, 0], [-1, 0, 0, 0], [-2, 0, 0, 0], [0, 1, 0, 0], [0, -1, 0, 0],
               [0, 0, -1, 0], [0, 0, 0, -3], [0, 0, -1, 1], [0, -1, 1, 0], [-0.0, -1, 1, 1],
               [-1e-17, 0.6, -0.8, 0], [1e-17, -0.6, 0.8, 0], [-1e-9, 0, 0, 1],
               [1, 1e-300, 0, 0], [-1, -1e-12, 1e-12, 0]]
    return np.concatenate([q, np.asarray(special, dtype=float)])


def test_module_imports_only_numpy_and_the_standard_library():
    import ast
    import sys

    import diffsheg_core.rotations as rotations

    tree = ast.parse(Path(rotations.__file__).read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name.split(".")[0] for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:          # relative: only the package's own errors module
                assert node.module == "errors"
                continue
            names = [node.module.split(".")[0]]
        else:
            continue
        for name in names:
            assert name == "numpy" or name in sys.stdlib_module_names, name


def test_axis_angle_conversions_match_scipy(Rotation):
    aa = _edge_axis_angles(np.random.default_rng(10))
    ref = Rotation.from_rotvec(aa)
    q = axis_angle_to_quaternion(aa)
    np.testing.assert_allclose(q, _sp_quat(ref), rtol=0, atol=1e-12)
    np.testing.assert_allclose(axis_angle_to_matrix(aa), ref.as_matrix(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(convert(aa, "axis_angle", "axis_angle"), ref.as_rotvec(),
                               rtol=0, atol=1e-9)
    # relative precision where the angle is tiny
    tiny = aa[np.linalg.norm(aa, axis=-1) < 1e-5]
    np.testing.assert_allclose(quaternion_to_axis_angle(axis_angle_to_quaternion(tiny)), tiny,
                               rtol=1e-12, atol=0)


def test_quaternion_conversions_match_scipy_including_sign(Rotation):
    q = _random_quaternions(np.random.default_rng(11))
    ref = _to_sp(q)
    canonical = convert(q, "quaternion", "quaternion")
    np.testing.assert_allclose(canonical, _sp_quat(ref), rtol=0, atol=1e-12)
    assert np.all(canonical[:, 0] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(canonical, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(convert(q, "quaternion", "matrix"), ref.as_matrix(),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_axis_angle(q), ref.as_rotvec(), rtol=0, atol=1e-9)
    # a half turn has one representation: the first nonzero component is positive
    np.testing.assert_allclose(convert(np.array([0.0, 0, -1, 1]), "quaternion", "quaternion"),
                               np.array([0.0, 0, 1, -1]) / np.sqrt(2), atol=1e-15)
    np.testing.assert_allclose(quaternion_to_axis_angle(np.array([0.0, -1, 0, 0])),
                               [np.pi, 0, 0], atol=1e-15)


def test_matrix_conversions_match_scipy(Rotation):
    rng = np.random.default_rng(12)
    half_turns = Rotation.from_rotvec(np.pi * np.array(
        [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, -1, 1], [1, 1, 1], [-1, 2, 0.5]])
        / np.linalg.norm([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, -1, 1],
                          [1, 1, 1], [-1, 2, 0.5]], axis=-1, keepdims=True))
    exact = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]),
             _rz(np.pi / 2), _rx(-np.pi / 2) @ _ry(np.pi / 2)]
    m = np.concatenate([Rotation.random(500, random_state=1).as_matrix(), half_turns.as_matrix(),
                        Rotation.from_rotvec(_edge_axis_angles(rng)).as_matrix(), exact])
    ref = Rotation.from_matrix(m)
    np.testing.assert_allclose(convert(m, "matrix", "quaternion"), _sp_quat(ref),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(matrix_to_axis_angle(m), ref.as_rotvec(), rtol=0, atol=1e-9)
    # not orthogonal: both take the nearest rotation
    noisy = m[:500] + rng.normal(scale=1e-3, size=(500, 3, 3))
    np.testing.assert_allclose(convert(noisy, "matrix", "quaternion"),
                               _sp_quat(Rotation.from_matrix(noisy)), rtol=0, atol=1e-12)
    shape = convert(m[:12].reshape(3, 4, 3, 3), "matrix", "axis_angle").shape
    assert shape == (3, 4, 3)


@pytest.mark.parametrize("bad", [np.diag([1.0, 1, -1]), np.zeros((3, 3)),
                                 np.ones((2, 3, 3))])
def test_reflections_and_degenerate_matrices_raise(bad):
    with pytest.raises(DiffshegError, match="determinant"):
        convert(bad, "matrix", "quaternion")


@pytest.mark.parametrize("order", ALL_ORDERS)
def test_euler_to_rotation_matches_scipy_all_orders(order, Rotation):
    angles = np.random.default_rng(13).uniform(-720.0, 720.0, size=(300, 3))
    ref = Rotation.from_euler(order, angles, degrees=True)
    np.testing.assert_allclose(convert(angles, "euler", "quaternion", order=order),
                               _sp_quat(ref), rtol=0, atol=1e-12)
    radians = np.radians(angles)
    np.testing.assert_allclose(convert(radians, "euler", "matrix", order=order, degrees=False),
                               ref.as_matrix(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("order", ALL_ORDERS)
def test_rotation_to_euler_matches_scipy_all_orders(order, Rotation):
    q = _random_quaternions(np.random.default_rng(14))[:500]
    ref = _to_sp(q)
    ours = convert(q, "quaternion", "euler", order=order)
    expected = ref.as_euler(order, degrees=True)
    # same branch: scipy may give -180 where we give 180, nothing else differs
    assert _wrapped_diff(ours, expected).max() < 1e-9
    np.testing.assert_allclose(ours[:, 1], expected[:, 1], rtol=0, atol=1e-9)
    radians = convert(q, "quaternion", "euler", order=order, degrees=False)
    assert _wrapped_diff(radians, ref.as_euler(order), 2 * np.pi).max() < 1e-11
    _assert_euler_ranges(ours, order)
    np.testing.assert_allclose(convert(ours, "euler", "matrix", order=order), ref.as_matrix(),
                               rtol=0, atol=1e-12)


def _assert_euler_ranges(angles: np.ndarray, order: str) -> None:
    assert np.all(angles[..., [0, 2]] > -180.0) and np.all(angles[..., [0, 2]] <= 180.0)
    if order[0] == order[2]:
        assert np.all(angles[..., 1] >= 0.0) and np.all(angles[..., 1] <= 180.0)
    else:
        assert np.all(np.abs(angles[..., 1]) <= 90.0)


@pytest.mark.parametrize("order", ALL_ORDERS)
def test_euler_at_gimbal_lock_gives_the_rotation_with_third_angle_zero(order, Rotation):
    import warnings

    rng = np.random.default_rng(15)
    locks = [0.0, 180.0] if order[0] == order[2] else [90.0, -90.0]
    # exactly at the lock, within scipy's 1e-7 rad of it, and just outside it
    offsets = [0.0, 1e-12, -1e-12, 3e-6, -3e-6, 1e-4, -1e-4]
    middle = np.array([lock + off for lock in locks for off in offsets
                       if abs(lock + off) <= 180.0 and (order[0] != order[2] or lock + off >= 0)])
    angles = rng.uniform(-180.0, 180.0, size=(len(middle), 20, 3))
    angles[..., 1] = middle[:, None]
    angles = angles.reshape(-1, 3)
    angles = np.concatenate([angles, [[0.0, locks[0], 0.0], [180.0, locks[1], 180.0]]])
    ref = Rotation.from_euler(order, angles, degrees=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        expected = ref.as_euler(order, degrees=True)
    ours = convert(angles, "euler", "euler", order=order)
    _assert_euler_ranges(ours, order)
    mine = convert(ours, "euler", "matrix", order=order)
    np.testing.assert_allclose(mine, Rotation.from_euler(order, expected, degrees=True)
                               .as_matrix(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours[:, 1], expected[:, 1], rtol=0, atol=1e-9)
    locked = np.abs(np.radians(expected[:, 1]) - np.radians(
        np.array(locks)[:, None])).min(axis=0) <= 1e-7 - 1e-12
    assert locked.sum() >= 100
    # the rotation is kept, except that a middle angle within 1e-7 rad of the lock
    # is snapped onto it (as scipy does)
    snapped = np.abs(np.abs(angles[:, 1]) - np.abs(np.round(angles[:, 1] / 90) * 90)) > 1e-9
    np.testing.assert_allclose(mine[~snapped], ref.as_matrix()[~snapped], rtol=0, atol=1e-9)
    np.testing.assert_allclose(mine[snapped], ref.as_matrix()[snapped], rtol=0, atol=2e-7)
    np.testing.assert_array_equal(ours[locked, 2], 0.0)
    np.testing.assert_array_equal(expected[locked, 2], 0.0)
    # where both agree on the lock, the free angle is the same too
    assert _wrapped_diff(ours[locked], expected[locked]).max() < 1e-6


@pytest.mark.parametrize("order", ALL_ORDERS)
def test_half_turns_and_identity_to_euler(order, Rotation):
    import warnings

    q = np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, -1, 0, 0],
                  [0, 1, 1, 0], [0, 0, -1, 1]])
    ours = convert(q, "quaternion", "euler", order=order)
    _assert_euler_ranges(ours, order)
    np.testing.assert_allclose(convert(ours, "euler", "matrix", order=order),
                               convert(q, "quaternion", "matrix"), atol=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        expected = _to_sp(q).as_euler(order, degrees=True)
    np.testing.assert_allclose(ours[:, 1], expected[:, 1], atol=1e-9)


def test_euler_keeps_leading_shape_and_radians():
    angles = np.random.default_rng(16).uniform(-180, 180, size=(4, 5, 3))
    for order in ("XYZ", "zxz"):
        back = convert(convert(angles, "euler", "quaternion", order=order),
                       "quaternion", "euler", order=order)
        assert back.shape == (4, 5, 3)
        np.testing.assert_allclose(convert(back, "euler", "matrix", order=order),
                                   convert(angles, "euler", "matrix", order=order), atol=1e-12)


def _scipy_slerp_resample(rotations: np.ndarray, src_fps: float, dst_fps: float,
                          n_out: int | None = None) -> np.ndarray:
    """Reference: scipy's Slerp per joint at the output times (held past the end)."""
    from scipy.spatial.transform import Rotation, Slerp

    t_src = np.arange(len(rotations)) / src_fps
    n = len(resample_weights(np.zeros((len(rotations), 1)), src_fps, dst_fps, n_out=n_out))
    t_out = np.minimum(np.arange(n) / dst_fps, t_src[-1])
    return np.stack([Slerp(t_src, Rotation.from_rotvec(rotations[:, j]))(t_out).as_rotvec()
                     for j in range(rotations.shape[1])], axis=1)


@pytest.mark.parametrize("fps", [(15.0, 60.0), (30.0, 25.0), (60.0, 30.0), (24.0, 29.97)])
def test_slerp_resample_matches_scipy_slerp(fps, Rotation):
    rng = np.random.default_rng(17)
    rotations = rng.normal(scale=1.5, size=(40, 6, 3))
    rotations[5:9, 1] = rotations[4, 1]                          # held pose
    rotations[:, 2] = rotations[0, 2] + rng.normal(scale=1e-8, size=(40, 3))   # tiny steps
    rotations[1::2, 3] = -rotations[::2, 3] * 0.999              # near-opposite neighbours
    rotations[:, 4] = (rng.uniform(np.pi - 1e-6, np.pi, size=(40, 1))
                       * np.array([0.0, 0.6, 0.8]))            # near half turns
    rotations[::2, 5] = 0.0                                      # exact half-turn steps
    rotations[1::2, 5] = [np.pi, 0.0, 0.0]
    ours = slerp_resample(rotations, *fps)
    expected = _scipy_slerp_resample(rotations, *fps)
    assert ours.shape == expected.shape
    assert _geodesic(ours, expected).max() < 1e-9
    safe = np.linalg.norm(expected, axis=-1) < np.pi - 1e-6      # rotvec sign is unique here
    np.testing.assert_allclose(ours[safe], expected[safe], rtol=0, atol=1e-9)
    long = slerp_resample(rotations, *fps, n_out=len(ours) + 5)      # held past the end
    assert _geodesic(long, _scipy_slerp_resample(rotations, *fps, len(ours) + 5)).max() < 1e-9
    assert _geodesic(long[-5:], np.broadcast_to(rotations[-1], (5, 6, 3))).max() < 1e-9


def test_slerp_resample_single_frame():
    rotations = np.array([[[0.1, 0.2, 0.3]]])
    out = slerp_resample(rotations, 15.0, 30.0, n_out=3)
    np.testing.assert_allclose(out, np.repeat(rotations, 3, axis=0), atol=1e-15)


def _pchip_cases(rng: np.random.Generator) -> list[np.ndarray]:
    steps = np.array([0, 0, 0, 0.05, 1, 1, 0.9, 0.05, 0, 0, 1, 0, 0.5, 0.5, 0.5, 2, -1])
    return [
        rng.normal(size=(50, 8)),                                  # sign changes everywhere
        np.cumsum(rng.uniform(0, 1, size=(30, 4)), axis=0),        # monotone
        np.repeat(steps[:, None], 2, axis=1) * [1.0, -3.0],        # flats and steps
        np.array([[0.0, 1.0, 0.0], [1.0, 1.0, 2.0]]),              # two samples: a line
        np.array([[0.0, 0.0, 1.0, 5.0], [1.0, 0.0, 0.0, 0.0], [3.0, 1.0, 0.0, 5.0]]),
        # end-slope rules: sign flip of the estimate, and the 3 m0 limit
        np.array([[0.0, 0.0], [1.0, 0.1], [5.0, -1.0], [5.5, -4.0], [0.0, 0.0]]),
        np.array([[0.0], [1.0], [0.0], [1e-9], [1.0]]),
    ]


@pytest.mark.parametrize("fps", [(15.0, 60.0), (30.0, 7.3), (25.0, 30.0), (60.0, 60.0)])
def test_resample_weights_cubic_matches_scipy_pchip(fps):
    PchipInterpolator = pytest.importorskip("scipy.interpolate").PchipInterpolator
    from diffsheg_core.rotations import resample_positions

    for values in _pchip_cases(np.random.default_rng(18)):
        n_out = len(resample_positions(len(values), *fps)) + 3   # also past the end
        ours = resample_weights(values, *fps, n_out=n_out)
        pos = resample_positions(len(values), *fps, n_out=n_out)
        expected = PchipInterpolator(np.arange(len(values)), values, axis=0)(pos)
        np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-12 * np.abs(values).max())


def test_pchip_matches_scipy_at_random_positions_and_slopes():
    PchipInterpolator = pytest.importorskip("scipy.interpolate").PchipInterpolator
    from diffsheg_core.rotations import _pchip

    rng = np.random.default_rng(19)
    for values in _pchip_cases(rng):
        pos = np.concatenate([rng.uniform(0, len(values) - 1, size=200),
                              np.arange(len(values)), [len(values) - 1 - 1e-15]])
        spline = PchipInterpolator(np.arange(len(values)), values, axis=0)
        np.testing.assert_allclose(_pchip(values, pos), spline(pos), rtol=0, atol=1e-12)
        eps = 1e-6   # slopes at the knots, from the right, agree with scipy's
        knots = np.arange(len(values) - 1, dtype=float)
        ours = (_pchip(values, knots + eps) - _pchip(values, knots)) / eps
        np.testing.assert_allclose(ours, spline(knots + eps / 2, 1), rtol=0, atol=1e-5)
