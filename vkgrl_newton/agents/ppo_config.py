"""rsl-rl's PPO configuration as plain data: Isaac Lab Factory's settings in rsl-rl's names.

A module of its own, importing no torch, so that train/run.py can parse and check every
`--ppo KEY=VALUE` before anything heavy is imported (agents/ppo.py uses it).

`FACTORY_PPO` is Isaac Lab Factory's rl_games PPO (shared/reference/isaaclab_factory_facts.md
section 10, `rl_games_ppo_cfg.yaml`): gamma 0.995, lambda 0.95, learning rate 1e-4 with the adaptive
KL schedule (desired KL 0.008), clip 0.2, entropy 0, value coefficient 2, gradient norm 1.0, 4
mini-epochs, 128 steps per env per iteration (256 for Forge NutThread), minibatches of 512
transitions, the actor MLP [512, 128, 64] ELU with a state-independent Gaussian (std 1), input
normalization. What differs, and why:
- no LSTM (Factory's actor has 2 x 1024 LSTM units before the MLP): rsl-rl's MLPModel; the
  third-party LSTM-free rerun of Factory's config reached 97.7-98.3 % (same reference);
- no asymmetric critic: the critic sees the actor's observation (the env has no privileged
  critic state yet);
- no value normalization, bounds loss or mixed precision (rsl-rl has none of the first two; the
  third is off on a CPU);
- `kgrl_ppo` (PPO in the KMP prior's null space) starts at the prior: its actor's mean at ~0
  (`start_at_prior`, the last layer's weights scaled by 1e-3 and its bias 0, as KGRL's SAC
  actor) and its Gaussian at std 0.1, not 1 (`METHOD_PPO_DEFAULTS`). For the same reason as
  KGRL's SAC (run.py's KGRL_EXPLORATION): a std-1 action clamped to [-1, 1] throws the part
  millimetres off the prior against a 0.06 mm clearance. Method defaults, not Factory's;
  `--ppo actor.distribution_cfg.init_std=1 --ppo start_at_prior=false` restores Factory's start.
"""

from __future__ import annotations

import copy
import json

__all__ = ["FACTORY_PPO", "MINIBATCH", "METHOD_PPO_DEFAULTS", "ppo_train_cfg", "parse_ppo_overrides"]

FACTORY_PPO = {
    "num_steps_per_env": 128,  # rl_games horizon_length; 256 for Forge NutThread
    "save_interval": 50,
    "obs_groups": {"actor": ["policy"], "critic": ["policy"]},
    "algorithm": {
        "class_name": "PPO", "num_learning_epochs": 4, "clip_param": 0.2, "gamma": 0.995, "lam": 0.95,
        "value_loss_coef": 2.0, "entropy_coef": 0.0, "learning_rate": 1e-4, "max_grad_norm": 1.0,
        "schedule": "adaptive", "desired_kl": 0.008, "use_clipped_value_loss": True,
    },
    "actor": {"class_name": "MLPModel", "hidden_dims": [512, 128, 64], "activation": "elu", "obs_normalization": True,
              "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": 1.0, "std_type": "scalar"}},
    "critic": {"class_name": "MLPModel", "hidden_dims": [512, 128, 64], "activation": "elu", "obs_normalization": True},
    "multi_gpu": None,
    "logger": "tensorboard",
    "check_for_nan": True,
    "start_at_prior": False,  # this project's: the actor's mean starts at ~0 (agents/ppo.py PPOAgent)
}
MINIBATCH = 512  # transitions per minibatch (rl_games minibatch_size)
# what a method sets on top of FACTORY_PPO (an override still wins); see the module docstring
METHOD_PPO_DEFAULTS: dict[str, dict] = {"kgrl_ppo": {"actor.distribution_cfg.init_std": 0.1, "start_at_prior": True}}


def ppo_train_cfg(task: str, family: str, num_envs: int, **overrides) -> dict:
    """The OnPolicyRunner configuration for `num_envs` worlds: FACTORY_PPO with Forge NutThread's longer
    horizon and as many minibatches as make ~512 transitions each (at least 1). `overrides` replace a
    setting by its dotted path ("num_steps_per_env", "algorithm.learning_rate",
    "actor.distribution_cfg.init_std"); an unknown path is a ValueError naming the allowed ones."""
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    cfg = copy.deepcopy(FACTORY_PPO)
    if family == "forge" and task == "NutThread":
        cfg["num_steps_per_env"] = 256
    for key, value in overrides.items():
        *parents, name = key.split(".")
        node = cfg
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or name not in node or isinstance(node[name], dict):
            raise ValueError(f"PPO setting {key!r} unknown; allowed: {', '.join(_leaf_paths(cfg))}")
        if not _same_kind(node[name], value):
            raise ValueError(f"PPO setting {key!r}: {value!r} is not a {type(node[name]).__name__} "
                             f"(default {node[name]!r})")
        node[name] = value
    if not (isinstance(cfg["num_steps_per_env"], int) and cfg["num_steps_per_env"] >= 1):
        raise ValueError(f"PPO setting 'num_steps_per_env' must be an integer >= 1, got {cfg['num_steps_per_env']!r}")
    cfg["algorithm"]["num_mini_batches"] = max(1, num_envs * cfg["num_steps_per_env"] // MINIBATCH)
    return cfg


def _same_kind(default, value) -> bool:
    """A value may replace a default of its kind: bool for bool, an int for an int, any number for a
    float, a list for a list, a string for a string; a setting that defaults to None takes anything."""
    if default is None:
        return True
    if isinstance(default, bool) or isinstance(value, bool):
        return isinstance(default, bool) and isinstance(value, bool)
    if isinstance(default, float):
        return isinstance(value, (int, float))
    return isinstance(value, type(default))


def _leaf_paths(node: dict, prefix: str = "") -> list[str]:
    out = []
    for k, v in node.items():
        out += _leaf_paths(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}"]
    return out


def parse_ppo_overrides(items: list[str]) -> dict:
    """KEY=VALUE strings -> {dotted path: value}; a value is read as JSON (numbers, true/false, lists)
    and otherwise kept as a string. The paths are checked by ppo_train_cfg."""
    out: dict = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--ppo {item!r}: expected KEY=VALUE, KEY a setting's dotted path "
                             "(e.g. algorithm.learning_rate=3e-4)")
        try:
            out[key] = json.loads(text)
        except json.JSONDecodeError:
            out[key] = text
    return out
