"""vkgrl-newton: demonstration-guided, vision-augmented RL (KGRL, Vision-KGRL) for contact-rich
assembly on NVIDIA Newton and Warp.

Pipeline, one direction: assets_usd -> sim -> envs -> agents -> train. Subpackages:
`kmp` (the KGRL trajectory prior), `kernels` (Warp kernels), `tasks` (per-task facts),
`rotations` (the torch quaternion maths).
"""

__version__ = "0.1.0"
