"""vkgrl-newton: demonstration-guided, vision-augmented RL (KGRL, Vision-KGRL) for contact-rich
assembly on NVIDIA Newton and Warp.

Pipeline, one direction: assets_usd -> sim -> envs -> agents -> train. Subpackages:
`kmp` (the KGRL trajectory prior), `kernels` (Warp kernels), `tasks` (per-task facts),
`rotations` (the torch quaternion maths). Importing the package registers its gymnasium ids
(`registration.py`; `gymnasium.make_vec("VKGRL/PegInsert-Factory-4D-KGRL-v0", num_envs=16)`).
"""

__version__ = "0.1.0"

from .registration import register_envs as _register_envs

_register_envs()  # the gymnasium ids VKGRL/<Task>-<Family>-<D>D[-Vision][-KGRL]-v0 (registration.py)
