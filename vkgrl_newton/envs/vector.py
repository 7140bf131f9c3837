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

from ..tasks import ACTION_DIMS, CONTROL_DT, FAMILIES, TASKS, geometry_error

__all__ = ["AssemblyVectorEnv", "AssemblySingleEnv", "TENSORS", "RENDER_MODES", "check_vector_kwargs"]

TENSORS = ("numpy", "torch")
RENDER_MODES = ("rgb_array",)


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
    (kept for the user to read: `envs.run_config`); render_mode: None or "rgb_array" (`render()` returns
    one task-camera frame per world, uint8 (H, W, 3), Table 5.6's camera: what gymnasium's vector
    RecordVideo tiles into a video).
    """

    # render_fps: the control rate (one frame per control step, 1/15 s)
    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": list(RENDER_MODES),
                "render_fps": int(round(1.0 / CONTROL_DT))}

    def __init__(self, env, action_path=None, tensors: str = "numpy", run_config=None, render_mode: str | None = None):
        if tensors not in TENSORS:
            raise ValueError(f"tensors={tensors!r} is not allowed; allowed: {list(TENSORS)}")
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode={render_mode!r} is not allowed; allowed: None or one of {list(RENDER_MODES)}")
        if action_path is not None and action_path.env is not env:
            raise ValueError("the action path drives another env")
        self.render_mode = render_mode
        self._camera = None  # made on the first render()
        self.env = env
        self.action_path = action_path
        self.run_config = run_config
        self._step = self.action_path.step if self.action_path is not None else env.step
        self.tensors = tensors
        self.num_envs = env.num_envs
        obs_dim = env.obs_dim
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
        self._check_open("reset")
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
        self._check_open("step")
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

    def render(self):
        """One frame per world of the task camera (uint8 (H, W, 3) numpy arrays), or None without
        render_mode="rgb_array"."""
        self._check_open("render")
        if self.render_mode != "rgb_array":
            return None
        if self._camera is None:
            from ..sim.camera import TASK_CAMERAS, TaskCamera

            self._camera = TaskCamera(self.env.model, TASK_CAMERAS[self.env.cfg.task], self.num_envs)
        images = self._camera.render(self.env.state_0, *self.env.hand_pose())
        return tuple(np.ascontiguousarray(images[i]) for i in range(self.num_envs))

    def close_extras(self, **kwargs) -> None:
        self.env = None
        self._camera = None

    def _check_open(self, what: str) -> None:
        if self.closed:
            raise gym.error.ClosedEnvironmentError(f"{what}() on a closed {type(self).__name__}: make a new one")

    def _out(self, t):
        return t if self.tensors == "torch" else t.detach().cpu().numpy()


class AssemblySingleEnv(gym.Env):
    """One world as a gymnasium `Env`: what `gymnasium.make(id)` gives, for the single-env checkers
    (gymnasium's and stable-baselines3's `check_env`), wrappers and learners.

    It is an `AssemblyVectorEnv` of one world underneath (the simulation is batched; for training,
    `gymnasium.make_vec(id, num_envs=N)` simulates N worlds in one step at about the cost of one on a
    GPU). At the time limit it returns the episode's last observation with truncated=True (the world
    has already been reset inside; the next `reset()` starts a fresh episode), and in `info` whether
    the part was seated ("success") and whether the world blew up ("physics_reset").
    """

    metadata = AssemblyVectorEnv.metadata

    def __init__(self, vector_env: AssemblyVectorEnv):
        if vector_env.num_envs != 1 or vector_env.tensors != "numpy":
            raise ValueError("AssemblySingleEnv wraps a one-world AssemblyVectorEnv with tensors='numpy'")
        self.vector_env = vector_env
        self.observation_space = vector_env.single_observation_space
        self.action_space = vector_env.single_action_space
        self.render_mode = vector_env.render_mode
        self.run_config = vector_env.run_config

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)  # seeds self.np_random, as gymnasium's contract asks
        obs, info = self.vector_env.reset(seed=seed, options=options)
        return obs[0], info

    def step(self, action):
        a = np.asarray(action, dtype=np.float32)
        if a.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {a.shape}")
        obs, reward, terminated, truncated, info = self.vector_env.step(a[None])
        out: dict = {}
        if truncated[0]:  # the ended episode's last observation (the world is already reset inside)
            obs = info["final_obs"]
            out = {"success": bool(info["final_info"]["success"][0]),
                   "physics_reset": bool(info["final_info"]["physics_reset"][0])}
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), out

    def render(self):
        frames = self.vector_env.render()
        return None if frames is None else frames[0]

    def close(self) -> None:
        self.vector_env.close()
