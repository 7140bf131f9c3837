"""The demonstrator's controller inversion against the OSC force law, in float64 (no simulation).

The env's OSC (kernels/osc.py; Isaac Lab's `compute_dof_torque` in factory_control.py, with FORGE's
wrench dead zone) applies per world-frame wrench component
F = dz(Kp . [e_p; e_r] - Kd . [v; w]) with e_p = cmd - x, e_r the axis-angle of cmd_q * q^-1, and
Forge's dead zone dz(f) = f - d sign(f) for |f| > d, else 0. The demonstrator chooses the command
so that this equals its own wrench F* = K (ref - x) - D v (rotation alike). Quaternion references
by scipy's Rotation.
"""

import types

import numpy as np
import torch
from quat_ref import random_quats
from scipy.spatial.transform import Rotation

from vkgrl_newton.envs.scripted import ALIGN, INSERT, ScriptedInserter, ScriptedParams


def _dead_zone(f, d):
    return np.where(np.abs(f) > d, f - np.sign(f) * d, 0.0)


def _rotvec_between(q_to, q_from):
    """Axis * angle (angle in [0, pi]) of q_to * q_from^-1, xyzw, float64."""
    return (Rotation.from_quat(q_to) * Rotation.from_quat(q_from).inv()).as_rotvec()


def test_invert_controller_applies_the_demonstrators_wrench():
    rng = np.random.default_rng(3)
    n = 64
    x = rng.uniform(-0.5, 0.5, (n, 3))
    q = random_quats(rng, n)
    twist = rng.normal(scale=(0.02, 0.02, 0.02, 0.2, 0.2, 0.2), size=(n, 6))
    ref = x + rng.normal(scale=0.01, size=(n, 3))
    # reference orientation within ~0.3 rad of the current one
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(0, 0.3, (n, 1))
    dq = np.hstack((np.sin(angles / 2) * axes, np.cos(angles / 2)))
    ref_q = (Rotation.from_quat(dq) * Rotation.from_quat(q)).as_quat()
    kp = rng.uniform(0.7, 1.41, (n, 6)) * np.array([565.0, 565, 565, 28, 28, 28])
    kd = 2.0 * np.sqrt(kp)
    dead = rng.uniform(0, 1, (n, 1)) * np.array([5.0, 5, 5, 1, 1, 1])
    dead[: n // 4] = 0.0  # Factory-like worlds: no dead zone
    phase = np.where(rng.uniform(size=n) < 0.5, INSERT, ALIGN)
    inside = (phase == INSERT) & (rng.uniform(size=n) < 0.5)  # part in the hole: soft lateral spring

    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    env = types.SimpleNamespace(tcp_pose=lambda: (t(x), t(q)), tcp_twist_w=t(twist), kp=t(kp), kd=t(kd),
                                dead_zone=t(dead))
    params = ScriptedParams()
    policy = ScriptedInserter(params)
    policy.started = torch.ones(n, dtype=torch.bool)
    policy.phase = torch.tensor(phase)
    policy.inside = torch.tensor(inside)
    cmd_p, cmd_q = policy._invert_controller(env, t(ref), t(ref_q))
    cmd_p, cmd_q = cmd_p.numpy(), cmd_q.numpy()

    for e in range(n):
        k_z = params.insert_stiffness_z if phase[e] == INSERT else params.stiffness
        k_xy = params.inside_lateral_stiffness if inside[e] else params.stiffness
        k = np.array([k_xy, k_xy, k_z])
        f_star = k * (ref[e] - x[e]) - params.damping * twist[e, :3]
        t_star = params.rot_stiffness * _rotvec_between(ref_q[e], q[e]) - params.rot_damping * twist[e, 3:]
        # what the env's OSC applies for this command
        e_r = _rotvec_between(cmd_q[e], q[e])
        pre = kp[e] * np.r_[cmd_p[e] - x[e], e_r] - kd[e] * twist[e]
        applied = _dead_zone(pre, dead[e])
        # float64 both ways: ~10 roundings of kp |x| <~ 300 N (cancelling in kp (cmd - x)): <~ 1e-12 N; 1e-7 N bounds it
        np.testing.assert_allclose(applied, np.r_[f_star, t_star], atol=1e-7, err_msg=f"world {e}")
    # sanity: the check can fail (a command at the reference does not apply F* under a dead zone)
    pre_naive = kp[-1] * np.r_[ref[-1] - x[-1], _rotvec_between(ref_q[-1], q[-1])] - kd[-1] * twist[-1]
    f_star = params.stiffness * (ref[-1] - x[-1]) - params.damping * twist[-1, :3]
    assert not np.allclose(_dead_zone(pre_naive, dead[-1])[:3], f_star, atol=1e-3)
    r0 = Rotation.from_quat(cmd_q[0]).as_matrix()
    # float64 (the whole test): a few dozen rounded operations of 2.2e-16 behind each, far below 1e-9
    assert np.allclose(r0 @ r0.T, np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.norm(cmd_q, axis=1), 1.0, atol=1e-9)  # unit command quaternions
