"""Record scripted demonstrations in the simulator for the KMP prior.

    python train/collect_demos.py --task PegInsert --num-demos 16 --out runs/demos/peg_insert.npz

Runs the scripted inserter (vkgrl_newton/envs/scripted.py) in `--num-envs` worlds until
`--num-demos` successful episodes are recorded, and writes the 6D relative TCP pose eta
(thesis eqs. 5.21, 5.26-5.29: position relative to the observed target frame, rotation as
log(q_ref^-1 q_tcp)) at every control step over normalized time s = t / T, in the npz format that
`train/plot_kmp.py --demos` and the KGRL prior read. Only episodes in which the part was seated
(`success_rate_any`) are kept: a demonstration should show the task done. The output file is
never overwritten.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vkgrl_newton.envs.assembly_env import FAMILIES, AssemblyEnv, EnvConfig  # noqa: E402
from vkgrl_newton.envs.scripted import ScriptedInserter  # noqa: E402
from vkgrl_newton.kmp.demos import DemoSet  # noqa: E402
from vkgrl_newton.kmp.pose import pose_to_eta, unwrap_rotation_vectors  # noqa: E402
from vkgrl_newton.tasks import TASKS  # noqa: E402


def collect(env: AssemblyEnv, num_demos: int, seed: int = 0, max_episodes: int = 20) -> tuple[list[np.ndarray], int]:
    """Successful eta trajectories (each (T+1, 6), float64) and the number of episodes run."""
    policy = ScriptedInserter(seed=seed)
    demos: list[np.ndarray] = []
    episodes = 0
    bar = tqdm(total=num_demos, desc="demos", unit="demo")
    while len(demos) < num_demos and episodes < max_episodes:
        policy.reset(env)
        traj = [_eta(env)]
        while True:
            _, _, _, extras = env.step_pose(*policy.act(env))
            if "episode" in extras:
                break
            traj.append(_eta(env))
        # the env auto-reset the worlds at the time-out; the last pose is the one before it
        success = env.last_episode_success_any.cpu().numpy()
        traj = np.stack(traj, axis=1)  # (E, T, 6)
        for w in np.nonzero(success)[0]:
            if len(demos) < num_demos:
                eta = traj[w].copy()
                eta[:, 3:] = unwrap_rotation_vectors(eta[:, 3:])
                demos.append(eta)
                bar.update(1)
        episodes += 1
    bar.close()
    return demos, episodes


def _eta(env: AssemblyEnv) -> np.ndarray:
    tcp_p, tcp_q = env.tcp_pose()
    eta = pose_to_eta(tcp_p.double(), tcp_q.double(), env.target_frame_pos_w.double(), env.task.psi_ref)
    return eta.cpu().numpy()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--env", default="factory", choices=FAMILIES)
    ap.add_argument("--num-demos", type=int, default=16)
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--max-episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True, help="output .npz (never overwritten)")
    args = ap.parse_args(argv)
    if args.num_demos < 2:
        ap.error("--num-demos must be >= 2 (a distribution needs several demonstrations)")
    if args.num_envs < 1:
        ap.error("--num-envs must be >= 1")
    if args.out.exists():
        ap.error(f"--out {args.out} exists; demonstrations are never overwritten")

    env = AssemblyEnv(EnvConfig(task=args.task, family=args.env, action_dim=6, num_envs=args.num_envs,
                                device=args.device, seed=args.seed))
    demos, episodes = collect(env, args.num_demos, seed=args.seed, max_episodes=args.max_episodes)
    if len(demos) < 2:
        print(f"only {len(demos)} successful demonstrations in {episodes} episodes; nothing written", file=sys.stderr)
        return 1
    lengths = np.array([d.shape[0] for d in demos], dtype=np.int64)
    s = np.concatenate([np.linspace(0.0, 1.0, n) for n in lengths])
    demo_set = DemoSet(s=s, eta=np.concatenate(demos), demo_lengths=lengths, task=args.task,
                       psi_ref=env.task.psi_ref, action_dim=6, source=f"scripted:{args.env}:seed{args.seed}")
    path = demo_set.save(args.out)
    print(f"wrote {len(demos)} demonstrations ({episodes} episodes of {args.num_envs} worlds) to {path}")
    return 0


if __name__ == "__main__":
    torch.set_num_threads(1)
    sys.exit(main())
