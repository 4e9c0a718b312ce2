"""Rotation conversions and frame-rate resampling of rotations and weights.

Conventions, fixed for the whole package:
- axis-angle: (..., 3) vectors, angle in radians = norm, as the models produce.
- quaternion: (..., 4) as (w, x, y, z), scalar first, as Blender stores them.
- matrix: (..., 3, 3), acting on column vectors.
- Euler: (..., 3) angles in the order of `order`, in degrees unless `degrees=False`.
  An upper-case order ('XYZ', 'ZXY') is intrinsic: rotate about X, then about the
  new Y, then the new Z, so R = Rx @ Ry @ Rz. This is how a BVH channel list such as
  "Xrotation Yrotation Zrotation" is read. A lower-case order ('xyz') is extrinsic
  (fixed axes, R = Rz @ Ry @ Rx): Blender's `rotation_mode = 'XYZ'` is extrinsic
  'xyz' here, equal to intrinsic 'ZYX'.

Everything is plain numpy (Blender ships numpy but not scipy); all conversions go
through unit quaternions. Results agree with scipy's `Rotation` (same canonical
choices: w >= 0, Tait-Bryan middle angle in [-90, 90], proper-Euler middle angle in
[0, 180], gimbal lock sets the third angle to zero), except that first and third Euler
angles lie in (-180, 180] where scipy may also return -180.
"""

from __future__ import annotations

import numpy as np

from .errors import DiffshegError

_TRAILING = {"axis_angle": (3,), "quaternion": (4,), "matrix": (3, 3), "euler": (3,)}
# Middle Euler angle this close (radians) to a singular value counts as gimbal lock.
_GIMBAL_EPS = 1e-7


def _check_kind(kind: str) -> tuple[int, ...]:
    try:
        return _TRAILING[kind]
    except KeyError:
        raise DiffshegError(
            f"unknown rotation kind '{kind}': choose one of {', '.join(_TRAILING)}") from None


def _check_order(order: str | None) -> str:
    if order is None or len(order) != 3 or not (order.isupper() or order.islower()) \
            or set(order.lower()) - set("xyz") or order[0] == order[1] or order[1] == order[2]:
        raise DiffshegError(
            f"Euler order {order!r} is not valid: give three axes such as 'XYZ' "
            "(upper case = intrinsic, as BVH channels) or 'xyz' (lower case = extrinsic)")
    return order


# ---------------------------------------------------------------- quaternion algebra

def quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) scalar-first quaternions."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quaternion_conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _canonical(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with w >= 0, one per rotation (q and -q are the same rotation).

    When w == 0 (a half turn) the first nonzero of x, y, z is made positive, as scipy
    does, so that a half turn also has a single representation.
    """
    q = _normalize(q)
    first = np.take_along_axis(q, np.argmax(q != 0.0, axis=-1)[..., None], axis=-1)
    return np.where(first < 0.0, -q, q)


# ---------------------------------------------------------------- to / from quaternion

def _axis_angle_to_quaternion(v: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    # sin(angle / 2) / angle, written with sinc so it stays exact (-> 1/2) at angle 0
    scale = 0.5 * np.sinc(angle / (2.0 * np.pi))
    return np.concatenate([np.cos(0.5 * angle), v * scale], axis=-1)


def _quaternion_to_axis_angle(q: np.ndarray) -> np.ndarray:
    """Rotation vector of the canonical (w >= 0) quaternion, so the angle is in [0, pi].

    angle = 2 atan2(|v|, w) is accurate at both ends (unlike acos(w) near 0 or
    asin(|v|) near pi), and angle / |v| keeps full relative precision for tiny |v|.
    """
    q = _canonical(q)
    norm = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(norm, q[..., :1])
    scale = np.divide(angle, norm, out=np.full_like(norm, 2.0), where=norm > 0.0)
    return q[..., 1:] * scale


def _quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(_normalize(q), -1, 0)
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """Reject reflections and degenerate frames; replace matrices that are not
    orthogonal (to 1e-12) by the nearest rotation, U @ Vt of their SVD."""
    if np.any(np.linalg.det(m) <= 0.0):
        raise DiffshegError(
            "matrix array holds a matrix with non-positive determinant "
            "(a reflection or a degenerate frame), which is not a rotation")
    gram = m @ np.swapaxes(m, -1, -2)
    skewed = np.any(np.abs(gram - np.eye(3)) > 1e-12, axis=(-2, -1))
    if np.any(skewed):
        m = m.copy()
        u, _, vt = np.linalg.svd(m[skewed])
        m[skewed] = u @ vt
    return m


def _matrix_to_quaternion(m: np.ndarray) -> np.ndarray:
    """Shepperd's method. Each row below is 4 * c * q, where c is one of w, x, y, z
    (4 w^2 = 1 + trace, 4 x^2 = 1 + 2 m00 - trace, the off-diagonal sums and
    differences give the cross terms). Dividing by the largest c, picked through the
    largest of (m00, m11, m22, trace), keeps it well away from zero."""
    m = _nearest_rotation(m)
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = (
        np.moveaxis(m[..., r, :], -1, 0) for r in range(3))
    trace = m00 + m11 + m22
    rows = np.stack([
        np.stack([m21 - m12, 1 + 2 * m00 - trace, m01 + m10, m02 + m20], axis=-1),
        np.stack([m02 - m20, m01 + m10, 1 + 2 * m11 - trace, m12 + m21], axis=-1),
        np.stack([m10 - m01, m02 + m20, m12 + m21, 1 + 2 * m22 - trace], axis=-1),
        np.stack([1 + trace, m21 - m12, m02 - m20, m10 - m01], axis=-1),
    ], axis=-2)
    pick = np.argmax(np.stack([m00, m11, m22, trace], axis=-1), axis=-1)
    return _normalize(np.take_along_axis(rows, pick[..., None, None], axis=-2)[..., 0, :])


def _euler_to_quaternion(angles: np.ndarray, order: str, degrees: bool) -> np.ndarray:
    """(..., 3) Euler angles -> (..., 4) scalar-first quaternions: the product of the
    three elementary rotations (reversed for extrinsic orders)."""
    half = 0.5 * (np.radians(angles) if degrees else angles)
    elementary = []
    for k, axis in enumerate(order.lower()):
        q = np.zeros(angles.shape[:-1] + (4,))
        q[..., 0] = np.cos(half[..., k])
        q[..., 1 + "xyz".index(axis)] = np.sin(half[..., k])
        elementary.append(q)
    if order.islower():
        elementary.reverse()
    return quaternion_product(quaternion_product(elementary[0], elementary[1]), elementary[2])


def _wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles in [-2 pi, 2 pi] -> (-pi, pi]."""
    return np.where(a > np.pi, a - 2 * np.pi, np.where(a <= -np.pi, a + 2 * np.pi, a))


def _quaternion_to_euler(q: np.ndarray, order: str, degrees: bool) -> np.ndarray:
    """Euler angles (first/third in (-pi, pi], middle in [-pi/2, pi/2] for Tait-Bryan
    orders, [0, pi] for proper ones); at gimbal lock the third angle is set to 0.

    Work with the extrinsic sequence R = R_k(c) R_j(b) R_i(a) (an intrinsic order
    'IJK' is the extrinsic sequence k, j, i with the angles reversed). Multiplying
    out the three half-angle quaternions, with e_i e_j = s e_l:
    - proper (i == k, l the unused axis):
        (w, q_i) = cos(b/2) (cos, sin)((a + c)/2)
        (q_j, s q_l) = sin(b/2) (cos, sin)((c - a)/2)
    - Tait-Bryan (l == k), writing C, S = cos(b/2), sin(b/2):
        (w - s q_j, q_i + q_k) = (C - s S) (cos, sin)((a + c)/2)
        (w + s q_j, q_k - q_i) = (C + s S) (cos, sin)((c - a)/2)
    So the two pairs give (a + c)/2 and (c - a)/2 by atan2 and b from the ratio of
    their lengths. When one pair vanishes (gimbal lock) its angle is undefined and
    only a + c or c - a is known.
    """
    extrinsic = order.islower()
    i, j, k = ("xyz".index(axis) for axis in (order if extrinsic else order[::-1]).lower())
    proper = i == k
    if proper:
        k = 3 - i - j
    s = 1.0 if (j - i) % 3 == 1 else -1.0
    q = _normalize(q)
    w, qi, qj, qk = q[..., 0], q[..., 1 + i], q[..., 1 + j], q[..., 1 + k]
    if proper:
        sum_pair, diff_pair = (w, qi), (qj, s * qk)
    else:
        sum_pair, diff_pair = (w - s * qj, qi + qk), (w + s * qj, qk - qi)
    half_sum = np.arctan2(sum_pair[1], sum_pair[0])
    half_diff = np.arctan2(diff_pair[1], diff_pair[0])
    beta = 2.0 * np.arctan2(np.hypot(*diff_pair), np.hypot(*sum_pair))  # in [0, pi]
    # gimbal lock: choose the undefined half angle so the user's third angle is 0,
    # which is c for an extrinsic order and a for an intrinsic one
    third_sign = -1.0 if extrinsic else 1.0
    half_diff = np.where(beta <= _GIMBAL_EPS, third_sign * half_sum, half_diff)
    half_sum = np.where(beta >= np.pi - _GIMBAL_EPS, third_sign * half_diff, half_sum)
    a = _wrap_angle(half_sum - half_diff)
    b = beta if proper else s * (beta - 0.5 * np.pi)
    c = _wrap_angle(half_sum + half_diff)
    angles = np.stack([a, b, c] if extrinsic else [c, b, a], axis=-1)
    return np.degrees(angles) if degrees else angles


def _to_quaternion(values: np.ndarray, kind: str, order: str | None, degrees: bool
                   ) -> tuple[np.ndarray, tuple[int, ...]]:
    """Validated (..., 4) unit quaternions and the leading shape."""
    trailing = _check_kind(kind)
    values = np.asarray(values, dtype=np.float64)
    if values.shape[values.ndim - len(trailing):] != trailing:
        raise DiffshegError(
            f"{kind} array must end in shape {trailing}, got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise DiffshegError(f"{kind} array holds NaN or infinite values")
    lead = values.shape[: values.ndim - len(trailing)]
    if kind == "axis_angle":
        q = _axis_angle_to_quaternion(values)
    elif kind == "quaternion":
        if np.any(np.linalg.norm(values, axis=-1) < 1e-12):
            raise DiffshegError("quaternion array holds a zero quaternion")
        q = values
    elif kind == "matrix":
        q = _matrix_to_quaternion(values)
    else:
        q = _euler_to_quaternion(values, _check_order(order), degrees)
    return _normalize(q), lead


def _from_quaternion(q: np.ndarray, lead: tuple[int, ...], kind: str, order: str | None,
                     degrees: bool) -> np.ndarray:
    trailing = _check_kind(kind)
    if kind == "axis_angle":
        out = _quaternion_to_axis_angle(q)
    elif kind == "quaternion":
        out = _canonical(q)
    elif kind == "matrix":
        out = _quaternion_to_matrix(q)
    else:
        out = _quaternion_to_euler(q, _check_order(order), degrees)
    return out.reshape(lead + trailing)


def convert(values: np.ndarray, src: str, dst: str, *, order: str | None = None,
            degrees: bool = True) -> np.ndarray:
    """Convert rotations between 'axis_angle', 'quaternion', 'matrix' and 'euler'.

    Leading dimensions are kept. `order` is needed when either side is 'euler'.
    Returns float64. Quaternions come back with w >= 0 (one per rotation); use
    `quaternion_sequence_continuous` before keying them over time.
    """
    q, lead = _to_quaternion(values, src, order, degrees)
    return _from_quaternion(q, lead, dst, order, degrees)


def axis_angle_to_quaternion(aa: np.ndarray) -> np.ndarray:
    return convert(aa, "axis_angle", "quaternion")


def quaternion_to_axis_angle(q: np.ndarray) -> np.ndarray:
    return convert(q, "quaternion", "axis_angle")


def axis_angle_to_matrix(aa: np.ndarray) -> np.ndarray:
    return convert(aa, "axis_angle", "matrix")


def matrix_to_axis_angle(m: np.ndarray) -> np.ndarray:
    return convert(m, "matrix", "axis_angle")


def axis_angle_to_euler(aa: np.ndarray, order: str, degrees: bool = True) -> np.ndarray:
    return convert(aa, "axis_angle", "euler", order=order, degrees=degrees)


def euler_to_axis_angle(euler: np.ndarray, order: str, degrees: bool = True) -> np.ndarray:
    return convert(euler, "euler", "axis_angle", order=order, degrees=degrees)


def quaternion_sequence_continuous(q: np.ndarray) -> np.ndarray:
    """Flip quaternion signs along axis 0 (time) so that neighbours lie in one hemisphere.

    q and -q are the same rotation, but keying both makes Blender interpolate the long
    way round between them; after this, every frame has a non-negative dot product with
    the previous one. Works on (T, ..., 4).
    """
    q = np.asarray(q, dtype=np.float64)
    if q.ndim < 1 or q.shape[-1] != 4:
        raise DiffshegError(f"quaternion sequence must end in 4 values, got shape {q.shape}")
    if len(q) < 2:
        return q.copy()
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    steps = np.where(dots < 0.0, -1.0, 1.0)
    signs = np.concatenate([np.ones_like(steps[:1]), np.cumprod(steps, axis=0)], axis=0)
    return q * signs[..., None]


def euler_continuous(euler: np.ndarray, order: str, reference: np.ndarray | None = None,
                     degrees: bool = True) -> np.ndarray:
    """Pick, frame by frame along axis 0, the Euler triple nearest the previous frame.

    A rotation has two Euler triples per 360-degree period ((a, b, c) and
    (a + 180, 180 - b, c + 180) for three distinct axes, (a + 180, -b, c + 180) for
    orders such as 'ZXZ'), and each angle can move by whole turns. Writers that convert
    from rotations get one canonical triple per frame, which jumps by 360 degrees or
    flips branch between frames; curve editors and Euler interpolation then spin the
    bone. This keeps angles continuous. The first frame is matched to `reference`
    (shape (..., 3), e.g. a template pose) when given, else left canonical.
    """
    order = _check_order(order)
    angles = np.array(euler, dtype=np.float64)
    if angles.ndim < 2 or angles.shape[-1] != 3:
        raise DiffshegError(f"Euler sequence must have shape (T, ..., 3), got {angles.shape}")
    half = 180.0 if degrees else np.pi
    flip = np.array([half, 0.0, half])
    sign = np.array([1.0, -1.0, 1.0])
    middle = half if order[0] != order[2] else 0.0

    def nearest(current: np.ndarray, previous: np.ndarray) -> np.ndarray:
        other = current * sign + flip
        other[..., 1] += middle
        best = None
        for cand in (current, other):
            cand = cand + 2 * half * np.round((previous - cand) / (2 * half))
            if best is None:
                best = cand
            else:
                closer = np.sum((cand - previous) ** 2, -1) < np.sum((best - previous) ** 2, -1)
                best = np.where(closer[..., None], cand, best)
        return best

    if reference is not None:
        angles[0] = nearest(angles[0], np.broadcast_to(reference, angles[0].shape))
    for t in range(1, len(angles)):
        angles[t] = nearest(angles[t], angles[t - 1])
    return angles


def resample_positions(n_src: int, src_fps: float, dst_fps: float, n_out: int | None = None
                       ) -> np.ndarray:
    """Source-frame positions (fractional) of output frames i / dst_fps.

    Default count: every output frame at or before the last source frame's time.
    A larger `n_out` is allowed; frames past the end hold the last source frame.
    """
    if src_fps <= 0 or dst_fps <= 0:
        raise DiffshegError(f"frame rates must be positive, got {src_fps} -> {dst_fps}")
    if n_src < 1:
        raise DiffshegError("cannot resample an empty sequence")
    if n_out is None:
        n_out = int(np.floor((n_src - 1) * dst_fps / src_fps + 1e-9)) + 1
    if n_out < 0:
        raise DiffshegError(f"n_out must be >= 0, got {n_out}")
    return np.minimum(np.arange(n_out) * (src_fps / dst_fps), n_src - 1)



def slerp_resample(rotations: np.ndarray, src_fps: float, dst_fps: float,
                   n_out: int | None = None) -> np.ndarray:
    """Resample (T, J, 3) axis-angle rotations from src_fps to dst_fps.

    Output frame i sits at time i / dst_fps and is the spherical linear interpolation,
    per joint, between the two source frames around it (shortest arc).
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    if rotations.ndim != 3 or rotations.shape[-1] != 3:
        raise DiffshegError(f"rotations must have shape (T, J, 3), got {rotations.shape}")
    pos = resample_positions(len(rotations), src_fps, dst_fps, n_out)
    i0 = np.minimum(np.floor(pos).astype(int), max(len(rotations) - 2, 0))
    i1 = np.minimum(i0 + 1, len(rotations) - 1)
    w = (pos - i0)[:, None, None]
    q = _axis_angle_to_quaternion(rotations)
    # relative rotation q0^-1 q1 as a vector of angle <= pi (the shortest arc), scaled by w
    step = _quaternion_to_axis_angle(quaternion_product(quaternion_conjugate(q[i0]), q[i1])) * w
    return _quaternion_to_axis_angle(quaternion_product(q[i0], _axis_angle_to_quaternion(step)))


def _pchip_end_slope(m0: np.ndarray, m1: np.ndarray) -> np.ndarray:
    """End-point slope from the first two secants m0 (at the end) and m1 (next in),
    unit spacing: the one-sided three-point estimate (3 m0 - m1) / 2, set to 0 if its
    sign differs from m0 and limited to 3 m0 where the data turn (m0, m1 differ in sign),
    so the end interval stays monotone."""
    d = (3.0 * m0 - m1) / 2.0
    limit = (np.sign(m0) != np.sign(m1)) & (np.abs(d) > 3.0 * np.abs(m0))
    return np.where(np.sign(d) != np.sign(m0), 0.0, np.where(limit, 3.0 * m0, d))


def _pchip(values: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """PCHIP (Fritsch-Butland slopes, as scipy's PchipInterpolator) through (T, K)
    samples at 0 .. T-1 (T >= 2), evaluated at positions `pos` in [0, T-1].

    Interior slopes are the harmonic mean of the two neighbouring secants, or 0 where
    these differ in sign or one is flat (a local extremum stays one); this is what
    stops overshoot. Two samples give a straight line."""
    m = np.diff(values, axis=0)
    if len(values) == 2:
        d = np.concatenate([m, m])
    else:
        left, right = m[:-1], m[1:]
        monotone = (np.sign(left) == np.sign(right)) & (left != 0.0) & (right != 0.0)
        inner = np.divide(2.0 * left * right, left + right,
                          out=np.zeros_like(left), where=monotone)
        d = np.concatenate([_pchip_end_slope(m[:1], m[1:2]), inner,
                            _pchip_end_slope(m[-1:], m[-2:-1])])
    k = np.minimum(np.floor(pos).astype(int), len(values) - 2)
    t = (pos - k)[:, None]
    d0, d1, mk = d[k], d[k + 1], m[k]
    # cubic Hermite on [k, k + 1] in powers of t
    return values[k] + t * (d0 + t * ((3.0 * mk - 2.0 * d0 - d1) + t * (d0 + d1 - 2.0 * mk)))


def resample_weights(values: np.ndarray, src_fps: float, dst_fps: float,
                     kind: str = "cubic", n_out: int | None = None) -> np.ndarray:
    """Resample (T, K) curves (blendshape weights, translations) to dst_fps.

    'cubic' is PCHIP (piecewise cubic Hermite with monotone slopes): smooth like a
    spline, but it never overshoots the neighbouring samples, so a weight in [0, 1]
    stays in [0, 1] and a sharp blink onset does not ring. A natural cubic spline or
    Catmull-Rom would overshoot exactly there. 'linear' joins samples by straight lines.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise DiffshegError(f"weights must have shape (T, K), got {values.shape}")
    if kind not in ("cubic", "linear"):
        raise DiffshegError(f"unknown interpolation '{kind}': choose 'cubic' or 'linear'")
    pos = resample_positions(len(values), src_fps, dst_fps, n_out)
    if len(values) == 1:
        return np.repeat(values, len(pos), axis=0)
    if kind == "cubic":
        return _pchip(values, pos)
    i0 = np.minimum(np.floor(pos).astype(int), len(values) - 2)
    w = (pos - i0)[:, None]
    return values[i0] * (1.0 - w) + values[i0 + 1] * w
