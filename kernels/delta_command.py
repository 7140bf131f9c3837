"""Factory's delta-pose action mapping (Isaac Lab `factory_env.py`, `_apply_action`), batched over worlds.

Runs once per physics step inside the captured control step (the SAC path of the env), so the
TCP target follows the current TCP pose without a torch op or a host read in the step. Per world
e, one thread, world frame, quaternions xyzw, a = the smoothed action (E, D), D in {4, 6}:

    p_tcp = p_hand + R_hand tcp_offset_hand,  q_tcp = q_hand          (hand pose from body_q)
    p*    = p_tcp + a[0:3] . pos_scale
    r     = (0, 0, a[3] rot_scale_z)          D = 4
            a[3:6] . rot_scale                D = 6
    r_z   = -(a[D-1] + 1) / 2 rot_scale_z     if unidirectional_yaw (NutThread: clockwise only)
    q*    = exp(r) q_tcp
    p*    = target_frame + clamp(p* - target_frame, -pos_bound, pos_bound)   (per axis)
    q*    = q(pi, 0, yaw(q*)) = (cos(yaw/2), sin(yaw/2), 0, 0)               D = 4: gripper down
            q* tilted back onto the cone of half-angle max_tilt about -z     D = 6
            (the gripper axis R* e_z rotated about (R* e_z x -e_z) by tilt - max_tilt when over)

yaw(q) is the XYZ-Euler yaw atan2(2 (w z + x y), 1 - 2 (y^2 + z^2)) (Isaac Lab's
`euler_xyz_from_quat`). The outputs are the command the OSC kernel tracks (`cmd_pos_w`,
`cmd_quat_w`); with `record_first` = 1 they are also copied to `first_pos_w` / `first_quat_w`
(the env's Forge action penalty reads the first command of a control step).

`delta_command_torch` in the tests (tests/test_delta_command_kernel.py) is the float64 reference,
built from vkgrl_newton.rotations.
"""

from __future__ import annotations

import warp as wp

from .kmp_horizon import quat_exp_rotvec  # the package's one Warp exp map

__all__ = ["delta_command_kernel", "delta_command"]

wp.set_module_options({"enable_backward": False})

@wp.kernel
def delta_command_kernel(
    body_q: wp.array(dtype=wp.transform),  # (B,) world poses of all bodies
    hand_body: wp.array(dtype=wp.int32),  # (E,) global body index of each world's hand
    tcp_offset_hand: wp.vec3,  # TCP in the hand frame, m
    actions: wp.array2d(dtype=wp.float32),  # (E, D) smoothed actions in [-1, 1]
    pos_scale: wp.array(dtype=wp.vec3),  # (E,) m per unit action
    rot_scale: wp.array(dtype=wp.vec3),  # (E,) rad per unit action
    target_frame_pos_w: wp.array(dtype=wp.vec3),  # (E,) centre of the position bound box, world
    pos_bound: float,  # m, half-width of the box
    max_tilt: float,  # rad, D = 6 only
    unidirectional_yaw: int,
    record_first: int,
    cmd_pos_w: wp.array(dtype=wp.vec3),  # (E,) out
    cmd_quat_w: wp.array(dtype=wp.quat),  # (E,) out
    first_pos_w: wp.array(dtype=wp.vec3),  # (E,) out when record_first
    first_quat_w: wp.array(dtype=wp.quat),  # (E,) out when record_first
):
    e = wp.tid()
    X = body_q[hand_body[e]]
    q_tcp = wp.transform_get_rotation(X)
    p_tcp = wp.transform_get_translation(X) + wp.quat_rotate(q_tcp, tcp_offset_hand)
    D = actions.shape[1]
    ps = pos_scale[e]
    rs = rot_scale[e]
    p = p_tcp + wp.vec3(actions[e, 0] * ps[0], actions[e, 1] * ps[1], actions[e, 2] * ps[2])
    r = wp.vec3(0.0, 0.0, actions[e, 3] * rs[2])
    if D == 6:
        r = wp.vec3(actions[e, 3] * rs[0], actions[e, 4] * rs[1], actions[e, 5] * rs[2])
    if unidirectional_yaw != 0:
        r = wp.vec3(r[0], r[1], -(actions[e, D - 1] + 1.0) * 0.5 * rs[2])
    q = quat_exp_rotvec(r) * q_tcp

    c = target_frame_pos_w[e]
    d = p - c
    p = c + wp.vec3(wp.clamp(d[0], -pos_bound, pos_bound), wp.clamp(d[1], -pos_bound, pos_bound),
                    wp.clamp(d[2], -pos_bound, pos_bound))
    if D == 4:
        x, y, z, w = q[0], q[1], q[2], q[3]
        yaw = wp.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        q = wp.quat(wp.cos(0.5 * yaw), wp.sin(0.5 * yaw), 0.0, 0.0)
    else:
        axis_z = wp.quat_rotate(q, wp.vec3(0.0, 0.0, 1.0))
        tilt = wp.acos(wp.clamp(-axis_z[2], -1.0, 1.0))
        if tilt > max_tilt:
            axis = wp.cross(axis_z, wp.vec3(0.0, 0.0, -1.0))
            n = wp.max(wp.length(axis), 1.0e-9)
            q = quat_exp_rotvec(axis * ((tilt - max_tilt) / n)) * q
    cmd_pos_w[e] = p
    cmd_quat_w[e] = q
    if record_first != 0:
        first_pos_w[e] = p
        first_quat_w[e] = q


def delta_command(*, body_q, hand_body, tcp_offset_hand, actions, pos_scale, rot_scale, target_frame_pos_w,
                  pos_bound, max_tilt, unidirectional_yaw, record_first, cmd_pos_w, cmd_quat_w, first_pos_w,
                  first_quat_w) -> None:
    """Launch `delta_command_kernel` over the E worlds (keyword arguments as the kernel's)."""
    wp.launch(
        delta_command_kernel, dim=actions.shape[0], device=actions.device,
        inputs=[body_q, hand_body, wp.vec3(*tcp_offset_hand), actions, pos_scale, rot_scale, target_frame_pos_w,
                float(pos_bound), float(max_tilt), int(unidirectional_yaw), int(record_first)],
        outputs=[cmd_pos_w, cmd_quat_w, first_pos_w, first_quat_w],
    )
