"""rsl-rl's PPO on the assembly env: the runner configuration and the KGRL env it acts through.

The env is already an rsl-rl `VecEnv` (envs.assembly_env.AssemblyEnv); `KGRLVecEnv` is the same
env acting in the KMP prior's null space (agents.kgrl.KGRLActionPath), for PPO in the prior's null
space. `ppo_train_cfg` gives rsl-rl's `OnPolicyRunner` Isaac Lab Factory's PPO settings
(shared/reference/isaaclab_factory_facts.md section 10, rl_games' `rl_games_ppo_cfg.yaml`):
gamma 0.995, lambda 0.95, learning rate 1e-4 with the adaptive KL schedule (desired KL 0.008),
clip 0.2, entropy 0, value coefficient 2, gradient norm 1.0, 4 mini-epochs, 128 steps per env per
iteration (256 for Forge NutThread), minibatches of 512 transitions, the actor MLP [512, 128, 64]
ELU with a state-independent Gaussian (std 1, log-std 0), input normalization.
What differs, and why:
- no LSTM (Factory's actor has 2 x 1024 LSTM units before the MLP): rsl-rl's MLPModel; the
  third-party LSTM-free rerun of Factory's config reached 97.7-98.3 % (same reference);
- no asymmetric critic: the critic sees the actor's observation (the env has no privileged
  critic state yet);
- no value normalization, bounds loss or mixed precision (rsl-rl has none of the first two; the
  third is off on a CPU).
"""

from __future__ import annotations

import copy

from rsl_rl.env import VecEnv

__all__ = ["FACTORY_PPO", "ppo_train_cfg", "KGRLVecEnv"]

# Factory's rl_games values (see the module docstring), in rsl-rl's names
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
}
MINIBATCH = 512  # transitions per minibatch (rl_games minibatch_size)


def ppo_train_cfg(task: str, family: str, num_envs: int, **overrides) -> dict:
    """The OnPolicyRunner configuration for `num_envs` worlds: FACTORY_PPO with Forge NutThread's longer
    horizon and as many minibatches as make ~512 transitions each (at least 1). `overrides` replace
    top-level keys or, as "algorithm.NAME", single algorithm settings."""
    cfg = copy.deepcopy(FACTORY_PPO)
    if family == "forge" and task == "NutThread":
        cfg["num_steps_per_env"] = 256
    for key, value in overrides.items():
        if key.startswith("algorithm."):
            name = key.split(".", 1)[1]
            if name not in cfg["algorithm"]:
                raise ValueError(f"PPO setting {name!r} unknown; allowed: {sorted(cfg['algorithm'])}")
            cfg["algorithm"][name] = value
        elif key in cfg:
            cfg[key] = value
        else:
            raise ValueError(f"PPO setting {key!r} unknown; allowed: {sorted(cfg)} or algorithm.<name>")
    cfg["algorithm"]["num_mini_batches"] = max(1, num_envs * cfg["num_steps_per_env"] // MINIBATCH)
    return cfg


class KGRLVecEnv(VecEnv):
    """An AssemblyEnv whose `step(actions)` goes through the KMP prior's null space: a in [-1, 1]^D,
    a = 0 follows the prior (agents.kgrl.KGRLActionPath). Everything else is the env's own."""

    def __init__(self, env, action_path):
        if action_path.env is not env:
            raise ValueError("the action path drives another env")
        self.env = env
        self.action_path = action_path
        self.num_envs, self.num_actions = env.num_envs, env.num_actions
        self.max_episode_length, self.device, self.cfg = env.max_episode_length, env.device, env.cfg

    @property
    def episode_length_buf(self):
        return self.env.episode_length_buf

    @episode_length_buf.setter
    def episode_length_buf(self, value):  # rsl-rl's init_at_random_ep_len sets it
        self.env.episode_length_buf = value

    def get_observations(self):
        return self.env.get_observations()

    def reset(self):
        return self.env.reset()

    def step(self, actions):
        return self.action_path.step(actions)
