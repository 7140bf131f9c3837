"""rsl-rl's PPO: the agent the run's PPO loop drives.

The env is already an rsl-rl `VecEnv` (envs.assembly_env.AssemblyEnv); `envs.rsl_rl.KGRLVecEnv` is
the same env acting in the KMP prior's null space, for PPO in the prior's null space. The configuration (Isaac Lab Factory's PPO settings, and what differs) is plain data in
agents/ppo_config.py. `PPOAgent` holds rsl-rl's PPO algorithm as `OnPolicyRunner` builds it, with
the small interface run.py and the evaluation need: `act`, `state_dict` / `load_state_dict` and the
count of gradient steps; run.py runs the rollout / update loop itself (OnPolicyRunner.learn's loop)
so that PPO runs log, checkpoint, resume and evaluate like the SAC methods.
"""

from __future__ import annotations

import torch
from rsl_rl.algorithms import PPO
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from .ppo_config import FACTORY_PPO, METHOD_PPO_DEFAULTS, MINIBATCH, parse_ppo_overrides, ppo_train_cfg

__all__ = ["FACTORY_PPO", "MINIBATCH", "METHOD_PPO_DEFAULTS", "ppo_train_cfg", "parse_ppo_overrides", "PPOAgent",
           "start_at_prior"]


def start_at_prior(alg: PPO) -> None:
    """Start the actor's mean action at ~0 (for kgrl_ppo: the KMP prior), as KGRL's SAC actor starts:
    its last layer's weights scaled by 1e-3, its bias 0. For an OnPolicyRunner of your own, call it on
    `runner.alg` before learning (PPOAgent does when its cfg says `start_at_prior`)."""
    head = [m for m in alg.get_policy().mlp.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        head.weight.mul_(1e-3)
        head.bias.zero_()


class PPOAgent:
    """rsl-rl's PPO (actor, critic, rollout storage, optimizer) for `env`'s observations, built the way
    OnPolicyRunner builds it. `alg` is rsl-rl's object; the loop calls alg.act / process_env_step /
    compute_returns / update. `cfg` is a ppo_train_cfg dict (copied: rsl-rl resolves it in place)."""

    def __init__(self, env: VecEnv, cfg: dict, device: str = "cpu"):
        import contextlib
        import copy
        import io

        self.cfg = copy.deepcopy(cfg)
        rsl_cfg = {k: v for k, v in copy.deepcopy(cfg).items() if k != "start_at_prior"}  # (this project's key)
        with contextlib.redirect_stdout(io.StringIO()):  # construct_algorithm prints both networks
            self.alg = PPO.construct_algorithm(env.get_observations().to(device), env, rsl_cfg, device)
        if cfg.get("start_at_prior"):
            start_at_prior(self.alg)
        self.device = device
        self.num_steps_per_env = int(cfg["num_steps_per_env"])
        self.iterations = 0  # PPO updates run (each: num_learning_epochs x num_mini_batches gradient steps)

    @property
    def num_updates(self) -> int:
        """Gradient steps so far (as SAC counts them)."""
        a = self.cfg["algorithm"]
        return self.iterations * int(a["num_learning_epochs"]) * int(a["num_mini_batches"])

    @torch.no_grad()
    def act(self, x: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
        """Actions for policy observations `x` (N, obs_dim): the Gaussian's mean, or a sample."""
        obs = TensorDict({"policy": x.to(self.device)}, batch_size=[x.shape[0]])
        return self.alg.get_policy()(obs, stochastic_output=not deterministic)

    def state_dict(self) -> dict:
        return {**self.alg.save(), "iterations": self.iterations}

    def load_state_dict(self, state: dict) -> None:
        self.alg.load(state, None, strict=True)
        self.iterations = int(state["iterations"])
