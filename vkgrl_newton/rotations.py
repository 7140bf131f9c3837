"""Quaternion and rotation-vector maths in torch: the one implementation the package uses.

Quaternions are (x, y, z, w), Warp's and Newton's order (USD's (w, x, y, z) is converted where a
stage is written, assets_usd/author.py). A quaternion q rotates a vector from the frame it
describes into the frame it is given in: a body's q in world frame maps body-frame vectors to
world frame. Rotation vectors are unit axis * angle (radians).

All functions are batched over leading dimensions and work in the input's dtype (use float64 for
references); numpy arrays and sequences become float64 tensors. The log map returns the rotation
vector of the shortest rotation (angle in [0, pi]); the sign of q is irrelevant (q and -q give the
same rotation vector). Warp kernels have their own `@wp.func` versions (kernels/).
"""

from __future__ import annotations

import torch

__all__ = [
    "quat_mul",
    "quat_conjugate",
    "quat_exp",
    "quat_log",
    "quat_from_euler_xyz",
    "euler_xyz_from_quat",
    "quat_rotate",
]

# Below this rotation angle exp/log switch to their Taylor series, where the closed forms
# lose precision (sin(t)/t); chosen so the series' truncation error is below float64 eps.
_SMALL_ANGLE = 1e-6


def _as_tensor(x) -> torch.Tensor:
    """x itself if it is a tensor, else x as a float64 tensor."""
    if isinstance(x, torch.Tensor):
        return x
    return torch.as_tensor(x, dtype=torch.float64)


def quat_mul(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product q1 * q2 of (..., 4) xyzw quaternions (q2 applied first)."""
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
    """Quaternion (..., 4) xyzw of extrinsic X-Y-Z Euler angles: q = q_z(yaw) * q_y(pitch) * q_x(roll).

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
    """(roll, pitch, yaw), each (...), of (..., 4) xyzw quaternions: the inverse of `quat_from_euler_xyz`.

    Pitch in [-pi/2, pi/2], roll and yaw in (-pi, pi]; as Isaac Lab's `euler_xyz_from_quat`.
    """
    x, y, z, w = _as_tensor(q).unbind(-1)
    roll = torch.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = torch.asin(torch.clamp(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = torch.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def quat_rotate(q, v) -> torch.Tensor:
    """Rotate (..., 3) vectors v by (..., 4) xyzw unit quaternions q: q v q^-1."""
    q, v = _as_tensor(q), _as_tensor(v)
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * torch.cross(u, v, dim=-1)
    return v + w * t + torch.cross(u, t, dim=-1)
