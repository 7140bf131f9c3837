"""KMP horizon evaluation: the KGRL action path of thesis eq. 4.36, batched over environments.

Per environment e, with its control step n = step_index[e] (clamped to the table):
    eta  = m[n] + B[n] zeta[e]                                 (6,)  [x, y, z, rx, ry, rz]
    pos  = target_pos_w[e] + eta[0:3]                          world frame, m       (eq. 5.25)
    quat = ref_quat_w[e] * exp(eta[3:6])                       world frame, xyzw    (eq. 5.32)

m (S, 6) and B (S, 6, 6) are the per-step tables of vkgrl_newton.kmp.tables, shared by all
environments; zeta = w * a is the scaled null-space action (eq. 5.20). The kernel knows
nothing of tasks or torch: warp arrays in, warp arrays out.
"""

from __future__ import annotations

import warp as wp

__all__ = ["vec6f", "mat66f", "kmp_horizon_pose_kernel", "kmp_horizon_pose"]

vec6f = wp.types.vector(length=6, dtype=wp.float32)
mat66f = wp.types.matrix(shape=(6, 6), dtype=wp.float32)

# Below this angle exp() uses the series of sin(t/2)/t; its next term is t^4/3840, below
# float32 resolution here.
_SMALL_ANGLE = wp.constant(1.0e-3)


@wp.func
def quat_exp_rotvec(r: wp.vec3) -> wp.quat:
    """Unit quaternion (xyzw) of the rotation vector r (angle |r| about r/|r|)."""
    theta = wp.length(r)
    scale = float(0.0)
    if theta < _SMALL_ANGLE:
        scale = 0.5 - theta * theta / 48.0
    else:
        scale = wp.sin(0.5 * theta) / theta
    return wp.quat(r[0] * scale, r[1] * scale, r[2] * scale, wp.cos(0.5 * theta))


@wp.kernel
def kmp_horizon_pose_kernel(
    step_index: wp.array(dtype=wp.int32),  # (E,) control step of each env
    zeta: wp.array(dtype=vec6f),  # (E,) scaled null-space action
    kmp_mean_table: wp.array(dtype=vec6f),  # (S,) m[n]
    kmp_gain_table: wp.array(dtype=mat66f),  # (S,) B[n]
    target_pos_w: wp.array(dtype=wp.vec3),  # (E,) target frame position, world
    ref_quat_w: wp.array(dtype=wp.quat),  # (E,) q_ref = q(pi, 0, psi_ref), world, xyzw
    eta_out: wp.array(dtype=vec6f),  # (E,) out: relative pose eta
    tcp_pos_cmd_w: wp.array(dtype=wp.vec3),  # (E,) out: commanded TCP position, world
    tcp_quat_cmd_w: wp.array(dtype=wp.quat),  # (E,) out: commanded TCP orientation, world, xyzw
):
    e = wp.tid()
    n = wp.clamp(step_index[e], 0, kmp_mean_table.shape[0] - 1)
    eta = kmp_mean_table[n] + kmp_gain_table[n] * zeta[e]
    eta_out[e] = eta
    tcp_pos_cmd_w[e] = target_pos_w[e] + wp.vec3(eta[0], eta[1], eta[2])
    q_rel = quat_exp_rotvec(wp.vec3(eta[3], eta[4], eta[5]))
    tcp_quat_cmd_w[e] = wp.normalize(ref_quat_w[e] * q_rel)


def kmp_horizon_pose(
    step_index: wp.array,
    zeta: wp.array,
    kmp_mean_table: wp.array,
    kmp_gain_table: wp.array,
    target_pos_w: wp.array,
    ref_quat_w: wp.array,
    eta_out: wp.array,
    tcp_pos_cmd_w: wp.array,
    tcp_quat_cmd_w: wp.array,
) -> None:
    """Launch `kmp_horizon_pose_kernel` over all environments (len(step_index)) on their device.

    Shapes: step_index (E,) int32; zeta (E,) vec6f; kmp_mean_table (S,) vec6f; kmp_gain_table
    (S,) mat66f; target_pos_w (E,) vec3; ref_quat_w (E,) quat; outputs eta_out (E,) vec6f,
    tcp_pos_cmd_w (E,) vec3, tcp_quat_cmd_w (E,) quat. Raises ValueError on mismatched lengths.
    """
    num_envs = step_index.shape[0]
    for name, arr in (("zeta", zeta), ("target_pos_w", target_pos_w), ("ref_quat_w", ref_quat_w),
                      ("eta_out", eta_out), ("tcp_pos_cmd_w", tcp_pos_cmd_w), ("tcp_quat_cmd_w", tcp_quat_cmd_w)):
        if arr.shape[0] != num_envs:
            raise ValueError(f"{name} has {arr.shape[0]} entries, step_index has {num_envs} (one per environment)")
    if kmp_gain_table.shape[0] != kmp_mean_table.shape[0] or kmp_mean_table.shape[0] == 0:
        raise ValueError(
            f"kmp_mean_table ({kmp_mean_table.shape[0]}) and kmp_gain_table ({kmp_gain_table.shape[0]}) "
            "must have the same, non-zero number of steps"
        )
    wp.launch(
        kmp_horizon_pose_kernel,
        dim=num_envs,
        inputs=[step_index, zeta, kmp_mean_table, kmp_gain_table, target_pos_w, ref_quat_w],
        outputs=[eta_out, tcp_pos_cmd_w, tcp_quat_cmd_w],
        device=step_index.device,
    )
