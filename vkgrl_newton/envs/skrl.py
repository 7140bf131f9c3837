"""skrl's agents on the gymnasium ids: the one thing skrl's own gymnasium wrapper does not carry.

    import gymnasium as gym
    from skrl.agents.torch.sac import SAC
    from skrl.envs.wrappers.torch import wrap_env
    import vkgrl_newton
    from vkgrl_newton.envs.skrl import with_final_obs

    env = wrap_env(gym.make_vec("VKGRL/PegInsert-Factory-4D-KGRL-v0", num_envs=16), wrapper="gymnasium")
    agent = with_final_obs(SAC)(models=..., memory=..., observation_space=env.observation_space,
                                action_space=env.action_space, device=env.device, cfg=...)

The env needs no adapter: skrl's `wrap_env(envs, wrapper="gymnasium")` takes the `AssemblyVectorEnv`
as it is (a gymnasium 1.x VectorEnv: single spaces, float32 numpy out, torch in; one reset, as its
worlds reset themselves). Run skrl's trainers with `headless=True` (skrl renders a vector env through
`VectorEnv.call`, which this one, one batched simulation, does not have).

What does not fit is the end of an episode. The ids reset an ended world inside the same step
(autoreset SAME_STEP): the observation returned is the new episode's first, the ended episode's last is
in `info["final_obs"]`. skrl's trainer records `next_observations` = what the step returned, so skrl
would bootstrap every time-out from the next episode's first state (SAC's target r + g Q(s'), PPO's
`time_limit_bootstrap` r + g V(s')). And as `terminated` is always False here (episodes end by time-out),
skrl 2.1's PPO without `time_limit_bootstrap` runs its GAE across episode ends (skrl issue #449).

`with_final_obs(AgentClass)` is the agent class with one change in `record_transition`:
- a world that timed out records `info["final_obs"]` as its next observation, so SAC, TD3, DDPG, ... and
  PPO with `time_limit_bootstrap=True` bootstrap from the state the episode ended in (what this
  project's own SAC and its stable-baselines3 adapter do, envs/sb3.py);
- a world reset after a physics blow-up (`info["final_info"]["physics_reset"]`; reward 0) is recorded
  as terminal with its new episode's first observation as the next one: its last observation may hold
  NaN and skrl's memories store every world's row of a step (this project's loops drop that row);
- an on-policy agent built without `time_limit_bootstrap=True` is refused (ValueError), for the GAE above.

Single agents only: skrl slices the observations of simultaneous agents by scope, not the infos.
"""

from __future__ import annotations

import torch

__all__ = ["FinalObs", "with_final_obs"]


class FinalObs:
    """Mixin before a skrl agent class (`class MySAC(FinalObs, SAC)`): module docstring."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if getattr(self.cfg, "time_limit_bootstrap", True) is not True:
            raise ValueError(f"{type(self).__name__}: cfg time_limit_bootstrap=True is needed: the VKGRL ids' episodes "
                             "end by time-out only (terminated is always False), and without it skrl's GAE runs "
                             "across episode ends")

    def record_transition(self, *, next_observations, terminated, truncated, infos, **kwargs) -> None:
        if isinstance(infos, dict) and "final_obs" in infos:
            dev = next_observations.device
            final = torch.as_tensor(infos["final_obs"], dtype=next_observations.dtype, device=dev)
            if final.shape != next_observations.shape:
                raise ValueError(f"info['final_obs'] has shape {tuple(final.shape)}, the observations "
                                 f"{tuple(next_observations.shape)}: with_final_obs takes one agent on all worlds")
            ended = torch.as_tensor(infos["_final_obs"], dtype=torch.bool, device=dev).view(-1, 1)
            blown = torch.as_tensor(infos["final_info"]["physics_reset"], dtype=torch.bool, device=dev).view(-1, 1)
            next_observations = torch.where(ended & ~blown, final, next_observations)
            terminated = terminated | blown
            truncated = truncated & ~blown
        super().record_transition(next_observations=next_observations, terminated=terminated, truncated=truncated,
                                  infos=infos, **kwargs)


def with_final_obs(agent_class: type) -> type:
    """`agent_class` (a skrl torch agent: SAC, PPO, TD3, ...) recording an ended episode's final observation."""
    return type(agent_class.__name__, (FinalObs, agent_class), {"__module__": __name__,
                                                                 "__doc__": FinalObs.__doc__})
