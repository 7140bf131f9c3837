"""Float64 quaternion references (xyzw) shared by the tests; written independently of the package."""

import numpy as np


def q_mul(a, b):
    """Hamilton product a * b."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + bw * ax + ay * bz - az * by,
                     aw * by + bw * ay + az * bx - ax * bz,
                     aw * bz + bw * az + ax * by - ay * bx,
                     aw * bw - ax * bx - ay * by - az * bz])


def q_to_matrix(q):
    """Rotation matrix of a (not necessarily normalized) quaternion."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def q_conj(q):
    """Conjugate (the inverse of a unit quaternion)."""
    return np.array([-q[0], -q[1], -q[2], q[3]], dtype=np.float64)


def q_axis_angle(q):
    """Axis * angle with angle in [0, pi] (the shorter of q, -q); q need not be normalized."""
    q = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    q = q if q[3] >= 0 else -q
    s = np.linalg.norm(q[:3])
    if s == 0.0:
        return np.zeros(3)
    return q[:3] / s * 2.0 * np.arctan2(s, q[3])


def random_quats(rng, n):
    """n uniformly random unit quaternions (n, 4)."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)
