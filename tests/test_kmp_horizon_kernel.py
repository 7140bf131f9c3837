"""The Warp KMP horizon kernel against a float64 torch reference of the same computation."""

import math

import numpy as np
import pytest
import torch

from vkgrl_newton.kmp.pose import reference_quat
from vkgrl_newton.rotations import quat_exp, quat_mul


def reference_pose(step_index, zeta, mean, gain, target_pos, ref_quat):
    """float64 reference: eta = m[n] + B[n] zeta, pos = target + eta[:3], quat = q_ref * exp(eta[3:])."""
    n = torch.clamp(torch.as_tensor(step_index, dtype=torch.long), 0, mean.shape[0] - 1)
    eta = mean[n] + torch.einsum("eij,ej->ei", gain[n], zeta)
    return eta, target_pos + eta[:, :3], quat_mul(ref_quat, quat_exp(eta[:, 3:]))


U32 = 2.0 ** -24  # float32's unit roundoff


def float32_bounds(step_index, zeta, mean, gain, target_pos):
    """What the float32 kernel may differ from the float64 reference by, per component, on any CPU.

    eta_i = m_i + sum_j B_ij zeta_j: the inputs rounded to float32 (u on m, 2 u on each product) and a
    7-term float32 sum (<= 7 u of the summed magnitudes, any order, FMA or not): <= ~10 u * S_i with
    S_i = |m_i| + sum_j |B_ij| |zeta_j|; bounded by 16 u S. pos adds |target| to S. The quaternion moves by
    at most half the rotation error plus q_ref's rounding, exp's sin/cos and the Hamilton product (~12 u
    of a unit quaternion): 16 u (1 + max S_rot)."""
    n = torch.clamp(torch.as_tensor(step_index, dtype=torch.long), 0, mean.shape[0] - 1)
    s = (mean[n].abs() + torch.einsum("eij,ej->ei", gain[n].abs(), zeta.abs())).double().numpy()
    eta_tol = 16 * U32 * s
    pos_tol = 16 * U32 * (s[:, :3] + np.abs(np.asarray(target_pos, dtype=np.float64)))
    quat_tol = 16 * U32 * (1.0 + s[:, 3:].max(axis=1, keepdims=True))
    return eta_tol, pos_tol, quat_tol


def run_kernel(wp, step_index, zeta, mean, gain, target_pos, ref_quat):
    from vkgrl_newton.kernels.kmp_horizon import kmp_horizon_pose, mat66f, vec6f

    e = len(step_index)
    f32 = lambda t: np.ascontiguousarray(np.asarray(t, dtype=np.float32))
    out_eta = wp.zeros(e, dtype=vec6f)
    out_pos = wp.zeros(e, dtype=wp.vec3)
    out_quat = wp.zeros(e, dtype=wp.quat)
    kmp_horizon_pose(
        wp.array(np.asarray(step_index, dtype=np.int32), dtype=wp.int32),
        wp.array(f32(zeta), dtype=vec6f),
        wp.array(f32(mean), dtype=vec6f),
        wp.array(f32(gain), dtype=mat66f),
        wp.array(f32(target_pos), dtype=wp.vec3),
        wp.array(f32(ref_quat), dtype=wp.quat),
        out_eta,
        out_pos,
        out_quat,
    )
    return out_eta.numpy(), out_pos.numpy(), out_quat.numpy()


def random_case(num_envs=257, num_steps=151, seed=0):
    g = torch.Generator().manual_seed(seed)
    rnd = lambda *shape: torch.rand(*shape, generator=g, dtype=torch.float64) * 2 - 1
    mean = torch.cat([0.05 * rnd(num_steps, 3), 1.2 * rnd(num_steps, 3)], dim=1)
    gain = 1e-3 * rnd(num_steps, 6, 6)
    zeta = torch.cat([150 * rnd(num_envs, 3), 15 * rnd(num_envs, 3)], dim=1)
    # steps include out-of-range indices on both sides: they must clamp to the table
    step_index = torch.randint(-3, num_steps + 5, (num_envs,), generator=g)
    target_pos = rnd(num_envs, 3) * torch.tensor([0.6, 0.6, 0.2], dtype=torch.float64)
    ref_quat = torch.nn.functional.normalize(rnd(num_envs, 4), dim=1)
    return step_index, zeta, mean, gain, target_pos, ref_quat


def test_kernel_matches_float64_reference_on_random_inputs(wp_cpu):
    case = random_case()
    eta, pos, quat = run_kernel(wp_cpu, *case)
    ref_eta, ref_pos, ref_quat = reference_pose(*case)
    # was max |error| < 1e-5 with no stated origin; now float32_bounds' derived bound (observed <= ~3 u S)
    eta_tol, pos_tol, quat_tol = float32_bounds(*case[:5])
    assert (np.abs(eta - ref_eta.numpy()) <= eta_tol).all()
    assert (np.abs(pos - ref_pos.numpy()) <= pos_tol).all()
    assert (np.abs(quat - ref_quat.numpy()) <= quat_tol).all()
    # |q| of q_ref * exp(r) in float32: q_ref rounded to float32 (~1 ulp of norm), exp's sin/cos (~2 ulps),
    # the Hamilton product (4 rounded terms per component, ~4 ulps): ~7 ulps of 1.19e-7 = 8.3e-7, doubled
    assert np.abs(np.linalg.norm(quat, axis=1) - 1).max() < 2e-6


def test_kernel_small_and_zero_rotations(wp_cpu):
    """The series branch of exp (angle < 1e-3) and angle 0 give q_ref * exp(r) as well."""
    num_envs = 64
    angles = torch.cat([torch.zeros(1), torch.logspace(-9, -2, num_envs - 1)]).double()
    axis = torch.nn.functional.normalize(torch.randn(num_envs, 3, generator=torch.Generator().manual_seed(1)).double(), dim=1)
    mean = torch.zeros(num_envs, 6, dtype=torch.float64)
    mean[:, 3:] = axis * angles[:, None]
    gain = torch.zeros(num_envs, 6, 6, dtype=torch.float64)
    step_index = torch.arange(num_envs)
    zeta = torch.zeros(num_envs, 6, dtype=torch.float64)
    target = torch.zeros(num_envs, 3, dtype=torch.float64)
    q_ref = reference_quat(math.radians(-40.0)).expand(num_envs, 4).contiguous()
    _, _, quat = run_kernel(wp_cpu, step_index, zeta, mean, gain, target, q_ref)
    _, _, ref_quat = reference_pose(step_index, zeta, mean, gain, target, q_ref)
    # angles <= 1e-2 (S_rot <= 1e-2), so float32_bounds gives 16 u (1 + 1e-2) ~ 9.6e-7 (was 1e-6, no origin)
    _, _, quat_tol = float32_bounds(step_index, zeta, mean, gain, target)
    assert (np.abs(quat - ref_quat.numpy()) <= quat_tol).all()
    # angle 0: the reference orientation up to its own rounding to float32 (<= u/2 of a unit component)
    assert np.abs(quat[0] - q_ref[0].numpy()).max() <= U32


def test_kernel_with_fitted_tables_matches_tables_predict_pose(wp_cpu):
    """Tables from the KMP pipeline (to_warp layout, 4D embedding) drive the kernel like predict_pose."""
    from vkgrl_newton.kmp import fit_prior, synthetic_demos
    from vkgrl_newton.kernels.kmp_horizon import kmp_horizon_pose, vec6f

    tables = fit_prior(synthetic_demos("PegInsert", 6, action_dim=4, seed=3), action_dim=4, n_components=4)
    mean_wp, gain_wp = tables.to_warp("cpu")
    num_envs = 128
    g = torch.Generator().manual_seed(2)
    action = torch.rand(num_envs, 6, generator=g, dtype=torch.float64) * 2 - 1
    action[:, 3:5] = 0.0  # 4D: no roll/pitch action
    zeta = action * torch.tensor([150.0] * 3 + [15.0] * 3, dtype=torch.float64)
    step_index = torch.randint(0, tables.n_steps + 1, (num_envs,), generator=g)
    target = torch.rand(num_envs, 3, generator=g, dtype=torch.float64)
    q_ref = reference_quat(0.0).expand(num_envs, 4).contiguous()
    out = [wp_cpu.zeros(num_envs, dtype=t) for t in (vec6f, wp_cpu.vec3, wp_cpu.quat)]
    kmp_horizon_pose(
        wp_cpu.array(step_index.numpy().astype(np.int32), dtype=wp_cpu.int32),
        wp_cpu.array(zeta.numpy().astype(np.float32), dtype=vec6f),
        mean_wp,
        gain_wp,
        wp_cpu.array(target.numpy().astype(np.float32), dtype=wp_cpu.vec3),
        wp_cpu.array(q_ref.numpy().astype(np.float32), dtype=wp_cpu.quat),
        *out,
    )
    ref_pos, ref_quat = tables.predict_pose(step_index, zeta, target, q_ref)
    # was < 1e-5 with no stated origin: float32_bounds on the tables' own mean and gain
    _, pos_tol, quat_tol = float32_bounds(step_index, zeta, tables.mean, tables.gain, target)
    assert (np.abs(out[1].numpy() - ref_pos.numpy()) <= pos_tol).all()
    assert (np.abs(out[2].numpy() - ref_quat.numpy()) <= quat_tol).all()
    # 4D: roll and pitch of the command stay at the reference
    assert np.abs(out[0].numpy()[:, 3:5]).max() == 0.0


def test_kernel_rejects_mismatched_lengths(wp_cpu):
    case = random_case(num_envs=8, num_steps=5)
    with pytest.raises(ValueError, match="zeta"):
        step_index, zeta, *rest = case
        run_kernel(wp_cpu, step_index, zeta[:7], *rest)


def test_kernel_reads_nonsymmetric_gain_through_from_torch(wp_cpu):
    """torch (S, 6, 6) tables viewed as mat66f with wp.from_torch (the env's zero-copy path)
    are read row-major: a non-symmetric B gives B @ zeta, not B^T @ zeta."""
    from vkgrl_newton.kernels.kmp_horizon import kmp_horizon_pose, mat66f, vec6f

    g = torch.Generator().manual_seed(5)
    num_envs, num_steps = 32, 7
    mean = torch.zeros(num_steps, 6)
    gain = torch.triu(torch.rand(num_steps, 6, 6, generator=g)) * 1e-2  # upper triangular: far from symmetric
    zeta = torch.rand(num_envs, 6, generator=g)
    step_index = torch.randint(0, num_steps, (num_envs,), generator=g, dtype=torch.int32)
    target = torch.zeros(num_envs, 3)
    q_ref = torch.tensor([[0.0, 0.0, 0.0, 1.0]]).repeat(num_envs, 1)
    eta = wp_cpu.zeros(num_envs, dtype=vec6f)
    kmp_horizon_pose(
        wp_cpu.from_torch(step_index, dtype=wp_cpu.int32),
        wp_cpu.from_torch(zeta, dtype=vec6f),
        wp_cpu.from_torch(mean, dtype=vec6f),
        wp_cpu.from_torch(gain, dtype=mat66f),
        wp_cpu.from_torch(target, dtype=wp_cpu.vec3),
        wp_cpu.from_torch(q_ref, dtype=wp_cpu.quat),
        eta,
        wp_cpu.zeros(num_envs, dtype=wp_cpu.vec3),
        wp_cpu.zeros(num_envs, dtype=wp_cpu.quat),
    )
    want = torch.einsum("eij,ej->ei", gain.double()[step_index.long()], zeta.double())
    # float32 inputs (no rounding of them), a 6-term float32 sum: <= 6 u sum |B| |zeta| (was < 1e-7, no origin)
    bound = 8 * U32 * torch.einsum("eij,ej->ei", gain.double().abs()[step_index.long()], zeta.double().abs())
    assert (np.abs(eta.numpy() - want.numpy()) <= bound.numpy()).all()
    wrong = torch.einsum("eji,ej->ei", gain.double()[step_index.long()], zeta.double())
    assert (want - wrong).abs().max() > 1e-3  # the check can tell the layouts apart
