"""Tests of vkgrl_newton.kmp.pose (the 6D relative pose eta) against scipy's Rotation, float64.

The quaternion maths itself (exp, log, products, Euler angles) is tested in test_rotations.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from quat_ref import random_axes, random_quats
from scipy.spatial.transform import Rotation

from vkgrl_newton.kmp.pose import eta_to_pose, pose_to_eta, reference_quat
from vkgrl_newton.rotations import quat_from_euler_xyz


def matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of one xyzw quaternion (4,), by scipy."""
    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def rotvec_matrix(r) -> np.ndarray:
    """Rotation matrix (3, 3) of one rotation vector (3,), by scipy."""
    return Rotation.from_rotvec(np.asarray(r, dtype=np.float64)).as_matrix()


def rz_rx(yaw, roll) -> np.ndarray:
    """R_z(yaw) R_x(roll), by scipy."""
    return (Rotation.from_euler("z", yaw) * Rotation.from_euler("x", roll)).as_matrix()


def t64(x):
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


# float64's unit roundoff: + - * / sqrt round alike on every CPU (IEEE); sin, cos, atan2 may differ by
# ~1 ulp between libm and numpy's or torch's SIMD kernels, so those count on both sides
U64 = 2.0 ** -53


def test_reference_quat_points_down():
    for psi in (0.0, math.radians(-40.0)):
        r = matrix(reference_quat(psi).numpy())
        # was 1e-15 (~9 u): our sin/cos and product (~4 u), scipy's normalize + matrix (~8 u) against scipy's
        # own Euler sin/cos and composition (~8 u), on entries <= 1: <= ~20 u
        np.testing.assert_allclose(r, rz_rx(psi, math.pi), atol=32 * U64)
        np.testing.assert_allclose(r @ [0, 0, 1.0], [0, 0, -1.0], atol=32 * U64)  # tool z axis points down


# ---------------------------------------------------------------------------------------
# pose <-> eta
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("psi_ref", [0.0, math.radians(-40.0)])
def test_pose_eta_round_trip(psi_ref):
    rng = np.random.default_rng(8)
    n = 200
    p_tcp = rng.normal(size=(n, 3)) * 0.1
    p_target = rng.normal(size=(n, 3)) * 0.1
    q_tcp = random_quats(rng, n)
    eta = pose_to_eta(t64(p_tcp), t64(q_tcp), t64(p_target), psi_ref)
    assert eta.shape == (n, 6) and eta.dtype == torch.float64
    # one IEEE subtraction on either side: the same bits on any CPU (was atol 1e-16)
    np.testing.assert_array_equal(eta[:, :3].numpy(), p_tcp - p_target)
    # rotation part equals log(q_ref^-1 q_tcp) computed with matrices: R(eta) = R_ref^T R_tcp
    r_ref = matrix(reference_quat(psi_ref).numpy())
    for i in range(0, n, 17):
        np.testing.assert_allclose(rotvec_matrix(eta[i, 3:].numpy()), r_ref.T @ matrix(q_tcp[i]), atol=1e-12)
    p_back, q_back = eta_to_pose(eta, t64(p_target), psi_ref)
    # (p - t) + t: two IEEE roundings of values < 1 (<= 2 u ~ 2.2e-16), the same on any CPU
    np.testing.assert_allclose(p_back.numpy(), p_tcp, atol=1e-15)
    q_back = q_back.numpy()
    sign = np.sign(np.sum(q_back * q_tcp, axis=1, keepdims=True))
    np.testing.assert_allclose(q_back, sign * q_tcp, atol=1e-12)

    # the other direction: eta (angle < pi) -> pose -> eta
    eta2 = np.concatenate([rng.normal(size=(n, 3)) * 0.05,
                           random_axes(rng, n) * rng.uniform(0, math.pi * 0.999, n)[:, None]], axis=1)
    p2, q2 = eta_to_pose(t64(eta2), t64(p_target), psi_ref)
    np.testing.assert_allclose(pose_to_eta(p2, q2, t64(p_target), psi_ref).numpy(), eta2, atol=1e-11)


@pytest.mark.parametrize("psi_ref", [0.0, math.radians(-40.0)])
def test_reference_pose_maps_to_zero(psi_ref):
    p_target = t64([0.1, -0.2, 0.3])
    eta = pose_to_eta(p_target, reference_quat(psi_ref), p_target, psi_ref)
    # positions: x - x = 0 exactly; rotation: v of q_ref^-1 q_ref is 4 products summed (<= 4 u), the
    # log doubles it (2 v / w): <= 8 u (was 1e-15 ~ 9 u, no margin)
    np.testing.assert_allclose(eta.numpy(), np.zeros(6), atol=16 * U64)


@pytest.mark.parametrize("psi_ref", [0.0, math.radians(-40.0)])
@pytest.mark.parametrize("dpsi", [0.3, -0.5, 1e-4, 2.0])
def test_yaw_only_offset_gives_rz_only(psi_ref, dpsi):
    """Eq. 5.33: a TCP that differs from q_ref only in world yaw has eta rotation (0, 0, -dpsi).

    q_tcp = q(pi, 0, psi_ref + d) = q_z(psi_ref + d) q_x(pi) and q_ref = q_z(psi_ref) q_x(pi), so
    q_ref^-1 q_tcp = q_x(pi)^-1 q_z(d) q_x(pi). Conjugating by a half turn about x maps the axis z to
    -z (R_x(pi)^T e_z = -e_z), so the relative rotation is d about -z, i.e. the rotation vector
    (0, 0, -d). The rotation vector is expressed in the gripper frame, whose z axis points down,
    so a positive world yaw is a negative rotation about the tool's own z axis.
    """
    p = t64([0.0, 0.0, 0.0])
    q_tcp = quat_from_euler_xyz(t64(math.pi), t64(0.0), t64(psi_ref + dpsi))
    eta = pose_to_eta(p, q_tcp, p, psi_ref).numpy()
    np.testing.assert_allclose(eta, [0, 0, 0, 0, 0, -dpsi], atol=1e-14)
    # and back: eta (0,0,0, 0,0,-d) reproduces the yawed gripper
    _, q_back = eta_to_pose(t64([0, 0, 0, 0, 0, -dpsi]), p, psi_ref)
    np.testing.assert_allclose(matrix(q_back.numpy()), rz_rx(psi_ref + dpsi, math.pi), atol=1e-14)
