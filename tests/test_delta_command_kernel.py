"""The delta-pose command kernel (kernels/delta_command.py) against a float64 reference written from
Factory's mapping with scipy's Rotation (exp map, XYZ Euler yaw, tilt about the gripper axis)."""

import math

import numpy as np
import pytest
from quat_ref import random_axes
from scipy.spatial.transform import Rotation

POS_BOUND = 0.05
MAX_TILT = math.radians(30.0)
TCP_OFFSET = np.array([0.0, 0.0, 0.1034])
# float32 bounds from the kernel's operation counts: positions ~0.6 m pass through ~6 float32
# operations (rotate the offset, add, scale, clamp): 6 ulps of 0.6 m (6e-8) = 3.6e-7 -> 1e-6; the
# quaternion through exp (sin, cos, |r|), a Hamilton product, the Euler yaw (atan2) and its
# half-angle sin/cos, or the tilt's acos (condition 1/sin(tilt) <= 2 over the cone's rim, 30 deg)
# and a second exp and product: ~20 rounded operations of ~1.19e-7 on unit numbers = 2.4e-6 -> 4e-6
POS_TOL, QUAT_TOL = 1e-6, 4e-6


def reference(hand_p, hand_q, actions, pos_scale, rot_scale, target, unidirectional):
    """float64 command (pos (E, 3), quat (E, 4) xyzw) from the float32 inputs."""
    E, D = actions.shape
    pos, quat = np.zeros((E, 3)), np.zeros((E, 4))
    for e in range(E):
        a = actions[e].astype(np.float64)
        R_tcp = Rotation.from_quat(hand_q[e])
        p = hand_p[e] + R_tcp.apply(TCP_OFFSET) + a[:3] * pos_scale[e]
        r = np.array([0.0, 0.0, a[3] * rot_scale[e, 2]]) if D == 4 else a[3:6] * rot_scale[e]
        if unidirectional:
            r[2] = -(a[D - 1] + 1.0) * 0.5 * rot_scale[e, 2]
        R = Rotation.from_rotvec(r) * R_tcp
        pos[e] = target[e] + np.clip(p - target[e], -POS_BOUND, POS_BOUND)
        if D == 4:
            yaw = R.as_euler("xyz")[2]  # extrinsic x-y-z, as Isaac Lab's euler_xyz_from_quat
            R = Rotation.from_euler("xyz", [math.pi, 0.0, yaw])
        else:
            z = R.apply([0.0, 0.0, 1.0])
            tilt = math.acos(np.clip(-z[2], -1.0, 1.0))
            if tilt > MAX_TILT:
                axis = np.cross(z, [0.0, 0.0, -1.0])
                R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * (tilt - MAX_TILT)) * R
        quat[e] = R.as_quat()
    return pos, quat


def _run_kernel(wp, hand_p, hand_q, actions, pos_scale, rot_scale, target, unidirectional, record_first):
    from vkgrl_newton.kernels.delta_command import delta_command

    E = actions.shape[0]
    body_q = np.concatenate((hand_p, hand_q), 1).astype(np.float32)
    arr = lambda x, dt: wp.array(np.ascontiguousarray(x, dtype=np.float32), dtype=dt, device="cpu")  # noqa: E731
    out = {k: wp.zeros(E, dtype=dt, device="cpu") for k, dt in
           (("p", wp.vec3), ("q", wp.quat), ("p0", wp.vec3), ("q0", wp.quat))}
    delta_command(
        body_q=arr(body_q, wp.transform), hand_body=wp.array(np.arange(E, dtype=np.int32), device="cpu"),
        tcp_offset_hand=tuple(TCP_OFFSET), actions=wp.array(actions.astype(np.float32), dtype=wp.float32, device="cpu"),
        pos_scale=arr(pos_scale, wp.vec3), rot_scale=arr(rot_scale, wp.vec3), target_frame_pos_w=arr(target, wp.vec3),
        pos_bound=POS_BOUND, max_tilt=MAX_TILT, unidirectional_yaw=unidirectional, record_first=record_first,
        cmd_pos_w=out["p"], cmd_quat_w=out["q"], first_pos_w=out["p0"], first_quat_w=out["q0"])
    return {k: v.numpy().astype(np.float64) for k, v in out.items()}


def _inputs(rng, E, D):
    """Hands pointing down within ~45 deg (both sides of the 30 deg cone), near and beyond the bound box."""
    yaw = rng.uniform(-math.pi, math.pi, E)
    tilt = Rotation.from_rotvec(random_axes(rng, E) * rng.uniform(0.0, math.radians(45.0), E)[:, None])
    hand_q = (tilt * Rotation.from_euler("xyz", np.stack([np.full(E, math.pi), np.zeros(E), yaw], 1))).as_quat()
    target = np.array([0.6, 0.0, 0.1]) + rng.uniform(-0.02, 0.02, (E, 3))
    hand_p = target + rng.uniform(-0.07, 0.07, (E, 3)) - Rotation.from_quat(hand_q).apply(TCP_OFFSET)
    f32 = lambda x: x.astype(np.float32).astype(np.float64)  # noqa: E731  the kernel's inputs, exactly
    return (f32(hand_p), f32(hand_q), f32(rng.uniform(-1, 1, (E, D))), f32(0.02 * rng.uniform(0.5, 1.5, (E, 3))),
            f32(0.097 * rng.uniform(0.5, 1.5, (E, 3))), f32(target))


@pytest.mark.parametrize("D,unidirectional", [(4, False), (6, False), (4, True), (6, True)])
def test_delta_command_matches_float64_reference(wp_cpu, D, unidirectional):
    rng = np.random.default_rng(10 * D + unidirectional)
    E = 256
    inputs = _inputs(rng, E, D)
    got = _run_kernel(wp_cpu, *inputs, unidirectional, record_first=1)
    pos, quat = reference(*inputs, unidirectional)
    np.testing.assert_allclose(got["p"], pos, rtol=0, atol=POS_TOL)
    sign = np.sign(np.sum(got["q"] * quat, axis=1, keepdims=True))  # q and -q are the same rotation
    np.testing.assert_allclose(got["q"], sign * quat, rtol=0, atol=QUAT_TOL)
    np.testing.assert_array_equal(got["p0"], got["p"])
    np.testing.assert_array_equal(got["q0"], got["q"])
    # the cases exercise both sides of each bound
    clipped = np.abs(pos - inputs[5]) >= POS_BOUND - 1e-12
    assert 0 < clipped.sum() < clipped.size
    if D == 6:
        z = Rotation.from_quat(got["q"]).apply([0.0, 0.0, 1.0])
        tilt = np.arccos(np.clip(-z[:, 2], -1, 1))
        assert tilt.max() < MAX_TILT + 1e-5
        assert (tilt > MAX_TILT - 1e-5).sum() > E // 10 and (tilt < MAX_TILT - 0.05).sum() > E // 10


def test_record_first_off_leaves_the_first_command(wp_cpu):
    rng = np.random.default_rng(3)
    got = _run_kernel(wp_cpu, *_inputs(rng, 8, 6), False, record_first=0)
    assert not got["p0"].any() and not got["q0"].any() and got["p"].any()


@pytest.mark.parametrize("D", [4, 6])
def test_delta_command_matches_the_torch_path_sign_included(wp_cpu, D):
    """The env's torch bounds (what `step_pose` applies, and what `step` applied before the kernel),
    in float64 from the same inputs: the same quaternion, sign included (the OSC kernel takes the
    shortest way either way, but a flipped sign would change what a test or a log compares)."""
    import torch

    from vkgrl_newton.envs.assembly_env import _bound_tilt
    from vkgrl_newton.rotations import euler_xyz_from_quat, quat_exp, quat_from_euler_xyz, quat_mul, quat_rotate

    rng = np.random.default_rng(5 + D)
    E = 128
    hand_p, hand_q, a, ps, rs, target = _inputs(rng, E, D)
    got = _run_kernel(wp_cpu, hand_p, hand_q, a, ps, rs, target, False, record_first=0)
    t = lambda x: torch.as_tensor(x, dtype=torch.float64)  # noqa: E731
    q_tcp = t(hand_q)
    p = t(hand_p) + quat_rotate(q_tcp, t(TCP_OFFSET).expand(E, 3)) + t(a[:, :3]) * t(ps)
    r = torch.zeros(E, 3, dtype=torch.float64)
    if D == 4:
        r[:, 2] = t(a[:, 3]) * t(rs[:, 2])
    else:
        r = t(a[:, 3:6]) * t(rs)
    q = quat_mul(quat_exp(r), q_tcp)
    p = t(target) + torch.clamp(p - t(target), -POS_BOUND, POS_BOUND)
    if D == 4:
        _, _, yaw = euler_xyz_from_quat(q)
        q = quat_from_euler_xyz(torch.full_like(yaw, math.pi), torch.zeros_like(yaw), yaw)
    else:
        q = _bound_tilt(q, MAX_TILT)
    np.testing.assert_allclose(got["p"], p.numpy(), rtol=0, atol=POS_TOL)
    np.testing.assert_allclose(got["q"], q.numpy(), rtol=0, atol=QUAT_TOL)


@pytest.mark.parametrize("D,unidirectional", [(4, False), (6, False), (4, True), (6, True)])
def test_actions_for_command_inverts_the_mapping_and_its_smoothing(D, unidirectional):
    """AssemblyEnv.actions_for_command (the scripted demonstrator through the SAC action space) against
    the float64 reference above: the pose commanded by a smoothed action s = ema a + (1 - ema) prev gives
    back a; a pose out of reach gives a saturated action of the right sign."""
    import functools
    from types import SimpleNamespace

    import torch

    from vkgrl_newton.envs.assembly_env import AssemblyEnv

    rng = np.random.default_rng(100 + 10 * D + unidirectional)
    E = 256
    hand_p, hand_q, _, pos_scale, rot_scale, _ = _inputs(rng, E, D)
    # hands within 15 deg of down and rotations of at most 0.15 rad: the 30 deg cone's clamp (6D) stays
    # out; the box centred on the TCP: the position bound too (both are the kernel's, not inverted)
    yaw = rng.uniform(-math.pi, math.pi, E)
    yaw[:32], yaw[32:64] = math.pi - rng.uniform(0.0, 0.12, 32), -math.pi + rng.uniform(0.0, 0.12, 32)  # near +-pi:
    # a yaw step of up to 0.146 rad crosses the wrap there, which the inverse must undo
    hand_q = (Rotation.from_rotvec(random_axes(rng, E) * rng.uniform(0.0, math.radians(15.0), E)[:, None])
              * Rotation.from_euler("xyz", np.stack([np.full(E, math.pi), np.zeros(E), yaw], 1)))
    hand_q = hand_q.as_quat().astype(np.float32).astype(np.float64)
    tcp_p = hand_p + Rotation.from_quat(hand_q).apply(TCP_OFFSET)
    raw = rng.uniform(-0.95, 0.95, (E, D))  # the actions to recover
    ema = rng.uniform(0.2, 1.0, E)  # Factory 0.2; Forge 0.025-0.1 would amplify the same errors x8 (see below)
    prev = rng.uniform(-1.0, 1.0, (E, D))
    smoothed = ema[:, None] * raw + (1.0 - ema[:, None]) * prev
    pos, quat = reference(hand_p, hand_q, smoothed, pos_scale, rot_scale, tcp_p, unidirectional)

    f32 = lambda x: torch.tensor(x, dtype=torch.float32)  # noqa: E731
    fake = SimpleNamespace(num_envs=E, tdev=torch.device("cpu"), cfg=SimpleNamespace(action_dim=D),
                           geometry=SimpleNamespace(unidirectional_yaw=unidirectional), pos_scale=f32(pos_scale),
                           rot_scale=f32(rot_scale), ema=f32(ema), actions_applied=f32(prev),
                           tcp_pose=lambda: (f32(tcp_p), f32(hand_q)))
    fake._check_actions = functools.partial(AssemblyEnv._check_actions, fake)
    got = AssemblyEnv.actions_for_command(fake, f32(pos), f32(quat)).double().numpy()
    # float32 error: positions ~0.6 m (6e-8 a rounding, ~4 of them) over pos_scale >= 0.01 m -> 2.4e-5;
    # rotations through quat_mul, quat_log or the Euler yaw (~20 roundings of 1.2e-7 on unit numbers ->
    # 2.4e-6 rad) over rot_scale >= 0.0485 -> 5e-5; then (s - (1 - ema) prev) / ema with ema >= 0.2: x5 -> 2.5e-4
    np.testing.assert_allclose(got, raw, atol=3e-4, rtol=0)

    far = f32(tcp_p + np.array([0.1, -0.1, 0.1]))  # 10 cm: 5x the largest step
    sat = AssemblyEnv.actions_for_command(fake, far, f32(hand_q)).numpy()
    assert (sat[:, 0] == 1.0).all() and (sat[:, 1] == -1.0).all() and (sat[:, 2] == 1.0).all()
