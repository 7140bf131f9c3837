"""Pose representation of thesis section 5.5: the 6D relative pose eta that the KMP models.

eta = [p_tcp - p_target (3, metres), log(q_ref^-1 * q_tcp) (3, radians)]        (eqs. 5.21, 5.26-5.29)
q_ref = q(roll=pi, pitch=0, yaw=psi_ref), psi_ref = 0 (PegInsert, GearMesh), -40 deg (NutThread)  (5.27-5.28)
Back to a pose: p_tcp = p_target + eta[:3], q_tcp = q_ref * exp(eta[3:])                   (5.25, 5.31-5.32)

Quaternions are (x, y, z, w), Warp's and Newton's order, in world frame; the quaternion maths
(exp, log, products, Euler angles) is vkgrl_newton.rotations. All functions are batched over
leading dimensions and work in the input's dtype (use float64 for references).

4D mode (xyz + yaw): roll and pitch stay at the reference, so the rotation vector is
(0, 0, delta_psi) (eq. 5.33). Sign: q_ref has roll
pi (gripper z down), so q_ref^-1 q(pi, 0, psi_ref + d) = q_z(-d): a world yaw of +d is rz = -d.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..rotations import _as_tensor, quat_conjugate, quat_exp, quat_from_euler_xyz, quat_log, quat_mul

__all__ = [
    "reference_quat",
    "pose_to_eta",
    "eta_to_pose",
    "unwrap_rotation_vectors",
    "AXES_4D",
]

# Components of the 6D eta that the 4D action space moves: x, y, z and yaw (rz).
AXES_4D = (0, 1, 2, 5)


def reference_quat(psi_ref: float, dtype=torch.float64, device=None) -> torch.Tensor:
    """q_ref = q(pi, 0, psi_ref) of eq. 5.27: gripper pointing down, yawed by psi_ref (radians)."""
    return quat_from_euler_xyz(
        torch.tensor(math.pi, dtype=dtype, device=device),
        torch.tensor(0.0, dtype=dtype, device=device),
        torch.tensor(float(psi_ref), dtype=dtype, device=device),
    )


def pose_to_eta(p_tcp, q_tcp, p_target, psi_ref: float) -> torch.Tensor:
    """6D relative pose eta (..., 6) of a TCP pose, eqs. 5.21 and 5.26-5.29.

    p_tcp (..., 3) and q_tcp (..., 4, xyzw) in world frame; p_target (..., 3) world frame.
    """
    p_tcp, q_tcp, p_target = _as_tensor(p_tcp), _as_tensor(q_tcp), _as_tensor(p_target)
    q_ref = reference_quat(psi_ref, dtype=q_tcp.dtype, device=q_tcp.device)
    q_rel = quat_mul(quat_conjugate(q_ref).expand_as(q_tcp), q_tcp)
    return torch.cat((p_tcp - p_target, quat_log(q_rel)), dim=-1)


def eta_to_pose(eta, p_target, psi_ref: float) -> tuple[torch.Tensor, torch.Tensor]:
    """TCP pose (p_tcp (..., 3), q_tcp (..., 4) xyzw) of a 6D relative pose, eqs. 5.25, 5.31-5.32."""
    eta, p_target = _as_tensor(eta), _as_tensor(p_target)
    q_ref = reference_quat(psi_ref, dtype=eta.dtype, device=eta.device)
    q_rel = quat_exp(eta[..., 3:])
    return p_target + eta[..., :3], quat_mul(q_ref.expand_as(q_rel), q_rel)


def unwrap_rotation_vectors(rotvec) -> np.ndarray:
    """Make a sequence of rotation vectors (T, 3) continuous across the log map's wrap at pi.

    log() returns angles in [0, pi]; a rotation passing through pi flips to the antipodal
    vector. Each sample is replaced by the equivalent vector r + 2 pi k r/|r| (k = -1, 0, 1
    relative to the previous sample's winding) closest to its predecessor, so that KMP sees a
    smooth trajectory (e.g. a nut turned past 180 degrees). exp() of the result is unchanged.
    """
    r = np.array(rotvec, dtype=np.float64, copy=True)
    if r.ndim != 2 or r.shape[1] != 3:
        raise ValueError(f"rotvec must have shape (T, 3), got {r.shape}")
    for t in range(1, r.shape[0]):
        angle = np.linalg.norm(r[t])
        if angle < 1e-12:
            continue
        axis = r[t] / angle
        # candidates with the same rotation: (angle + 2 pi k) * axis, k in a small range
        cands = [(angle + 2.0 * math.pi * k) * axis for k in range(-2, 3)]
        r[t] = min(cands, key=lambda c: float(np.linalg.norm(c - r[t - 1])))
    return r
