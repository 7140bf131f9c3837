"""The gymnasium ids' entry point: an id's configuration -> a `RunConfig` -> the run library's builder
-> `envs.vector.AssemblyVectorEnv`.

    envs = gymnasium.make_vec("VKGRL/PegInsert-Factory-4D-KGRL-v0", num_envs=16)
    envs.run_config          # the RunConfig it was built from: train/run.py --method kgrl's env

An id is the env of one train/run.py method (its spec kwargs name it: `method`), built as run.py
builds it: the same preset default (thesis on CUDA, quick on a CPU; `preset=` to choose), and for the
KGRL ids the same KGRL recipe's null space (`kgrl_recipe=None`: the preset's default, on quick residual
for PegInsert Factory 4D (a = 0 is a fixed controller, the Vision id's reads the near-hole probe) and
reach_keep_prior with its 3 / 25 mm reach floors elsewhere, base on thesis: the thesis's null space; the
recipe's SAC fields are the learner's and do not apply to an env). `gym_config(...)` is that RunConfig without
building anything (tests hold it equal to run.py's).
"""

from __future__ import annotations

import sys
from pathlib import Path

from .._io import output_path_error
from ..envs.vector import RENDER_MODES, AssemblySingleEnv, AssemblyVectorEnv, check_vector_kwargs
from .config import ConfigError, RunConfig
from .methods import METHODS
from .presets import DEFAULT_KGRL_RECIPE, KGRL_RECIPES, NO_RECIPE, default_kgrl_recipe, recipe_options

__all__ = ["make_vec_env", "make_env", "gym_config", "KWARGS"]


def _quiet(message: str) -> None:
    """The cache's progress lines (recording demonstrations, fitting the prior) go to stderr."""
    print(f"vkgrl_newton: {message}", file=sys.stderr)


def gym_config(task: str = "PegInsert", family: str = "factory", action_dim: int = 4, method: str = "sac",
               num_envs: int = 16, device: str | None = None, seed: int = 0, cache_dir: str | Path = "runs/cache",
               tensors: str = "numpy", geometry: str = "primitives", vae: str | Path | None = None,
               demos: str | Path | None = None, preset: str | None = None, kgrl_recipe: str | None = None) -> RunConfig:
    """The RunConfig of an id's kwargs; ValueError naming the kwarg and the allowed values, before anything is built."""
    check_vector_kwargs(task, family, action_dim, num_envs, tensors, geometry)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
        raise ValueError(f"seed={seed!r} is not allowed; allowed: an integer in [0, 2**32)")
    for name, value in (("cache_dir", cache_dir), ("demos", demos), ("vae", vae)):
        if value is not None and not isinstance(value, (str, Path)):
            raise ValueError(f"{name}={value!r} is not allowed; allowed: a path (str or pathlib.Path)")
    if method in METHODS and (METHODS[method].uses_kmp or METHODS[method].vision) \
            and (why := output_path_error(cache_dir, "cache_dir", may_exist=True)):  # (the prerequisites go there)
        raise ValueError(why)
    if method not in METHODS or METHODS[method].uses_ppo:
        raise ValueError(f"method={method!r} is not allowed; allowed: "
                         f"{[m for m, row in METHODS.items() if not row.uses_ppo]} (an id is an env, not a learner)")
    row = METHODS[method]
    if demos is not None and not row.uses_kmp:
        raise ValueError("demos is for the KGRL ids (their prior's demonstrations)")
    if vae is not None and not row.vision:
        raise ValueError("vae is for the Vision ids (their frozen encoder)")
    if kgrl_recipe is not None and (not row.takes_recipe or kgrl_recipe not in KGRL_RECIPES):
        raise ValueError(f"kgrl_recipe={kgrl_recipe!r} is not allowed; allowed: None (the preset's) or one of "
                         f"{sorted(KGRL_RECIPES)}, for the KGRL ids")
    if preset is not None and preset not in DEFAULT_KGRL_RECIPE:
        raise ValueError(f"preset={preset!r} is not allowed; allowed: None (thesis on CUDA, quick on a CPU) or one of "
                         f"{sorted(DEFAULT_KGRL_RECIPE)}")
    from ..runtime import configure_warp, default_device, device_error

    configure_warp()
    device = device or default_device()
    if (why := device_error(device, "device")) is not None:
        raise ValueError(why)
    preset = preset or ("thesis" if str(device).startswith("cuda") else "quick")
    recipe_name = (kgrl_recipe or default_kgrl_recipe(preset, task, family, action_dim)) if row.takes_recipe else None
    recipe = KGRL_RECIPES[recipe_name] if recipe_name else NO_RECIPE
    options = recipe_options(recipe, method)  # the recipe's run options: a = 0's base controller, the probe's input
    if options.get("vision_probe_obs") and vae is not None:
        raise ValueError(f"vae with the KGRL recipe {recipe_name}: its env reads the near-hole probe fitted on the cached "
                         "VAE's own image set, which a given vae does not come with; leave out vae, or give "
                         "kgrl_recipe='reach_keep_prior'")
    cfg = RunConfig(task=task, method=method, env=family, action_dim=int(action_dim), seed=seed,
                    num_envs=int(num_envs), preset=preset, geometry=geometry, kgrl_recipe=recipe_name,
                    demos=Path(demos) if demos is not None else None, vae=Path(vae) if vae is not None else None,
                    reach_floor_mm=float(recipe["reach_floor_mm"]), reach_floor_z_mm=float(recipe["reach_floor_z_mm"]),
                    seat_press_mm=float(recipe.get("seat_press_mm", 0.0)), **options,
                    device=device, cache_dir=Path(cache_dir), progress=False)
    _check_files(cfg)
    return cfg


def _check_files(cfg: RunConfig) -> None:
    """A given demos or vae file that is missing, damaged or of another task: one line, before any build."""
    from .resolve import check_demos_file, check_vae_file

    try:
        if cfg.demos is not None:
            check_demos_file(cfg.demos, cfg.task)
        if cfg.vae is not None:
            check_vae_file(cfg.vae, cfg.task)
    except ConfigError as e:
        raise ValueError(str(e).replace("--demos ", "demos=").replace("--demos:", "demos:").replace("--vae:", "vae:")
                         .replace("--task ", "task=")) from None


KWARGS = ("num_envs", "device", "seed", "cache_dir", "tensors", "geometry", "vae", "demos", "preset", "kgrl_recipe",
          "render_mode")  # what make_vec and make take beyond an id's own spec kwargs


def _check_kwargs(given: dict) -> None:
    if unknown := sorted(set(given) - set(KWARGS)):
        raise ValueError(f"{unknown[0]}={given[unknown[0]]!r} is not a kwarg of the VKGRL ids; allowed: {list(KWARGS)}")


def make_vec_env(task: str = "PegInsert", family: str = "factory", action_dim: int = 4, method: str = "sac",
                 num_envs: int = 16, tensors: str = "numpy", env=None, render_mode: str | None = None,
                 **kwargs) -> AssemblyVectorEnv:
    """gymnasium.make_vec's entry point for the VKGRL ids (kwargs: gym_config's, and render_mode None or
    "rgb_array"). env: an AssemblyEnv already built for this configuration (tests share one); else it is
    built here."""
    _check_kwargs({**kwargs, "num_envs": num_envs, "tensors": tensors, "render_mode": render_mode})
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode={render_mode!r} is not allowed; allowed: None or one of {list(RENDER_MODES)}")
    cfg = gym_config(task, family, action_dim, method, num_envs=num_envs, tensors=tensors, **kwargs)
    from ..signals import stop_exits
    from .build import build_action_path, build_encoder, build_env

    # a stop while the cache's prerequisites are made (minutes on an empty cache) ends the program as a
    # stopped run.py does: the entries whole or absent, one line, exit 130 / 143 / 129 (docs/cli.md, Signals)
    with stop_exits("vkgrl_newton", "the env was not made; the cache keeps what was finished, make it again to "
                    "continue"):
        if env is None:  # in run.py's order: the encoder (its preparation may take minutes), then the env
            env = build_env(cfg, build_encoder(cfg, log=_quiet))
        else:
            got = (env.cfg.task, env.cfg.family, env.cfg.action_dim, env.cfg.vision_latent_dim)
            if got != (task, family, action_dim, cfg.latent_dim):
                raise ValueError(f"env is a {got[0]} {got[1]} {got[2]}D env with a {got[3]}-dimensional vision "
                                 f"slot, not {task} {family} {action_dim}D with {cfg.latent_dim}")
        action_path, _ = build_action_path(cfg, env, log=_quiet)
    return AssemblyVectorEnv(env, action_path, tensors=tensors, run_config=cfg, render_mode=render_mode)


def make_env(task: str = "PegInsert", family: str = "factory", action_dim: int = 4, method: str = "sac",
             render_mode: str | None = None, **kwargs) -> AssemblySingleEnv:
    """gymnasium.make's entry point: one world (envs.vector.AssemblySingleEnv; kwargs as make_vec_env's
    but num_envs, which is 1, and tensors, which is numpy)."""
    for name in ("num_envs", "tensors"):
        if name in kwargs:
            raise ValueError(f"{name} is not a kwarg of gymnasium.make's one-world env; use gymnasium.make_vec(id, "
                             f"num_envs=N) for N worlds in one batched simulation")
    return AssemblySingleEnv(make_vec_env(task, family, action_dim, method, num_envs=1, tensors="numpy",
                                          render_mode=render_mode, **kwargs))
