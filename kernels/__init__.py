"""Custom Warp kernels (installed as vkgrl_newton.kernels). Warp arrays in, warp arrays out;
no task, config or torch knowledge. `python -m vkgrl_newton.kernels.bench` times them."""

from .kmp_horizon import kmp_horizon_pose, kmp_horizon_pose_kernel, mat66f, vec6f

__all__ = ["kmp_horizon_pose", "kmp_horizon_pose_kernel", "vec6f", "mat66f"]
