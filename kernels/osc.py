"""Task-space impedance ("OSC") torques of Isaac Lab Factory (`compute_dof_torque`), batched over environments.

Per environment e, one thread, with the robot's 7 arm joints (world frame everywhere, quaternions xyzw):
    p_tcp = p_hand + R_hand tcp_offset_hand,  q_tcp = q_hand                         TCP pose
    r     = p_tcp - p_com                     (p_com: the hand body's centre of mass, world)
    v_tcp = v_com + w x r,                    w: hand angular velocity                TCP twist
    J     = [J_lin_com + J_ang x r; J_ang]    (6, 7)  i.e. J_lin_com - skew(r) J_ang  TCP Jacobian
    e_p   = p* - p_tcp
    e_r   = rotvec(q* q_tcp^-1), q* first negated if <q*, q_tcp> < 0                 angle in [0, pi]
    F     = kp . [e_p; e_r] - kd . [v_tcp; w], then the FORGE dead zone per component:
            |F_i| < d_i -> 0, else F_i - sign(F_i) d_i                                (d = 0: off)
    tau   = J^T F
          + (I - J^T Lambda J M^-1) M u,   u = kp_null wrap_[-pi,pi](q_null - q) - kd_null qd,
                                           Lambda = (J M^-1 J^T)^-1                 (null space)
    tau   <- clamp(tau, -torque_limit, torque_limit), written to the arm columns of joint_f.

Dynamics come from Newton: `newton.eval_jacobian` (A, 6*Lmax, Dmax), rows 6L..6L+2 the linear velocity
of link L's centre of mass, rows 6L+3..6L+5 its angular velocity, both world frame; and
`newton.eval_mass_matrix` (A, Dmax, Dmax), armature included. M is the 7x7 arm block.

Null space. Since the posture command is u = M u0, M^-1 u = u0 and the projection is evaluated as
    tau_null = M u0 - J^T y,   (J M^-1 J^T + eps diag(J M^-1 J^T)) y = J u0,   eps = 1e-6,
with two in-kernel Choleskys (M, then the 6x6 task matrix). The relative diagonal regularization eps
keeps the solve finite at kinematic singularities; it is unit-consistent (it scales with each axis'
own entry, so metres and radians need no common scale) and away from singularities it changes the
null torque by about eps * cond(J M^-1 J^T): on the Franka near the Factory reset pose (cond ~200)
by 6e-6 relative (median; max 1.7e-5), the order of the float32 error itself. Its price:
J M^-1 tau_null is eps diag(J M^-1 J^T) Lambda_eps J u0 instead of exactly 0. Cholesky pivots are
clamped to at least 1e-7 of the diagonal entry so float32 cancellation can't produce NaN.
kp_null = kd_null = 0 skips the null-space branch entirely, so the torque is then exactly clamp(J^T F).

One deliberate difference from Isaac Lab: Factory's J is the mean of the two finger bodies' Jacobians
(a point between the finger bodies, ~5 cm above the TCP), while its pose error and twist are at the
TCP; here J is the TCP Jacobian, consistent with the error and twist (as Newton's own controller).

`osc_torques_torch` is the same computation batched in torch (any float dtype), for benchmarks and
tests. The kernel module is compiled without backward code (it is a controller, not differentiated).
"""

from __future__ import annotations

import math

from typing import Any

import warp as wp

from .kmp_horizon import mat66f, vec6f

__all__ = ["vec7f", "mat77f", "mat67f", "OSC_TASK_REG", "osc_torques_kernel", "osc_torques", "osc_torques_torch",
           "quat_to_rotvec", "wrap_to_pi"]

wp.set_module_options({"enable_backward": False})

vec7f = wp.types.vector(length=7, dtype=wp.float32)
mat77f = wp.types.matrix(shape=(7, 7), dtype=wp.float32)
mat67f = wp.types.matrix(shape=(6, 7), dtype=wp.float32)

OSC_TASK_REG = 1.0e-6  # eps of the null-space task matrix regularization, see the module docstring
_TASK_REG = wp.constant(OSC_TASK_REG)
_PIVOT_FLOOR = wp.constant(1.0e-7)  # Cholesky pivot >= this * |diagonal entry|
# Below this |vector part| (= sin(angle/2)) rotvec uses the series of 2 atan2(s, w)/s; its next term,
# s^4/5, is below float32 resolution.
_SMALL_SIN = wp.constant(1.0e-3)
_PI = wp.constant(math.pi)
_TWO_PI = wp.constant(2.0 * math.pi)


@wp.func
def quat_to_rotvec(q: wp.quat) -> wp.vec3:
    """Rotation vector (unit axis * angle, angle in [0, pi]) of a unit quaternion q (xyzw); 0 at identity."""
    v = wp.vec3(q[0], q[1], q[2])
    w = q[3]
    if w < 0.0:  # q and -q are the same rotation: take the one with the shorter angle
        v = -v
        w = -w
    s = wp.length(v)
    scale = float(0.0)
    if s < _SMALL_SIN:
        scale = (2.0 / w) * (1.0 - s * s / (3.0 * w * w))
    else:
        scale = 2.0 * wp.atan2(s, w) / s
    return v * scale


@wp.func
def wrap_to_pi(x: float) -> float:
    """x wrapped to [-pi, pi), as Python's (x + pi) % (2 pi) - pi."""
    return x - _TWO_PI * wp.floor((x + _PI) / _TWO_PI)


@wp.func
def cholesky(m: Any):
    """Lower Cholesky factor L (L L^T = m) of a symmetric positive definite n x n matrix (any
    square Warp matrix type); the upper part is 0. Pivots are floored at _PIVOT_FLOOR |m_jj|."""
    n = len(m)
    l = m * 0.0
    for j in range(n):
        d = m[j, j]
        for k in range(j):
            d -= l[j, k] * l[j, k]
        d = wp.sqrt(wp.max(d, _PIVOT_FLOOR * wp.abs(m[j, j])))
        l[j, j] = d
        for i in range(j + 1, n):
            s = m[i, j]
            for k in range(j):
                s -= l[i, k] * l[j, k]
            l[i, j] = s / d
    return l


@wp.func
def cholesky_solve(l: Any, b: Any):
    """x with L L^T x = b, L the lower factor from `cholesky` (matching matrix and vector sizes)."""
    n = len(b)
    y = b * 0.0
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= l[i, k] * y[k]
        y[i] = s / l[i, i]
    x = b * 0.0
    for ii in range(n):
        i = n - 1 - ii
        s = y[i]
        for k in range(i + 1, n):
            s -= l[k, i] * x[k]
        x[i] = s / l[i, i]
    return x


@wp.kernel
def osc_torques_kernel(
    jacobian: wp.array3d(dtype=wp.float32),  # (A, 6*Lmax, Dmax) newton.eval_jacobian: COM twist rows per link, world
    mass_matrix: wp.array3d(dtype=wp.float32),  # (A, Dmax, Dmax) newton.eval_mass_matrix
    robot_articulation: wp.array(dtype=wp.int32),  # (E,) articulation index of env e's robot
    hand_link: int,  # link (row block) index of the hand inside the articulation
    arm_dof_start: int,  # first arm column of the articulation's DOFs in jacobian / mass_matrix
    body_q: wp.array(dtype=wp.transform),  # (B,) body poses, world, quaternion xyzw
    body_qd: wp.array(dtype=wp.spatial_vector),  # (B,) (COM linear velocity, angular velocity), world
    body_com: wp.array(dtype=wp.vec3),  # (B,) centre of mass, body frame
    hand_body: wp.array(dtype=wp.int32),  # (E,) global body index of env e's hand
    tcp_offset_hand: wp.vec3,  # TCP position, hand frame (TCP orientation = hand orientation)
    joint_q: wp.array2d(dtype=wp.float32),  # (E, Qw) joint coordinates per world
    joint_qd: wp.array2d(dtype=wp.float32),  # (E, Dw) joint velocities per world
    arm_q_start: int,  # first arm column of joint_q
    arm_qd_start: int,  # first arm column of joint_qd and joint_f
    target_pos_w: wp.array(dtype=wp.vec3),  # (E,) TCP target position p*, world
    target_quat_w: wp.array(dtype=wp.quat),  # (E,) TCP target orientation q*, world, xyzw
    kp: wp.array(dtype=vec6f),  # (E,) stiffness: xyz [N/m], then rotation [N m/rad]
    kd: wp.array(dtype=vec6f),  # (E,) damping: xyz [N s/m], then rotation [N m s/rad]
    dead_zone: wp.array(dtype=vec6f),  # (E,) wrench dead zone [N, N m] per component (0: off)
    q_null: wp.array(dtype=wp.float32),  # (7,) null-space posture [rad]
    kp_null: float,  # null-space stiffness [1/s^2] (scaled by M)
    kd_null: float,  # null-space damping [1/s]; kp_null = kd_null = 0 disables the null space
    torque_limit: wp.array(dtype=wp.float32),  # (7,) |tau_j| <= torque_limit[j] [N m]
    tcp_pos_w: wp.array(dtype=wp.vec3),  # (E,) out: TCP position, world
    tcp_quat_w: wp.array(dtype=wp.quat),  # (E,) out: TCP orientation, world, xyzw
    tcp_twist_w: wp.array(dtype=wp.spatial_vector),  # (E,) out: TCP (linear, angular) velocity, world
    wrench_w: wp.array(dtype=vec6f),  # (E,) out: commanded wrench F (force, torque), world, after dead zone
    joint_f: wp.array2d(dtype=wp.float32),  # (E, Dw) out: columns arm_qd_start..+6 get tau, others untouched
):
    e = wp.tid()
    a = robot_articulation[e]
    hb = hand_body[e]
    row0 = 6 * hand_link

    # TCP pose and twist
    x_hand = body_q[hb]
    q_tcp = wp.transform_get_rotation(x_hand)
    p_tcp = wp.transform_point(x_hand, tcp_offset_hand)
    r = p_tcp - wp.transform_point(x_hand, body_com[hb])  # COM -> TCP, world
    twist_com = body_qd[hb]
    w = wp.spatial_bottom(twist_com)
    v_tcp = wp.spatial_top(twist_com) + wp.cross(w, r)

    # TCP Jacobian: linear rows J_lin + J_ang x r (= J_lin - skew(r) J_ang), angular rows unchanged
    jac = mat67f()
    for j in range(7):
        c = arm_dof_start + j
        j_lin = wp.vec3(jacobian[a, row0 + 0, c], jacobian[a, row0 + 1, c], jacobian[a, row0 + 2, c])
        j_ang = wp.vec3(jacobian[a, row0 + 3, c], jacobian[a, row0 + 4, c], jacobian[a, row0 + 5, c])
        j_lin = j_lin + wp.cross(j_ang, r)
        for i in range(3):
            jac[i, j] = j_lin[i]
            jac[i + 3, j] = j_ang[i]

    # pose error and wrench
    e_p = target_pos_w[e] - p_tcp
    q_des = target_quat_w[e]
    if wp.dot(q_des, q_tcp) < 0.0:
        q_des = -q_des
    e_r = quat_to_rotvec(q_des * wp.quat_inverse(q_tcp))
    err = vec6f(e_p[0], e_p[1], e_p[2], e_r[0], e_r[1], e_r[2])
    vel = vec6f(v_tcp[0], v_tcp[1], v_tcp[2], w[0], w[1], w[2])
    wrench = wp.cw_mul(kp[e], err) - wp.cw_mul(kd[e], vel)
    dz = dead_zone[e]
    for i in range(6):
        f = wrench[i]
        if wp.abs(f) < dz[i]:
            wrench[i] = 0.0
        else:
            wrench[i] = f - wp.sign(f) * dz[i]

    tau = wp.transpose(jac) * wrench

    # null-space posture, dynamically consistent: tau_null = M u0 - J^T (J M^-1 J^T)^-1 J u0
    if kp_null != 0.0 or kd_null != 0.0:
        m = mat77f()
        u0 = vec7f()
        for i in range(7):
            for j in range(7):
                m[i, j] = mass_matrix[a, arm_dof_start + i, arm_dof_start + j]
            dq = wrap_to_pi(q_null[i] - joint_q[e, arm_q_start + i])
            u0[i] = kp_null * dq - kd_null * joint_qd[e, arm_qd_start + i]
        l_m = cholesky(m)
        # task matrix J M^-1 J^T, one column of M^-1 J^T per task row
        minv_jt = mat67f()  # row i = (M^-1 J^T)[:, i]
        for i in range(6):
            jrow = vec7f()
            for j in range(7):
                jrow[j] = jac[i, j]
            col = cholesky_solve(l_m, jrow)
            for j in range(7):
                minv_jt[i, j] = col[j]
        task = jac * wp.transpose(minv_jt)
        task = 0.5 * (task + wp.transpose(task))
        for i in range(6):
            task[i, i] = task[i, i] * (1.0 + _TASK_REG)
        y = cholesky_solve(cholesky(task), jac * u0)
        tau += m * u0 - wp.transpose(jac) * y

    for j in range(7):
        lim = torque_limit[j]
        joint_f[e, arm_qd_start + j] = wp.clamp(tau[j], -lim, lim)

    tcp_pos_w[e] = p_tcp
    tcp_quat_w[e] = q_tcp
    tcp_twist_w[e] = wp.spatial_vector(v_tcp, w)
    wrench_w[e] = wrench


def osc_torques(
    *,
    jacobian: wp.array,
    mass_matrix: wp.array,
    robot_articulation: wp.array,
    hand_link: int,
    arm_dof_start: int,
    body_q: wp.array,
    body_qd: wp.array,
    body_com: wp.array,
    hand_body: wp.array,
    tcp_offset_hand,
    joint_q: wp.array,
    joint_qd: wp.array,
    arm_q_start: int,
    arm_qd_start: int,
    target_pos_w: wp.array,
    target_quat_w: wp.array,
    kp: wp.array,
    kd: wp.array,
    dead_zone: wp.array,
    q_null: wp.array,
    kp_null: float,
    kd_null: float,
    torque_limit: wp.array,
    tcp_pos_w: wp.array,
    tcp_quat_w: wp.array,
    tcp_twist_w: wp.array,
    wrench_w: wp.array,
    joint_f: wp.array,
) -> None:
    """Launch `osc_torques_kernel` over all environments (len(robot_articulation)) on their device.

    Shapes as in the kernel: jacobian (A, 6*Lmax, Dmax) and mass_matrix (A, Dmax, Dmax) float32;
    robot_articulation, hand_body (E,) int32; body_q (B,) transform, body_qd (B,) spatial_vector,
    body_com (B,) vec3; tcp_offset_hand a vec3 or 3-sequence; joint_q (E, Qw), joint_qd and joint_f
    (E, Dw) float32 2D (per-world views of the model's flat arrays); target_pos_w (E,) vec3,
    target_quat_w (E,) quat; kp, kd, dead_zone (E,) vec6f; q_null, torque_limit (7,) float32; outputs
    tcp_pos_w (E,) vec3, tcp_quat_w (E,) quat, tcp_twist_w (E,) spatial_vector, wrench_w (E,) vec6f,
    and joint_f written in place (arm columns only). kp_null = kd_null = 0 turns the null space off.
    Raises ValueError on mismatched lengths or arm columns out of range.
    """
    num_envs = robot_articulation.shape[0]
    for name, arr in (("hand_body", hand_body), ("joint_q", joint_q), ("joint_qd", joint_qd),
                      ("target_pos_w", target_pos_w), ("target_quat_w", target_quat_w), ("kp", kp), ("kd", kd),
                      ("dead_zone", dead_zone), ("tcp_pos_w", tcp_pos_w), ("tcp_quat_w", tcp_quat_w),
                      ("tcp_twist_w", tcp_twist_w), ("wrench_w", wrench_w), ("joint_f", joint_f)):
        if arr.shape[0] != num_envs:
            raise ValueError(f"{name} has {arr.shape[0]} rows, robot_articulation has {num_envs} (one per environment)")
    for name, arr in (("joint_q", joint_q), ("joint_qd", joint_qd), ("joint_f", joint_f),
                      ("jacobian", jacobian), ("mass_matrix", mass_matrix)):
        want = 3 if name in ("jacobian", "mass_matrix") else 2
        if arr.ndim != want:
            raise ValueError(f"{name} must be {want}D, got shape {arr.shape}")
    checks = (
        ("arm_q_start", arm_q_start, joint_q.shape[1]),
        ("arm_qd_start", arm_qd_start, min(joint_qd.shape[1], joint_f.shape[1])),
        ("arm_dof_start", arm_dof_start, min(jacobian.shape[2], mass_matrix.shape[1], mass_matrix.shape[2])),
    )
    for name, start, width in checks:
        if start < 0 or start + 7 > width:
            raise ValueError(f"{name}={start}: 7 arm columns do not fit in {width}")
    if hand_link < 0 or 6 * hand_link + 6 > jacobian.shape[1]:
        raise ValueError(f"hand_link={hand_link} is outside the jacobian's {jacobian.shape[1] // 6} links")
    if mass_matrix.shape[0] != jacobian.shape[0]:
        raise ValueError(f"mass_matrix has {mass_matrix.shape[0]} articulations, jacobian {jacobian.shape[0]}")
    if q_null.shape[0] != 7 or torque_limit.shape[0] != 7:
        raise ValueError(f"q_null ({q_null.shape[0]}) and torque_limit ({torque_limit.shape[0]}) need 7 entries")
    wp.launch(
        osc_torques_kernel,
        dim=num_envs,
        inputs=[jacobian, mass_matrix, robot_articulation, int(hand_link), int(arm_dof_start), body_q, body_qd,
                body_com, hand_body, wp.vec3(*tcp_offset_hand), joint_q, joint_qd, int(arm_q_start),
                int(arm_qd_start), target_pos_w, target_quat_w, kp, kd, dead_zone, q_null, float(kp_null),
                float(kd_null), torque_limit],
        outputs=[tcp_pos_w, tcp_quat_w, tcp_twist_w, wrench_w, joint_f],
        device=robot_articulation.device,
    )


# ---------------------------------------------------------------------------------------------------
# torch: the same computation, batched (benchmark baseline and a second implementation to test),
# on the package's torch quaternion maths (vkgrl_newton.rotations)


def osc_torques_torch(
    *,
    jacobian,
    mass_matrix,
    robot_articulation,
    hand_link: int,
    arm_dof_start: int,
    body_q,
    body_qd,
    body_com,
    hand_body,
    tcp_offset_hand,
    joint_q,
    joint_qd,
    arm_q_start: int,
    arm_qd_start: int,
    target_pos_w,
    target_quat_w,
    kp,
    kd,
    dead_zone,
    q_null,
    kp_null: float,
    kd_null: float,
    torque_limit,
    joint_f=None,
):
    """`osc_torques` in batched torch, same arguments as torch tensors of one float dtype (body_q (B, 7) as
    p xyz + quat xyzw, body_qd (B, 6), target_quat_w (E, 4), kp/kd/dead_zone (E, 6), index tensors
    integer). Returns (tcp_pos_w (E, 3), tcp_quat_w (E, 4), tcp_twist_w (E, 6), wrench_w (E, 6),
    tau (E, 7)); when joint_f (E, Dw) is given, tau is also written to its arm columns."""
    import torch

    # torch only here, in the twin: the Warp kernel above needs neither torch nor these
    from ..rotations import quat_conjugate, quat_log, quat_mul, quat_rotate

    a = robot_articulation.long()
    hb = hand_body.long()
    cols = slice(arm_dof_start, arm_dof_start + 7)
    jac_hand = jacobian[a, 6 * hand_link:6 * hand_link + 6, cols]  # (E, 6, 7)
    x_hand = body_q[hb]
    p_hand, q_tcp = x_hand[:, :3], x_hand[:, 3:]
    offset = torch.as_tensor(tcp_offset_hand, dtype=body_q.dtype, device=body_q.device).expand_as(p_hand)
    p_tcp = p_hand + quat_rotate(q_tcp, offset)
    r = p_tcp - (p_hand + quat_rotate(q_tcp, body_com[hb]))
    twist = body_qd[hb]
    w = twist[:, 3:]
    v_tcp = twist[:, :3] + torch.linalg.cross(w, r, dim=-1)
    j_ang = jac_hand[:, 3:]
    j_lin = jac_hand[:, :3] + torch.linalg.cross(j_ang, r[:, :, None].expand_as(j_ang), dim=1)
    jac = torch.cat([j_lin, j_ang], dim=1)  # (E, 6, 7)

    e_p = target_pos_w - p_tcp
    q_des = torch.where((target_quat_w * q_tcp).sum(-1, keepdim=True) < 0.0, -target_quat_w, target_quat_w)
    e_r = quat_log(quat_mul(q_des, quat_conjugate(q_tcp)))  # the kernel's quat_to_rotvec, angle in [0, pi]
    vel = torch.cat([v_tcp, w], dim=-1)
    wrench = kp * torch.cat([e_p, e_r], dim=-1) - kd * vel
    wrench = torch.where(wrench.abs() < dead_zone, torch.zeros_like(wrench), wrench - torch.sign(wrench) * dead_zone)
    jac_t = jac.transpose(1, 2)
    tau = (jac_t @ wrench[:, :, None])[:, :, 0]

    if kp_null != 0.0 or kd_null != 0.0:
        m = mass_matrix[a][:, cols, cols]
        dq = q_null[None, :] - joint_q[:, arm_q_start:arm_q_start + 7]
        dq = torch.remainder(dq + math.pi, 2.0 * math.pi) - math.pi
        u0 = kp_null * dq - kd_null * joint_qd[:, arm_qd_start:arm_qd_start + 7]
        l_m, _ = torch.linalg.cholesky_ex(m)
        task = jac @ torch.cholesky_solve(jac_t, l_m)
        task = 0.5 * (task + task.transpose(1, 2))
        task = task + OSC_TASK_REG * torch.diag_embed(torch.diagonal(task, dim1=1, dim2=2))
        l_t, _ = torch.linalg.cholesky_ex(task)
        y = torch.cholesky_solve(jac @ u0[:, :, None], l_t)
        tau = tau + (m @ u0[:, :, None] - jac_t @ y)[:, :, 0]

    tau = torch.clamp(tau, -torque_limit, torque_limit)
    if joint_f is not None:
        joint_f[:, arm_qd_start:arm_qd_start + 7] = tau.to(joint_f.dtype)
    return p_tcp, q_tcp, torch.cat([v_tcp, w], dim=-1), wrench, tau
