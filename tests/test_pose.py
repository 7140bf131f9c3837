"""Tests of vkgrl_newton.kmp.pose against independent float64 numpy quaternion / rotation-matrix maths."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vkgrl_newton.kmp.pose import (
    eta_to_pose,
    pose_to_eta,
    quat_conjugate,
    quat_exp,
    quat_from_euler_xyz,
    quat_log,
    quat_mul,
    reference_quat,
)


# ---------------------------------------------------------------------------------------
# Independent numpy references
# ---------------------------------------------------------------------------------------
def np_quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) of unit quaternions (..., 4) in xyzw order."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - z * w)
    r[..., 0, 2] = 2 * (x * z + y * w)
    r[..., 1, 0] = 2 * (x * y + z * w)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - x * w)
    r[..., 2, 0] = 2 * (x * z - y * w)
    r[..., 2, 1] = 2 * (y * z + x * w)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def np_rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, for one rotation vector (3,)."""
    r = np.asarray(r, dtype=np.float64)
    theta = np.linalg.norm(r)
    if theta == 0.0:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx


def rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def np_hamilton(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product in xyzw via the vector form (w1 w2 - v1.v2, w1 v2 + w2 v1 + v1 x v2)."""
    v1, w1 = q1[..., :3], q1[..., 3:]
    v2, w2 = q2[..., :3], q2[..., 3:]
    v = w1 * v2 + w2 * v1 + np.cross(v1, v2)
    w = w1 * w2 - np.sum(v1 * v2, axis=-1, keepdims=True)
    return np.concatenate([v, w], axis=-1)


def random_unit_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_axes(rng, n):
    a = rng.normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def t64(x):
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


# ---------------------------------------------------------------------------------------
# exp / log
# ---------------------------------------------------------------------------------------
def test_quat_exp_matches_rodrigues_and_is_unit():
    rng = np.random.default_rng(0)
    angles = rng.uniform(0.0, math.pi, 200)
    r = random_axes(rng, 200) * angles[:, None]
    q = quat_exp(t64(r)).numpy()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    got = np_quat_to_matrix(q)
    want = np.stack([np_rotvec_to_matrix(v) for v in r])
    np.testing.assert_allclose(got, want, atol=1e-14)


def test_log_exp_round_trip_generic_angles():
    rng = np.random.default_rng(1)
    angles = rng.uniform(0.0, math.pi, 500)
    r = random_axes(rng, 500) * angles[:, None]
    back = quat_log(quat_exp(t64(r))).numpy()
    np.testing.assert_allclose(back, r, atol=1e-9, rtol=0)


@pytest.mark.parametrize("delta", [1e-6, 3e-7, 1e-7, 1e-8, 1e-9])
def test_log_exp_round_trip_near_pi(delta):
    """Angles pi - delta (< pi): the log must give back r itself, not -r."""
    rng = np.random.default_rng(2)
    r = random_axes(rng, 50) * (math.pi - delta)
    back = quat_log(quat_exp(t64(r))).numpy()
    np.testing.assert_allclose(back, r, atol=1e-9, rtol=0)
    # and the angle stays in [0, pi]
    assert np.all(np.linalg.norm(back, axis=1) <= math.pi + 1e-15)


@pytest.mark.parametrize("delta", [0.0, 1e-15, 1e-12, 1e-9, 1e-6])
def test_log_exp_near_pi_same_rotation(delta):
    """At (or within rounding of) pi, r and -r are the same rotation: compare rotation matrices."""
    rng = np.random.default_rng(3)
    r = random_axes(rng, 50) * (math.pi - delta)
    back = quat_log(quat_exp(t64(r))).numpy()
    assert np.all(np.linalg.norm(back, axis=1) <= math.pi + 1e-12)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), math.pi - delta, atol=1e-12)
    want = np.stack([np_rotvec_to_matrix(v) for v in r])
    got = np.stack([np_rotvec_to_matrix(v) for v in back])
    np.testing.assert_allclose(got, want, atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 1e-6 * (1 - 1e-3), 1e-6 * (1 + 1e-3), 1e-5])
def test_log_exp_round_trip_tiny_angles(angle):
    """Tiny angles (both sides of the series switch): relative accuracy, not just atol."""
    rng = np.random.default_rng(4)
    axes = random_axes(rng, 20)
    r = axes * angle
    q = quat_exp(t64(r))
    assert torch.isfinite(q).all()
    # closed form: q = (sin(a/2) axis, cos(a/2))
    np.testing.assert_allclose(q.numpy()[:, :3], axes * math.sin(angle / 2), rtol=1e-14, atol=0)
    np.testing.assert_allclose(q.numpy()[:, 3], math.cos(angle / 2), rtol=1e-15, atol=0)
    back = quat_log(q).numpy()
    assert np.all(np.isfinite(back))
    np.testing.assert_allclose(back, r, rtol=1e-12, atol=0)


def test_exp_log_round_trip_random_quaternions():
    rng = np.random.default_rng(5)
    q = random_unit_quats(rng, 500)
    # include some with w < 0, w == 0 and near identity
    q[0] = [0.0, 0.0, 0.0, -1.0]
    q[1] = [1.0, 0.0, 0.0, 0.0]
    q[2] = np.array([1e-10, -2e-10, 3e-10, 1.0]) / np.linalg.norm([1e-10, -2e-10, 3e-10, 1.0])
    r = quat_log(t64(q))
    assert np.all(r.norm(dim=-1).numpy() <= math.pi + 1e-12)
    back = quat_exp(r).numpy()
    sign = np.sign(np.sum(back * q, axis=1, keepdims=True))
    np.testing.assert_allclose(back, sign * q, atol=1e-12)
    # q and -q give the same rotation vector (away from pi, where the vector is unique)
    away = np.abs(q[:, 3]) > 1e-3
    np.testing.assert_allclose(quat_log(t64(-q)).numpy()[away], r.numpy()[away], atol=1e-12)


def test_quat_exp_xyzw_convention():
    for theta in (0.3, -1.2, 2.5):
        q = quat_exp(t64([0.0, 0.0, theta])).numpy()
        np.testing.assert_allclose(q, [0.0, 0.0, math.sin(theta / 2), math.cos(theta / 2)], atol=1e-16)
    q = quat_exp(t64([0.7, 0.0, 0.0])).numpy()
    np.testing.assert_allclose(q, [math.sin(0.35), 0.0, 0.0, math.cos(0.35)], atol=1e-16)


def test_quat_exp_log_batched_shapes():
    r = torch.zeros(2, 5, 3, dtype=torch.float64)
    assert quat_exp(r).shape == (2, 5, 4)
    assert quat_log(quat_exp(r)).shape == (2, 5, 3)


# ---------------------------------------------------------------------------------------
# products, Euler
# ---------------------------------------------------------------------------------------
def test_quat_mul_against_numpy_and_matrices():
    rng = np.random.default_rng(6)
    q1, q2 = random_unit_quats(rng, 300), random_unit_quats(rng, 300)
    got = quat_mul(t64(q1), t64(q2)).numpy()
    np.testing.assert_allclose(got, np_hamilton(q1, q2), atol=1e-15)
    np.testing.assert_allclose(np_quat_to_matrix(got), np_quat_to_matrix(q1) @ np_quat_to_matrix(q2), atol=1e-14)
    # conjugate is the inverse
    ident = quat_mul(quat_conjugate(t64(q1)), t64(q1)).numpy()
    np.testing.assert_allclose(ident, np.tile([0, 0, 0, 1.0], (300, 1)), atol=1e-15)


def test_quat_from_euler_xyz_matches_rz_ry_rx():
    rng = np.random.default_rng(7)
    roll = rng.uniform(-math.pi, math.pi, 100)
    pitch = rng.uniform(-math.pi / 2, math.pi / 2, 100)
    yaw = rng.uniform(-math.pi, math.pi, 100)
    q = quat_from_euler_xyz(t64(roll), t64(pitch), t64(yaw)).numpy()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    want = np.stack([rz(c) @ ry(b) @ rx(a) for a, b, c in zip(roll, pitch, yaw)])
    np.testing.assert_allclose(np_quat_to_matrix(q), want, atol=1e-14)


def test_reference_quat_points_down():
    for psi in (0.0, math.radians(-40.0)):
        r = np_quat_to_matrix(reference_quat(psi).numpy())
        np.testing.assert_allclose(r, rz(psi) @ rx(math.pi), atol=1e-15)
        np.testing.assert_allclose(r @ [0, 0, 1.0], [0, 0, -1.0], atol=1e-15)  # tool z axis points down


# ---------------------------------------------------------------------------------------
# pose <-> eta
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("psi_ref", [0.0, math.radians(-40.0)])
def test_pose_eta_round_trip(psi_ref):
    rng = np.random.default_rng(8)
    n = 200
    p_tcp = rng.normal(size=(n, 3)) * 0.1
    p_target = rng.normal(size=(n, 3)) * 0.1
    q_tcp = random_unit_quats(rng, n)
    eta = pose_to_eta(t64(p_tcp), t64(q_tcp), t64(p_target), psi_ref)
    assert eta.shape == (n, 6) and eta.dtype == torch.float64
    np.testing.assert_allclose(eta[:, :3].numpy(), p_tcp - p_target, atol=1e-16)
    # rotation part equals log(q_ref^-1 q_tcp) computed with numpy matrices: R(eta) = R_ref^T R_tcp
    r_ref = np_quat_to_matrix(reference_quat(psi_ref).numpy())
    for i in range(0, n, 17):
        np.testing.assert_allclose(np_rotvec_to_matrix(eta[i, 3:].numpy()), r_ref.T @ np_quat_to_matrix(q_tcp[i]),
                                   atol=1e-12)
    p_back, q_back = eta_to_pose(eta, t64(p_target), psi_ref)
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
    np.testing.assert_allclose(eta.numpy(), np.zeros(6), atol=1e-15)


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
    np.testing.assert_allclose(np_quat_to_matrix(q_back.numpy()), rz(psi_ref + dpsi) @ rx(math.pi), atol=1e-14)
