"""Can the KGRL action space beat its prior on PegInsert Factory 4D at all? A scripted search.

A hand-written policy in the null space (a = 0: the prior) that, from step n0 on, while the TCP is
still above the seated height, sweeps a spiral of growing radius (a_xy = r(k) (cos, sin)(2 pi k / T))
on the 128 evaluation episodes of eval seed 10000, the episodes run.py's final evaluation uses.
Paired with the prior on the same episodes. Usage: python docs/results/kgrl_reach_28/spiral_probe.py
[XY_MM,Z_MM ...] (reach floors on x, y and on z)
"""
import math
import sys

import numpy as np
import torch

from vkgrl_newton.runtime import configure_warp

configure_warp()
from vkgrl_newton.envs.kgrl_action import KGRLActionPath  # noqa: E402
from vkgrl_newton.prepare.prior import load_or_make_prior
from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig  # noqa: E402
from vkgrl_newton.kmp.tables import with_reach_floor  # noqa: E402
from vkgrl_newton.results.paired import paired_gain, seed_evaluation  # noqa: E402

torch.set_num_threads(1)
E, ROUNDS = 16, 8
env = AssemblyEnv(EnvConfig(task="PegInsert", family="factory", action_dim=4, num_envs=E, device="cpu", seed=0))
tables, _ = load_or_make_prior("PegInsert", 4, "runs/cache", device="cpu", log=lambda m: None)
seat_z = float(tables.mean[-1, 2])  # the prior's final TCP height over the target frame (seated)


def run(path, policy) -> np.ndarray:
    seed_evaluation(env, 10000)
    out = []
    for _ in range(ROUNDS):
        obs = env.get_observations()["policy"]
        for n in range(env.max_episode_length):
            obs, _, _, _ = path.step(policy(n, obs))
            obs = obs["policy"]
        out.append(env.last_episode_success_any.float().numpy().copy())
    return np.concatenate(out)


def spiral(n0: int, turn_steps: int, grow_steps: int, blocked_mm: float, lift: float = 0.0):
    def policy(n, obs):
        a = torch.zeros(E, 4)
        k = n - n0
        if k >= 0:
            r = min(1.0, (k + 1) / grow_steps)
            th = 2 * math.pi * k / turn_steps
            blocked = (obs[:, 3] - seat_z) > blocked_mm * 1e-3  # obs: time, tcp - target (x, y, z), quat
            a[:, 0] = r * math.cos(th) * blocked
            a[:, 1] = r * math.sin(th) * blocked
            a[:, 2] = lift * blocked  # up: less pressing force, so the peg can slide (z needs a floor too)
        return a
    return policy


W = [env.task.w_pos] * 3 + [env.task.w_rot] * 3
for floor_mm, z_floor_mm in [tuple(float(x) for x in v.split(",")) for v in sys.argv[1:]] or [(3.0, 0.0)]:
    lifted = with_reach_floor(with_reach_floor(tables, floor_mm * 1e-3, W, axes=(0, 1)), z_floor_mm * 1e-3, W, axes=(2,))
    path = KGRLActionPath(lifted, env)
    prior = run(path, lambda n, obs: torch.zeros(E, 4))
    print(f"reach floor xy {floor_mm} mm, z {z_floor_mm} mm: prior success_any {prior.mean():.3f} "
          f"({int(prior.sum())}/{len(prior)})", flush=True)
    for n0, turn, grow, blocked, lift in ((90, 20, 40, 3.0, 0.0), (90, 20, 40, 3.0, 0.8), (70, 30, 60, 3.0, 0.8)):
        if lift and not z_floor_mm:
            continue
        s = run(path, spiral(n0, turn, grow, blocked, lift))
        g = paired_gain(s, prior, seed=0)
        print(f"  spiral n0={n0} turn={turn} grow={grow} blocked>{blocked}mm lift={lift}: {s.mean():.3f} ({int(s.sum())}/{len(s)}), "
              f"gain {g['mean']:+.3f} [{g['ci_low']:+.3f}, {g['ci_high']:+.3f}]", flush=True)
