"""The assembly env as a gymnasium `VectorEnv`, for learners other than this project's own.

    import gymnasium as gym
    import vkgrl_newton  # registers the VKGRL/... ids (vkgrl_newton/registration.py; built by run/gym.py)

    envs = gym.make_vec("VKGRL/PegInsert-Factory-4D-KGRL-v0", num_envs=16)
    obs, info = envs.reset(seed=0)
    obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())

One `AssemblyEnv` simulates all `num_envs` worlds at once (batched Warp physics); this class only
converts at its edge. Its contract, gymnasium 1.x's:
- observations (num_envs, obs_dim) float32: the thesis's proprioceptive vector (normalized time,
  TCP position relative to the observed target frame, TCP quaternion; Forge adds the smoothed
  contact force; the vision variants the frozen VAE's latent). Actions (num_envs, D) in [-1, 1]:
  D = 4 (xyz + yaw) or 6. A KGRL id acts in the KMP prior's null space (`envs.kgrl_action.
  KGRLActionPath`; a = 0 follows the prior), the others by Factory's delta-pose mapping.
- autoreset: `AutoresetMode.SAME_STEP`. A world whose episode ended is reset inside the same
  `step`; the returned observation is the new episode's first, the ended episode's last is in
  `info["final_obs"]` (rows where `info["_final_obs"]` is True), its outcome in
  `info["final_info"]` ("success": the part was seated at some step of the episode;
  "physics_reset": the world blew up and was reset, see below).
- terminated is always False: an assembly episode has no terminal state (a seated part may still be
  pulled out; Factory and the thesis run every episode to its time limit). truncated is True at the
  time limit and for a world reset after a physics blow-up (its transition is not the policy's
  doing; off-policy learners should drop it, `info["final_info"]["physics_reset"]`).
- `tensors="torch"` returns torch tensors on the env's device (no copies through numpy) and takes
  torch or numpy actions; "numpy" (default) returns numpy arrays.
- reset(seed=s) reseeds the env's generator (`results.paired.seed_evaluation`): the same s gives
  the same initial states, target noise and in-hand offsets, world by world.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from ..tasks import ACTION_DIMS, FAMILIES, TASKS, geometry_error, observation_dim

__all__ = ["AssemblyVectorEnv", "TENSORS", "check_vector_kwargs"]

TENSORS = ("numpy", "torch")


def check_vector_kwargs(task: str, family: str, action_dim: int, num_envs: int, tensors: str, geometry: str) -> None:
    """ValueError naming the field, its value and the allowed ones, before anything is built."""
    for name, value, allowed in (("task", task, sorted(TASKS)), ("family", family, list(FAMILIES)),
                                 ("action_dim", action_dim, list(ACTION_DIMS)), ("tensors", tensors, list(TENSORS))):
        if value not in allowed:
            raise ValueError(f"{name}={value!r} is not allowed; allowed: {allowed}")
    if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
        raise ValueError(f"num_envs={num_envs!r} is not allowed; allowed: an integer >= 1")
    if (why := geometry_error(task, geometry)) is not None:
        raise ValueError(why)


class AssemblyVectorEnv(VectorEnv):
    """gymnasium VectorEnv over one batched `AssemblyEnv` (module docstring).

    env: the AssemblyEnv (built by `vkgrl_newton.run.gym.make_vec_env`, the ids' entry point, through the
    run library's builder, so that an id's env is the env train/run.py trains on); action_path: the KGRL
    action path (envs.kgrl_action.KGRLActionPath) the actions go through, or None for Factory's
    delta-pose mapping; tensors: "numpy" | "torch"; run_config: the run configuration it was built from
    (kept for the user to read: `envs.run_config`).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, env, action_path=None, tensors: str = "numpy", run_config=None):
        if tensors not in TENSORS:
            raise ValueError(f"tensors={tensors!r} is not allowed; allowed: {list(TENSORS)}")
        if action_path is not None and action_path.env is not env:
            raise ValueError("the action path drives another env")
        self.env = env
        self.action_path = action_path
        self.run_config = run_config
        self._step = self.action_path.step if self.action_path is not None else env.step
        self.tensors = tensors
        self.num_envs = env.num_envs
        obs_dim = observation_dim(env.cfg.family, env.cfg.vision_latent_dim)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (env.cfg.action_dim,), np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)

    def rsl_rl_env(self):
        """The same worlds as an rsl-rl `VecEnv` for rsl-rl's runners: the env itself, or for a KGRL id
        the env acting through its prior's null space (envs.rsl_rl.KGRLVecEnv). Both share this env's
        state: step one or the other, not both."""
        if self.action_path is None:
            return self.env
        from .rsl_rl import KGRLVecEnv

        return KGRLVecEnv(self.env, self.action_path)

    # -- the gymnasium contract ---------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**63:
                raise ValueError(f"seed={seed!r}: one integer in [0, 2**63) seeds all {self.num_envs} worlds "
                                 "(a list of seeds is not supported: the worlds share one generator)")
            self.env.generator.manual_seed(int(seed))
        if options:
            raise ValueError(f"options={options!r}: reset takes no options")
        obs = self.env.reset()["policy"]
        return self._out(obs), {}

    def step(self, actions):
        a = torch.as_tensor(actions, dtype=torch.float32, device=self.env.tdev)
        if a.shape != (self.num_envs, self.single_action_space.shape[0]):
            raise ValueError(f"actions must have shape {(self.num_envs, self.single_action_space.shape[0])}, "
                             f"got {tuple(a.shape)}")
        obs, reward, dones, extras = self._step(a)
        truncated = dones.bool()
        terminated = torch.zeros_like(truncated)
        info: dict = {}
        if "final_observations" in extras:  # some world ended: its last observation, before the reset
            final = torch.zeros_like(obs["policy"])
            final[truncated] = extras["final_observations"]["policy"][truncated]
            blown = extras["physics_resets"].bool()
            seated = getattr(self.env, "last_episode_success_any", None)  # set at the first time-out
            seated = torch.zeros_like(truncated) if seated is None else seated & extras["time_outs"]
            info = {"final_obs": self._out(final), "_final_obs": self._out(truncated),
                    "final_info": {"success": self._out(seated),
                                   "physics_reset": self._out(blown)},
                    "_final_info": self._out(truncated)}
        return (self._out(obs["policy"]), self._out(reward.float()), self._out(terminated), self._out(truncated),
                info)

    def close_extras(self, **kwargs) -> None:
        self.env = None

    def _out(self, t):
        return t if self.tensors == "torch" else t.detach().cpu().numpy()
