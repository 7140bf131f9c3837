"""Record scripted demonstrations in the simulator for the KMP prior.

    python train/collect_demos.py --task PegInsert --num-demos 16 --out runs/demos/peg_insert.npz

Runs the scripted inserter (vkgrl_newton/envs/scripted.py) in `--num-envs` worlds until
`--num-demos` successful episodes are recorded, and writes the 6D relative TCP pose eta
at every control step over normalized time s = t / T (vkgrl_newton/envs/demonstrations.py), in
the npz format that `train/plot_kmp.py --demos` and the KGRL prior read. The output file is
never overwritten. `train/run.py --method kgrl` records its own when none are given.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# light modules only until the arguments are checked (see train/evaluate.py)
from vkgrl_newton._io import output_path_error  # noqa: E402
from vkgrl_newton.cli_types import add_device_option, device_name, positive_int, seed_error  # noqa: E402
from vkgrl_newton.runtime import parse_cli  # noqa: E402
from vkgrl_newton.signals import run_cli  # noqa: E402
from vkgrl_newton.tasks import FAMILIES, TASKS  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--env", default="factory", choices=FAMILIES)
    ap.add_argument("--num-demos", type=int, default=16)
    ap.add_argument("--num-envs", type=positive_int, default=16)
    ap.add_argument("--max-episodes", type=positive_int, default=20, help="rounds of --num-envs episodes at most")
    ap.add_argument("--seed", type=int, default=0)
    add_device_option(ap)
    ap.add_argument("--out", type=Path, required=True, help="output .npz (never overwritten)")
    args = parse_cli(ap, argv, device=True)
    if args.num_demos < 2:
        ap.error("--num-demos must be >= 2 (a distribution needs several demonstrations)")
    if why := seed_error("--seed", args.seed):
        ap.error(why)
    if why := output_path_error(args.out, "--out", what="demonstrations"):  # (before recording: never lost at the end)
        ap.error(why)

    import torch

    from vkgrl_newton.envs.assembly_env import AssemblyEnv, EnvConfig
    from vkgrl_newton.envs.demonstrations import record_demonstrations

    torch.set_num_threads(1)
    env = AssemblyEnv(EnvConfig(task=args.task, family=args.env, action_dim=6, num_envs=args.num_envs,
                                device=args.device, seed=args.seed))
    demo_set, episodes = record_demonstrations(env, args.num_demos, seed=args.seed, max_episodes=args.max_episodes)
    if demo_set is None:
        print(f"fewer than 2 successful demonstrations in {episodes} episodes; nothing written", file=sys.stderr)
        return 1
    path = demo_set.save(args.out)
    n = len(demo_set.demo_lengths)
    print(f"wrote {n} demonstrations ({episodes} episodes of {args.num_envs} worlds) to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "train/collect_demos.py"))
