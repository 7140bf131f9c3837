"""Float64 quaternion references (xyzw) and random rotations for the tests; the references are
scipy's Rotation (independent of the package).

New tests call scipy.spatial.transform.Rotation directly; q_mul and q_to_matrix stay for the
tests that import them.
"""

import numpy as np
from scipy.spatial.transform import Rotation


def q_mul(a, b):
    """Hamilton product a * b of the normalized quaternions (scipy keeps the product's sign)."""
    return (Rotation.from_quat(a) * Rotation.from_quat(b)).as_quat()


def q_to_matrix(q):
    """Rotation matrix of a (not necessarily normalized) quaternion."""
    return Rotation.from_quat(q).as_matrix()


def random_quats(rng, n):
    """n uniformly random unit quaternions (n, 4)."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_axes(rng, n):
    """n uniformly random unit vectors (n, 3)."""
    a = rng.normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)
