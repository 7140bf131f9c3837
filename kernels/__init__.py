"""Custom Warp kernels (installed as vkgrl_newton.kernels). Warp arrays in, warp arrays out;
no task, config or torch knowledge. `python -m vkgrl_newton.tools.bench_kernels` times them."""

import importlib

# lazy (PEP 562): importing vkgrl_newton.kernels (e.g. for `python -m vkgrl_newton.tools.bench_kernels --help`)
# does not load Warp
_LAZY = {name: "vkgrl_newton.kernels.kmp_horizon" for name in ("kmp_horizon_pose", "kmp_horizon_pose_kernel", "vec6f",
                                                               "mat66f")}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'vkgrl_newton.kernels' has no attribute {name!r}")
