"""An AssemblyEnv as rsl-rl's `VecEnv` on the KGRL action path, for rsl-rl's runners and PPO.

The env is already an rsl-rl `VecEnv` (envs.assembly_env.AssemblyEnv) on Factory's delta-pose path;
`KGRLVecEnv` is the same env stepping through the KMP prior's null space (envs.kgrl_action)."""

from __future__ import annotations

from rsl_rl.env import VecEnv

__all__ = ["KGRLVecEnv"]


class KGRLVecEnv(VecEnv):
    """An AssemblyEnv whose `step(actions)` goes through the KMP prior's null space: a in [-1, 1]^D,
    a = 0 follows the prior (envs.kgrl_action.KGRLActionPath). Everything else is the env's own."""

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
