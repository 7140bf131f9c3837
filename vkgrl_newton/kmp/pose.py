"""Pose representation of thesis section 5.5: the 6D relative pose eta that the KMP models.

eta = [p_tcp - p_target (3, metres), log(q_ref^-1 * q_tcp) (3, radians)]        (eqs. 5.21, 5.26-5.29)
q_ref = q(roll=pi, pitch=0, yaw=psi_ref), psi_ref = 0 (PegInsert, GearMesh), -40 deg (NutThread)  (5.27-5.28)
Back to a pose: p_tcp = p_target + eta[:3], q_tcp = q_ref * exp(eta[3:])                   (5.25, 5.31-5.32)

Quaternions are (x, y, z, w), Warp's and Newton's order, in world frame. All functions are
batched over leading dimensions and work in the input's dtype (use float64 for references).
The log map returns the rotation vector of the shortest rotation (angle in [0, pi]); the sign
of q is irrelevant (q and -q give the same rotation vector).

4D mode (xyz + yaw): roll and pitch stay at the reference, so the rotation vector is
(0, 0, delta_psi) (eq. 5.33). Sign: q_ref has roll
pi (gripper z down), so q_ref^-1 q(pi, 0, psi_ref + d) = q_z(-d): a world yaw of +d is rz = -d.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = [
    "quat_mul",
    "quat_conjugate",
    "quat_exp",
    "quat_log",
    "quat_from_euler_xyz",
    "euler_xyz_from_quat",
    "quat_rotate",
    "reference_quat",
    "pose_to_eta",
    "eta_to_pose",
    "unwrap_rotation_vectors",
    "AXES_4D",
]

# Components of the 6D eta that the 4D action space moves: x, y, z and yaw (rz).
AXES_4D = (0, 1, 2, 5)

# Below this rotation angle exp/log switch to their Taylor series, where the closed forms
# lose precision (sin(t)/t); chosen so the series' truncation error is below float64 eps.
_SMALL_ANGLE = 1e-6


def _as_tensor(x) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    return torch.as_tensor(x, dtype=torch.float64)


def quat_mul(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product q1 * q2 of (..., 4) xyzw quaternions."""
    q1, q2 = _as_tensor(q1), _as_tensor(q2)
    x1, y1, z1, w1 = q1.unbind(-1)
    x2, y2, z2, w2 = q2.unbind(-1)
    return torch.stack(
        (
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ),
        dim=-1,
    )


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (= inverse for unit quaternions) of (..., 4) xyzw quaternions."""
    q = _as_tensor(q)
    return torch.cat((-q[..., :3], q[..., 3:]), dim=-1)


def quat_exp(rotvec: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (..., 4) xyzw of a rotation vector (..., 3): angle |r| about r/|r|."""
    r = _as_tensor(rotvec)
    theta = torch.linalg.vector_norm(r, dim=-1, keepdim=True)
    half = 0.5 * theta
    small = theta < _SMALL_ANGLE
    safe_theta = torch.where(small, torch.ones_like(theta), theta)
    # sin(theta/2)/theta, with its series 1/2 - theta^2/48 near zero
    scale = torch.where(small, 0.5 - theta * theta / 48.0, torch.sin(half) / safe_theta)
    return torch.cat((r * scale, torch.cos(half)), dim=-1)


def quat_log(q: torch.Tensor) -> torch.Tensor:
    """Rotation vector (..., 3) of unit quaternions (..., 4) xyzw, angle in [0, pi].

    Uses atan2 on (|v|, w), which stays accurate for angles near 0 and near pi, and flips q
    to w >= 0 first so that q and -q map to the same vector.
    """
    q = _as_tensor(q)
    q = torch.where(q[..., 3:4] < 0, -q, q)
    v, w = q[..., :3], q[..., 3:4]
    sin_half = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    theta = 2.0 * torch.atan2(sin_half, w)
    small = sin_half < _SMALL_ANGLE
    safe_sin = torch.where(small, torch.ones_like(sin_half), sin_half)
    # theta / sin(theta/2) = 2 atan(s/w)/s, with its series (2/w)(1 - s^2/(3 w^2)) near zero
    scale = torch.where(small, 2.0 / w * (1.0 - sin_half * sin_half / (3.0 * w * w)), theta / safe_sin)
    return v * scale


def quat_from_euler_xyz(roll, pitch, yaw) -> torch.Tensor:
    """Quaternion xyzw of extrinsic X-Y-Z Euler angles: q = q_z(yaw) * q_y(pitch) * q_x(roll).

    The same convention as Isaac Lab's `quat_from_euler_xyz`, which the thesis's q(pi, 0, psi) uses.
    """
    roll, pitch, yaw = (_as_tensor(a) for a in (roll, pitch, yaw))
    roll, pitch, yaw = torch.broadcast_tensors(roll, pitch, yaw)
    cr, sr = torch.cos(roll * 0.5), torch.sin(roll * 0.5)
    cp, sp = torch.cos(pitch * 0.5), torch.sin(pitch * 0.5)
    cy, sy = torch.cos(yaw * 0.5), torch.sin(yaw * 0.5)
    return torch.stack(
        (
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ),
        dim=-1,
    )


def euler_xyz_from_quat(q) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(roll, pitch, yaw) of an xyzw quaternion, the inverse of `quat_from_euler_xyz`.

    Pitch in [-pi/2, pi/2], roll and yaw in (-pi, pi]; as Isaac Lab's `euler_xyz_from_quat`.
    """
    x, y, z, w = _as_tensor(q).unbind(-1)
    roll = torch.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = torch.asin(torch.clamp(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = torch.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def quat_rotate(q, v) -> torch.Tensor:
    """Rotate (..., 3) vectors v by (..., 4) xyzw quaternions q."""
    q, v = _as_tensor(q), _as_tensor(v)
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * torch.cross(u, v, dim=-1)
    return v + w * t + torch.cross(u, t, dim=-1)


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
