"""Tests of vkgrl_newton.rotations against scipy's Rotation (float64, scalar-last xyzw like ours)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from quat_ref import random_axes, random_quats
from scipy.spatial.transform import Rotation

from vkgrl_newton.rotations import (
    euler_xyz_from_quat,
    quat_conjugate,
    quat_exp,
    quat_from_euler_xyz,
    quat_log,
    quat_mul,
    quat_rotate,
)


def matrices(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of xyzw quaternions (..., 4), by scipy (which normalizes them)."""
    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))


def rotvec_matrices(r) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors (N, 3), by scipy."""
    return Rotation.from_rotvec(np.asarray(r, dtype=np.float64)).as_matrix()


def t64(x):
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


# float64's unit roundoff. The tolerances below count roundings of values <= 1 in magnitude: any
# CPU rounds + - * / sqrt the same (IEEE), but sin, cos, atan2 may differ by ~1 ulp between libm,
# numpy's and torch's SIMD kernels (AVX2 vs AVX-512 builds), so those count on both sides.
U64 = 2.0 ** -53


# ---------------------------------------------------------------------------------------
# exp / log
# ---------------------------------------------------------------------------------------
def test_quat_exp_matches_rodrigues_and_is_unit():
    rng = np.random.default_rng(0)
    angles = rng.uniform(0.0, math.pi, 200)
    r = random_axes(rng, 200) * angles[:, None]
    q = quat_exp(t64(r)).numpy()
    # |q|: sin and cos (1 ulp each), r * sin(t/2)/t (3 roundings), 4 squares, 3 sums, sqrt: <= ~12 u
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=16 * U64)
    # each matrix entry: ~10 roundings here and in scipy's exp, on entries <= 1 (<= ~2e-15); 1e-14 ~ 90 u
    np.testing.assert_allclose(matrices(q), rotvec_matrices(r), atol=1e-14)


def test_log_exp_round_trip_generic_angles():
    rng = np.random.default_rng(1)
    angles = rng.uniform(0.0, math.pi, 500)
    r = random_axes(rng, 500) * angles[:, None]
    back = quat_log(quat_exp(t64(r))).numpy()
    # float64 throughout: exp and log are a few dozen rounded operations of 2.2e-16 on values <= pi, so the
    # round trip holds to ~1e-14 (any CPU: IEEE float64); 1e-9 is a bound, not a measured value
    np.testing.assert_allclose(back, r, atol=1e-9, rtol=0)
    # and the log is scipy's rotation vector of the same quaternion
    np.testing.assert_allclose(back, Rotation.from_quat(quat_exp(t64(r)).numpy()).as_rotvec(), atol=1e-9, rtol=0)


@pytest.mark.parametrize("delta", [1e-6, 3e-7, 1e-7, 1e-8, 1e-9])
def test_log_exp_round_trip_near_pi(delta):
    """Angles pi - delta (< pi): the log must give back r itself, not -r."""
    rng = np.random.default_rng(2)
    r = random_axes(rng, 50) * (math.pi - delta)
    back = quat_log(quat_exp(t64(r))).numpy()
    # float64: atan2(|v|, w) keeps the angle to ~eps near pi; the axis v/|v| with |v| ~ 1 to ~eps too
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
    np.testing.assert_allclose(rotvec_matrices(back), rotvec_matrices(r), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 1e-6 * (1 - 1e-3), 1e-6 * (1 + 1e-3), 1e-5])
def test_log_exp_round_trip_tiny_angles(angle):
    """Tiny angles (both sides of the series switch): relative accuracy, not just atol."""
    rng = np.random.default_rng(4)
    axes = random_axes(rng, 20)
    r = axes * angle
    q = quat_exp(t64(r))
    assert torch.isfinite(q).all()
    # closed form: q = (sin(a/2) axis, cos(a/2))
    # relative: the series or sin(t/2)/t and the product by r (<= ~5 roundings) against math.sin's ~1 ulp,
    # and the norm |r| (~3 roundings): <= ~10 u ~ 1.1e-15; rtol 1e-14 ~ 90 u
    np.testing.assert_allclose(q.numpy()[:, :3], axes * math.sin(angle / 2), rtol=1e-14, atol=0)
    # cos(t/2) of t <= 1e-5: 1 ulp on either side (torch's kernel vs libm) plus |r|'s ~3 u: ~5 u ~ 5.6e-16
    np.testing.assert_allclose(q.numpy()[:, 3], math.cos(angle / 2), rtol=8 * U64, atol=0)
    back = quat_log(q).numpy()
    assert np.all(np.isfinite(back))
    np.testing.assert_allclose(back, r, rtol=1e-12, atol=0)


def test_exp_log_round_trip_random_quaternions():
    rng = np.random.default_rng(5)
    q = random_quats(rng, 500)
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
        # was atol 1e-16 (< 1 ulp: held only where torch and libm round sin/cos alike). sin, cos 1 ulp on
        # each side (torch's SIMD kernel vs libm), r * sin(t/2) / t 2 more roundings: <= ~5 u of a value < 1
        np.testing.assert_allclose(q, [0.0, 0.0, math.sin(theta / 2), math.cos(theta / 2)], atol=8 * U64)
    q = quat_exp(t64([0.7, 0.0, 0.0])).numpy()
    np.testing.assert_allclose(q, [math.sin(0.35), 0.0, 0.0, math.cos(0.35)], atol=8 * U64)


def test_quat_exp_log_batched_shapes():
    r = torch.zeros(2, 5, 3, dtype=torch.float64)
    assert quat_exp(r).shape == (2, 5, 4)
    assert quat_log(quat_exp(r)).shape == (2, 5, 3)


# ---------------------------------------------------------------------------------------
# products, rotation, Euler
# ---------------------------------------------------------------------------------------
def test_quat_mul_against_scipy_and_matrices():
    rng = np.random.default_rng(6)
    q1, q2 = random_quats(rng, 300), random_quats(rng, 300)
    got = quat_mul(t64(q1), t64(q2)).numpy()
    # scipy composes p * q as the Hamilton product of the (normalized) quaternions, sign kept
    # was atol 1e-15, below the bound: each component is 4 products summed (<= 4 u * |q1||q2| = 4 u, ours
    # and scipy's, in any order or with FMA) and scipy renormalizes both inputs (~2 u each): <= 12 u
    np.testing.assert_allclose(got, (Rotation.from_quat(q1) * Rotation.from_quat(q2)).as_quat(), atol=16 * U64)
    # 3x3 products of entries <= 1 (3 terms) after ~10 roundings per matrix: <= ~40 u; 1e-14 ~ 90 u
    np.testing.assert_allclose(matrices(got), matrices(q1) @ matrices(q2), atol=1e-14)
    # conjugate is the inverse
    ident = quat_mul(quat_conjugate(t64(q1)), t64(q1)).numpy()
    # w = |q|^2 (4 squares summed: <= 4 u, and the input's own |q|^2 - 1 <= ~3 u); x, y, z cancel to <= 4 u
    np.testing.assert_allclose(ident, np.tile([0, 0, 0, 1.0], (300, 1)), atol=8 * U64)


def test_quat_rotate_matches_scipy():
    rng = np.random.default_rng(9)
    q, v = random_quats(rng, 200), rng.normal(size=(200, 3))
    got = quat_rotate(t64(q), t64(v)).numpy()
    # |v| <~ 4 (normal draws): ~15 roundings here and in scipy's matrix product, <= ~60 u * 4 ~ 5e-15
    np.testing.assert_allclose(got, Rotation.from_quat(q).apply(v), atol=1e-14)
    # batched over leading dimensions: (2, 100, 4) with (2, 100, 3)
    assert quat_rotate(t64(q).view(2, 100, 4), t64(v).view(2, 100, 3)).shape == (2, 100, 3)


def test_quat_from_euler_xyz_matches_rz_ry_rx():
    """q = q_z(yaw) q_y(pitch) q_x(roll): scipy's extrinsic 'xyz' (lowercase), R = Rz Ry Rx."""
    rng = np.random.default_rng(7)
    roll = rng.uniform(-math.pi, math.pi, 100)
    pitch = rng.uniform(-math.pi / 2, math.pi / 2, 100)
    yaw = rng.uniform(-math.pi, math.pi, 100)
    q = quat_from_euler_xyz(t64(roll), t64(pitch), t64(yaw)).numpy()
    # three half-angle sin/cos pairs (1 ulp each), two Hamilton products (4 u each), the norm (~4 u): <= ~14 u
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=16 * U64)
    want = Rotation.from_euler("xyz", np.stack([roll, pitch, yaw], axis=1)).as_matrix()
    np.testing.assert_allclose(matrices(q), want, atol=1e-14)
    composed = (Rotation.from_euler("z", yaw[:, None]) * Rotation.from_euler("y", pitch[:, None])
                * Rotation.from_euler("x", roll[:, None]))
    np.testing.assert_allclose(matrices(q), composed.as_matrix(), atol=1e-14)


def test_euler_xyz_from_quat_inverts_and_matches_scipy():
    rng = np.random.default_rng(8)
    q = random_quats(rng, 300)
    roll, pitch, yaw = (a.numpy() for a in euler_xyz_from_quat(t64(q)))
    assert np.all(np.abs(pitch) <= math.pi / 2) and np.all(np.abs(roll) <= math.pi) and np.all(np.abs(yaw) <= math.pi)
    # the same rotation back (no gimbal lock in these draws: |pitch| < pi/2 - 1e-3)
    assert np.all(np.abs(pitch) < math.pi / 2 - 1e-3)
    back = quat_from_euler_xyz(t64(roll), t64(pitch), t64(yaw)).numpy()
    np.testing.assert_allclose(matrices(back), matrices(q), atol=1e-12)
    np.testing.assert_allclose(np.stack([roll, pitch, yaw], axis=1), Rotation.from_quat(q).as_euler("xyz"), atol=1e-12)


def test_inputs_dtype():
    """Tensors keep their dtype; numpy arrays and sequences become float64."""
    q32 = torch.tensor([[0.0, 0.0, 0.6, 0.8]], dtype=torch.float32)
    assert quat_mul(q32, q32).dtype == torch.float32 and quat_log(q32).dtype == torch.float32
    assert quat_mul([0.0, 0.0, 0.6, 0.8], np.array([0.0, 0.0, 0.6, 0.8], np.float32)).dtype == torch.float64
    assert quat_from_euler_xyz(math.pi, 0.0, 0.5).dtype == torch.float64
