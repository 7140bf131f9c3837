"""gymnasium ids for every task x family x action space x observation/action variant.

`import vkgrl_newton` registers them (`register_envs`, idempotent); `gymnasium.make(id)` builds one
world as a gymnasium `Env` (`envs.vector.AssemblySingleEnv`: for the env checkers, wrappers and
single-env learners); `gymnasium.make_vec(id,
num_envs=N, **kwargs)` builds an `envs.vector.AssemblyVectorEnv` (one batched simulation of N
worlds):

    VKGRL/<Task>-<Family>-<D>D[-Vision][-KGRL]-v0
    Task: PegInsert | GearMesh | NutThread; Family: Factory | Forge; D: 4 | 6
    -KGRL: actions in the KMP prior's null space (a = 0 follows the prior); -Vision: the
    observation adds the frozen VAE latent of the task camera (thesis 5.6)

3 x 2 x 2 x 4 = 48 ids, each the env of one train/run.py method (spec kwargs `method`), built by
the run library's builder (`run.gym.make_vec_env`) exactly as run.py builds it: the KGRL ids in the
null space of the preset's KGRL recipe (`kgrl_recipe=None`: on a CPU's quick preset residual for PegInsert
Factory 4D, whose a = 0 is a fixed controller of the ceiling instead of the prior, and reach_keep_prior for the
others; base, the thesis's, on CUDA's thesis preset; or name one; `preset=` chooses the preset). kwargs (make_vec's): device (None: CUDA when present), seed, cache_dir
(where the KGRL prior and the vision VAE are made once and reused, as train/run.py does),
tensors ("numpy" | "torch"), geometry ("primitives" | "mesh" for GearMesh and NutThread), vae (a
vae.pt of your own). The ids are built here from `tasks.py`, not imported from the env, so that
registering costs no torch, Warp or Newton import.
"""

from __future__ import annotations

from .tasks import ACTION_DIMS, FAMILIES, TASKS

__all__ = ["NAMESPACE", "VARIANTS", "env_id", "env_ids", "register_envs"]

NAMESPACE = "VKGRL"
VECTOR_ENTRY_POINT = "vkgrl_newton.run.gym:make_vec_env"  # through the run library's builder
ENTRY_POINT = "vkgrl_newton.run.gym:make_env"  # gymnasium.make: one world (envs.vector.AssemblySingleEnv)
VARIANTS = {"": (False, False), "-KGRL": (True, False), "-Vision": (False, True), "-Vision-KGRL": (True, True)}
# (kgrl, vision): SAC, KGRL, Vision-SAC and Vision-KGRL's env of the thesis: the train/run.py method of each
VARIANT_METHODS = {(False, False): "sac", (True, False): "kgrl", (False, True): "vision_sac", (True, True): "vision_kgrl"}


def env_id(task: str, family: str, action_dim: int, kgrl: bool = False, vision: bool = False,
           method: str | None = None, **_spec) -> str:
    """'VKGRL/PegInsert-Factory-4D-KGRL-v0' for (PegInsert, factory, 4, kgrl=True) or (..., method="kgrl");
    the rest of an id's spec kwargs (kgrl_recipe) do not change its name."""
    if method is not None:
        kgrl, vision = {m: kv for kv, m in VARIANT_METHODS.items()}[method]
    suffix = {v: k for k, v in VARIANTS.items()}[(bool(kgrl), bool(vision))]
    return f"{NAMESPACE}/{task}-{family.capitalize()}-{int(action_dim)}D{suffix}-v0"


def env_ids() -> dict[str, dict]:
    """Every id with its spec kwargs (task, family, action_dim, method: the train/run.py method whose env it
    is; the KGRL ids also kgrl_recipe None: the preset's, as run.py), in a fixed order."""
    out = {}
    for t in TASKS:
        for f in FAMILIES:
            for d in ACTION_DIMS:
                for kgrl, vision in VARIANTS.values():
                    kw = {"task": t, "family": f, "action_dim": d, "method": VARIANT_METHODS[(kgrl, vision)]}
                    if kgrl:
                        kw["kgrl_recipe"] = None
                    out[env_id(t, f, d, kgrl, vision)] = kw
    return out


def register_envs() -> list[str]:
    """Register every id with gymnasium (already registered ones are left as they are)."""
    import gymnasium as gym

    for name, kwargs in env_ids().items():
        if name not in gym.registry:
            gym.register(id=name, entry_point=ENTRY_POINT, vector_entry_point=VECTOR_ENTRY_POINT, kwargs=dict(kwargs))
    return list(env_ids())
