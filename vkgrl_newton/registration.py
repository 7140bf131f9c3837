"""gymnasium ids for every task x family x action space x observation/action variant.

`import vkgrl_newton` registers them (`register_envs`, idempotent); `gymnasium.make_vec(id,
num_envs=N, **kwargs)` builds an `envs.vector.AssemblyVectorEnv` (one batched simulation of N
worlds):

    VKGRL/<Task>-<Family>-<D>D[-Vision][-KGRL]-v0
    Task: PegInsert | GearMesh | NutThread; Family: Factory | Forge; D: 4 | 6
    -KGRL: actions in the KMP prior's null space (a = 0 follows the prior); -Vision: the
    observation adds the frozen VAE latent of the task camera (thesis 5.6)

3 x 2 x 2 x 4 = 48 ids. kwargs (make_vec's): device (None: CUDA when present), seed, cache_dir
(where the KGRL prior and the vision VAE are made once and reused, as train/run.py does),
tensors ("numpy" | "torch"), geometry ("primitives" | "mesh" for GearMesh and NutThread), vae (a
vae.pt of your own). The ids are built here from `tasks.py`, not imported from the env, so that
registering costs no torch, Warp or Newton import.
"""

from __future__ import annotations

from .tasks import ACTION_DIMS, FAMILIES, TASKS

__all__ = ["NAMESPACE", "VARIANTS", "env_id", "env_ids", "register_envs"]

NAMESPACE = "VKGRL"
VECTOR_ENTRY_POINT = "vkgrl_newton.envs.vector:AssemblyVectorEnv"
VARIANTS = {"": (False, False), "-KGRL": (True, False), "-Vision": (False, True), "-Vision-KGRL": (True, True)}
# (kgrl, vision): SAC, KGRL, Vision-SAC and Vision-KGRL's env of the thesis


def env_id(task: str, family: str, action_dim: int, kgrl: bool = False, vision: bool = False) -> str:
    """'VKGRL/PegInsert-Factory-4D-KGRL-v0' for (PegInsert, factory, 4, kgrl=True)."""
    suffix = {v: k for k, v in VARIANTS.items()}[(bool(kgrl), bool(vision))]
    return f"{NAMESPACE}/{task}-{family.capitalize()}-{int(action_dim)}D{suffix}-v0"


def env_ids() -> dict[str, dict]:
    """Every id with its kwargs (task, family, action_dim, kgrl, vision), in a fixed order."""
    return {env_id(t, f, d, kgrl, vision): {"task": t, "family": f, "action_dim": d, "kgrl": kgrl, "vision": vision}
            for t in TASKS for f in FAMILIES for d in ACTION_DIMS for kgrl, vision in VARIANTS.values()}


def register_envs() -> list[str]:
    """Register every id with gymnasium (already registered ones are left as they are)."""
    import gymnasium as gym

    for name, kwargs in env_ids().items():
        if name not in gym.registry:
            gym.register(id=name, vector_entry_point=VECTOR_ENTRY_POINT, kwargs=dict(kwargs))
    return list(env_ids())
