"""Custom Warp kernels (installed as vkgrl_newton.kernels). Warp arrays in, warp arrays out;
no task, config or torch knowledge. `python -m vkgrl_newton.kernels.bench` times them."""

import importlib

# lazy (PEP 562): `python -m vkgrl_newton.kernels.bench --help` answers without loading Warp
_LAZY = {name: "vkgrl_newton.kernels.kmp_horizon" for name in ("kmp_horizon_pose", "kmp_horizon_pose_kernel", "vec6f",
                                                               "mat66f")}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'vkgrl_newton.kernels' has no attribute {name!r}")
