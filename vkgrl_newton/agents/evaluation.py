"""Policies as the env sees them, and the evaluation loop that reports the thesis metrics.

A policy here has `reset(env)` (called at the start of every evaluation episode) and
`step(env, obs) -> env step result`: it picks its action and drives the env through the matching
entry point (`env.step` for the SAC path, `env.step_pose` for KGRL and the scripted demonstrator).

- `ScriptedPolicy`: the privileged demonstrator (envs/scripted.py).
- `RandomPolicy`, `ZeroPolicy`: uniform in [-1, 1]^D / zeros, through the SAC path.
- `KMPPriorPolicy`: the KMP prior alone, zeta = 0 (KGRL with a silent policy).
- `AgentPolicy`: a trained SAC agent, deterministic (tanh of the mean), on its method's path.

`evaluate(env, policy, episodes)` runs whole episodes (all worlds together) and returns the
metrics of train/evaluate.py's JSON; `record_video` renders the task camera along the way.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import math
import time

import numpy as np
import torch
from tqdm import tqdm

__all__ = ["Policy", "ScriptedPolicy", "RandomPolicy", "ZeroPolicy", "KMPPriorPolicy", "AgentPolicy", "evaluate",
           "policy_observation"]


def policy_observation(obs, time_obs: bool = True) -> torch.Tensor:
    """The policy's input from the env's observation TensorDict; without normalized time (column 0)
    for the time ablation of thesis Appendix A.1 (the KMP still follows time)."""
    x = obs["policy"] if not isinstance(obs, torch.Tensor) else obs
    return x if time_obs else x[:, 1:]


class Policy(ABC):
    """Base of the evaluation policies: `reset` is called at every episode start (nothing to do
    unless the policy keeps per-episode state), `step` drives the env one control step."""

    def reset(self, env) -> None:
        return None

    @abstractmethod
    def step(self, env, obs):
        """One control step: returns what the env's step returns (obs, rewards, dones, extras)."""


class ScriptedPolicy(Policy):
    def __init__(self, seed: int = 0):
        from ..envs.scripted import ScriptedInserter

        self.inserter = ScriptedInserter(seed=seed)

    def reset(self, env) -> None:
        self.inserter.reset(env)

    def step(self, env, obs):
        return env.step_pose(*self.inserter.act(env))


class RandomPolicy(Policy):
    def __init__(self, seed: int = 0):
        self.seed = seed
        self.gen = None

    def reset(self, env) -> None:
        if self.gen is None:
            self.gen = torch.Generator(device=env.tdev).manual_seed(self.seed)

    def step(self, env, obs):
        a = torch.rand(env.num_envs, env.num_actions, device=env.tdev, generator=self.gen) * 2 - 1
        return env.step(a)


class ZeroPolicy(Policy):
    def step(self, env, obs):
        return env.step(torch.zeros(env.num_envs, env.num_actions, device=env.tdev))


class KMPPriorPolicy(Policy):
    """Follows the KMP prior: zeta = 0 at every step (the KGRL path with a zero action)."""

    def __init__(self, action_path):
        self.path = action_path

    def step(self, env, obs):
        return self.path.step(torch.zeros(env.num_envs, env.num_actions, device=env.tdev))


class AgentPolicy(Policy):
    """A SAC agent acting deterministically; `action_path` is the KGRLActionPath for kgrl methods."""

    def __init__(self, agent, action_path=None, time_obs: bool = True):
        self.agent, self.path, self.time_obs = agent, action_path, time_obs

    def step(self, env, obs):
        a = self.agent.act(policy_observation(obs, self.time_obs), deterministic=True)
        return self.path.step(a) if self.path is not None else env.step(a)


def evaluate(env, policy, episodes: int, progress: bool = True, video_frames: list | None = None,
             camera=None, video_worlds: int = 4, desc: str = "evaluate") -> dict:
    """Run `episodes` full episodes of all worlds and return the thesis metrics.

    The env is reset first unless it is at the start of an episode. With `video_frames` (a list)
    and `camera` (sim.camera.TaskCamera), each control step appends one frame: the task camera of
    the first `video_worlds` worlds, tiled left to right (uint8 (H, W * n, 3)).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    resets0, ik0, overflow0 = env.physics_resets_total, env.ik_failures_total, env.contact_overflows_total
    if bool((env.episode_length_buf != 0).any()):
        env.reset()
    obs = env.get_observations()
    per_episode = []
    steps = 0
    t0 = time.perf_counter()
    bar = tqdm(total=episodes * env.max_episode_length, desc=desc, disable=not progress, unit="step", leave=False)
    for _ in range(episodes):
        policy.reset(env)
        while True:
            if video_frames is not None:
                video_frames.append(_camera_frame(env, camera, video_worlds))
            obs, _, _, extras = policy.step(env, obs)
            steps += 1
            bar.update(1)
            if "episode" in extras:
                per_episode.append(extras["episode"])
                break
    bar.close()
    wall = time.perf_counter() - t0

    def mean(key):
        vals = [(e[key], e["num_episodes"]) for e in per_episode if not math.isnan(e[key])]
        return sum(v * w for v, w in vals) / sum(w for _, w in vals) if vals else float("nan")

    return {
        "success_rate": mean("success_rate"),
        "success_rate_any": mean("success_rate_any"),
        "mean_contact_force": mean("mean_contact_force"),
        "peak_contact_force": max((e["peak_contact_force"] for e in per_episode
                                   if not math.isnan(e["peak_contact_force"])), default=float("nan")),
        "mean_peak_contact_force": mean("mean_peak_contact_force"),
        "time_to_first_success_s": mean("time_to_first_success_s"),
        "mean_episode_reward": mean("episode_reward"),
        "episodes": sum(e["num_episodes"] for e in per_episode),
        "env_steps_per_s": steps * env.num_envs / wall,
        "wall_s": wall,
        "physics_resets": env.physics_resets_total - resets0,
        # worlds whose reset IK did not converge (they ran their episode from the last iterate)
        "ik_failures": env.ik_failures_total - ik0,
        # world-substeps whose contacts overflowed the solver's buffers (SimConfig.nconmax / njmax)
        "contact_overflows": env.contact_overflows_total - overflow0,
        "per_episode": per_episode,
    }


def _camera_frame(env, camera, n: int) -> np.ndarray:
    images = camera.render(env.state_0, *env.hand_pose())
    return np.concatenate(list(images[:n]), axis=1)


def write_video(path, frames: list, fps: float = 15.0) -> None:
    """Frames (uint8 (H, W, 3)) to an animated GIF, written atomically, never overwriting."""
    from PIL import Image

    from .._io import atomic_write

    if not frames:
        raise ValueError("no frames to write")
    images = [Image.fromarray(f) for f in frames]
    atomic_write(path, overwrite=False, suffix=".gif",
                 write=lambda f: images[0].save(f, format="GIF", save_all=True, append_images=images[1:],
                                                duration=int(round(1000.0 / fps)), loop=0))
