"""stable-baselines3's VecEnv over `envs.vector.AssemblyVectorEnv` (SB3: the optional extra).

    import gymnasium as gym
    from stable_baselines3 import SAC
    import vkgrl_newton
    from vkgrl_newton.envs.sb3 import SB3VecEnv

    env = SB3VecEnv(gym.make_vec("VKGRL/PegInsert-Factory-4D-KGRL-v0", num_envs=16))
    SAC("MlpPolicy", env, learning_starts=1024).learn(30_000)

SB3's contract: `dones` = terminated or truncated; an ended world's last observation is
`infos[i]["terminal_observation"]` and `infos[i]["TimeLimit.truncated"]` is True when the episode
was cut (here always: assembly episodes end at their time limit, see vector.py), so SB3's
off-policy learners bootstrap them; `infos[i]["is_success"]` says whether the part was seated at
some step of the episode (SB3's success-rate logging reads it). `seed(s)` before `reset()` seeds
all worlds (one generator; SB3 passes one seed per world, the first is used).
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

__all__ = ["SB3VecEnv"]


class SB3VecEnv(VecEnv):
    """A numpy `AssemblyVectorEnv` as stable-baselines3's VecEnv (module docstring)."""

    def __init__(self, venv):
        if getattr(venv, "tensors", "numpy") != "numpy":
            raise ValueError("SB3VecEnv needs the vector env's numpy output (make_vec(..., tensors='numpy'))")
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self._actions = None

    def reset(self):
        seed = self._seeds[0] if getattr(self, "_seeds", None) else None
        obs, _ = self.venv.reset(seed=seed)
        self._reset_seeds()
        return obs

    def step_async(self, actions) -> None:
        self._actions = np.asarray(actions, dtype=np.float32)

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.venv.step(self._actions)
        dones = terminated | truncated
        infos: list[dict] = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(dones):
            infos[i] = {"terminal_observation": info["final_obs"][i],
                        "TimeLimit.truncated": bool(truncated[i] and not terminated[i]),
                        "is_success": bool(info["final_info"]["success"][i])}
        return obs, reward.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name, indices=None):
        return [getattr(self.venv, attr_name)] * len(self._get_indices(indices))

    def set_attr(self, attr_name, value, indices=None) -> None:
        setattr(self.venv, attr_name, value)  # one simulation: the value holds for every world

    def env_method(self, method_name, *method_args, indices=None, **method_kwargs):
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result] * len(self._get_indices(indices))

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(self._get_indices(indices))

    def _get_indices(self, indices):
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else list(indices)
