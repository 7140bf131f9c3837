"""Run a policy in the assembly env and write the thesis metrics as JSON.

    python train/evaluate.py --task PegInsert --env factory --action-dim 4 --policy scripted \
        --num-envs 16 --episodes 2 --json runs/eval/peg_factory_4d_scripted.json

Policies: `scripted` (privileged demonstrator, absolute TCP poses through `step_pose`), `random`
(uniform in [-1, 1]^D) and `zero` (both through the SAC action path `step`). Metrics per episode
(all worlds end together): success at the episode's last step (`success_rate`), success at any
step (`success_rate_any`), mean contact force (thesis eq. 6.1, N), peak contact force, time to
first success (s, over the episodes that reached it), episode reward; plus env steps per second
and the number of physics resets. An existing JSON file is never overwritten.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vkgrl_newton._io import atomic_write_text  # noqa: E402
from vkgrl_newton.envs.assembly_env import ACTION_DIMS, FAMILIES, AssemblyEnv, EnvConfig  # noqa: E402
from vkgrl_newton.envs.scripted import ScriptedInserter  # noqa: E402
from vkgrl_newton.sim.scene import SOLVERS, SimConfig  # noqa: E402
from vkgrl_newton.tasks import TASKS  # noqa: E402

POLICIES = ("scripted", "random", "zero")


def run(env: AssemblyEnv, policy: str, episodes: int, seed: int = 0, progress: bool = True) -> dict:
    gen = torch.Generator(device=env.tdev).manual_seed(seed)
    scripted = ScriptedInserter(seed=seed) if policy == "scripted" else None
    per_episode = []
    steps = 0
    t0 = time.perf_counter()
    bar = tqdm(total=episodes * env.max_episode_length, desc=f"{policy} {env.cfg.family} {env.cfg.action_dim}D",
               disable=not progress, unit="step")
    for _ in range(episodes):
        if scripted is not None:
            scripted.reset(env)
        while True:
            if scripted is not None:
                _, _, _, extras = env.step_pose(*scripted.act(env))
            else:
                a = (torch.rand(env.num_envs, env.num_actions, device=env.tdev, generator=gen) * 2 - 1
                     if policy == "random" else torch.zeros(env.num_envs, env.num_actions, device=env.tdev))
                _, _, _, extras = env.step(a)
            steps += 1
            bar.update(1)
            if "episode" in extras:
                per_episode.append(extras["episode"])
                break
    bar.close()
    wall = time.perf_counter() - t0
    n = sum(e["num_episodes"] for e in per_episode)

    def mean(key):
        vals = [(e[key], e["num_episodes"]) for e in per_episode if not math.isnan(e[key])]
        return sum(v * w for v, w in vals) / sum(w for _, w in vals) if vals else float("nan")

    return {
        "success_rate": mean("success_rate"),
        "success_rate_any": mean("success_rate_any"),
        "mean_contact_force": mean("mean_contact_force"),
        "peak_contact_force": max(e["peak_contact_force"] for e in per_episode),
        "mean_peak_contact_force": mean("mean_peak_contact_force"),
        "time_to_first_success_s": mean("time_to_first_success_s"),
        "mean_episode_reward": mean("episode_reward"),
        "episodes": n,
        "env_steps_per_s": steps * env.num_envs / wall,
        "wall_s": wall,
        "physics_resets": env.physics_resets_total,
        "per_episode": per_episode,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--env", default="factory", choices=FAMILIES)
    ap.add_argument("--action-dim", type=int, default=6, choices=ACTION_DIMS)
    ap.add_argument("--policy", default="scripted", choices=POLICIES)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default=None, help="cpu or cuda:0 (default: cuda:0 when present)")
    ap.add_argument("--solver", default="mujoco", choices=SOLVERS)
    ap.add_argument("--json", type=Path, default=None, help="output file (never overwritten)")
    args = ap.parse_args(argv)
    if args.num_envs < 1:
        ap.error("--num-envs must be >= 1")
    if args.episodes < 1:
        ap.error("--episodes must be >= 1")
    if args.json is not None and args.json.exists():
        ap.error(f"--json {args.json} exists; choose another path (results are never overwritten)")

    cfg = EnvConfig(task=args.task, family=args.env, action_dim=args.action_dim, num_envs=args.num_envs,
                    device=args.device, seed=args.seed, sim=SimConfig(solver=args.solver))
    env = AssemblyEnv(cfg)
    result = run(env, args.policy, args.episodes, seed=args.seed)
    result.update(task=args.task, env=args.env, action_dim=args.action_dim, policy=args.policy,
                  num_envs=args.num_envs, device=env.device, solver=args.solver, seed=args.seed)
    print(json.dumps({k: v for k, v in result.items() if k != "per_episode"}, indent=2))
    if args.json is not None:
        atomic_write_text(args.json, json.dumps(result, indent=2))  # FileExistsError rather than overwrite
    return 0


if __name__ == "__main__":
    sys.exit(main())
