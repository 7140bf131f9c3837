"""Run a policy in the assembly env and write the thesis metrics as JSON.

    python train/evaluate.py --task PegInsert --env factory --action-dim 4 --policy scripted \
        --num-envs 16 --episodes 2 --json runs/eval/peg_factory_4d_scripted.json
    python train/evaluate.py --checkpoint runs/train/PegInsert_kgrl_factory_4d_seed0/checkpoints/last.pt \
        --episodes 2 --video runs/eval/kgrl.gif

Policies: `scripted` (privileged demonstrator, absolute TCP poses through `step_pose`),
`scripted_delta` (the same demonstrator through the SAC action space: what a SAC run's
`--sac prior_rollouts_policy=scripted` rollouts are), `random`
(uniform in [-1, 1]^D) and `zero` (both through the SAC action path `step`), `kmp_prior` (the
KMP prior alone, zeta = 0, fitted as train/run.py does), `kmp_search` (the prior plus a blind spiral
search once the part is blocked, from the observation alone, in a null space with reach floors of its
own: envs.evaluation.KMPSearchPolicy, a baseline of what the KGRL action space holds). `--checkpoint` evaluates a trained
agent deterministically (`--stochastic`: with samples of its actions, as in training); task, method, family, action space and time ablation come from the
checkpoint. Metrics per episode (all worlds end together): success at the episode's last step
(`success_rate`), success at any step (`success_rate_any`), mean contact force (thesis eq. 6.1,
N), peak contact force, time to first success (s, over the episodes that reached it), episode
reward; plus env steps per second and the number of physics resets. `--video` records the task
camera of the first worlds as a GIF. Existing output files are never overwritten.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# light modules only up to the argument checks (no torch, Warp or Newton): --help and argument errors
# answer at once; the heavy modules load in main() once the arguments are checked
from vkgrl_newton._io import atomic_write_text, output_path_error, strict_json  # noqa: E402
from vkgrl_newton.cli_types import (EVAL_SEED_BITS, add_cache_dir_option, add_device_option,  # noqa: E402
                                    add_eager_physics_flag, add_eval_seed_option, add_kmp_reference_option,
                                    positive_int, seed_error)
from vkgrl_newton.results.paired import EVAL_SEED  # noqa: E402
from vkgrl_newton.run.config import ConfigError, add_cpu_matmul_option  # noqa: E402
from vkgrl_newton.run.evaluate import POLICIES, checkpoint_config, evaluate_policy  # noqa: E402
from vkgrl_newton.runtime import parse_cli  # noqa: E402
from vkgrl_newton.signals import run_cli  # noqa: E402
from vkgrl_newton.tasks import ACTION_DIMS, FAMILIES, GEOMETRIES, SOLVERS, TASKS  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--env", default="factory", choices=FAMILIES)
    ap.add_argument("--action-dim", type=int, default=6, choices=ACTION_DIMS)
    ap.add_argument("--policy", default="scripted", choices=POLICIES)
    ap.add_argument("--checkpoint", type=Path, default=None, help="a train/run.py checkpoint (replaces --policy)")
    ap.add_argument("--stochastic", action="store_true",
                    help="with --checkpoint: act with samples of the policy (as in training) instead of its mean; "
                         "the draws follow --seed")
    ap.add_argument("--num-envs", type=positive_int, default=16)
    ap.add_argument("--episodes", type=positive_int, default=2)
    ap.add_argument("--seed", type=int, default=0, help="the env's construction and the scripted/random policies' draws")
    add_eval_seed_option(ap, EVAL_SEED)
    add_device_option(ap)
    add_eager_physics_flag(ap)
    ap.add_argument("--solver", default="mujoco", choices=SOLVERS)
    ap.add_argument("--geometry", default=None, choices=GEOMETRIES,
                    help="GearMesh/NutThread collision geometry (mesh: tooth/thread meshes, SDFs on CUDA); "
                         "default: the checkpoint's, else primitives (given, it evaluates a policy on the other one)")
    ap.add_argument("--no-time-obs", action="store_true", help="kmp_prior / checkpoint: policy input without time")
    add_cache_dir_option(ap)
    ap.add_argument("--demos", type=Path, default=None, help="kmp_prior, kmp_search: your own demonstrations")
    add_kmp_reference_option(ap, "gmr")
    add_cpu_matmul_option(ap, "a SAC checkpoint's CPU matmul library: default the one it trained on (its results "
                              "repeat); auto (this machine's faster one), onednn or torch (MKL)")
    ap.add_argument("--json", type=Path, default=None, help="output file (never overwritten)")
    ap.add_argument("--video", type=Path, default=None, help="GIF of the task camera (first 4 worlds, tiled)")
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = parse_cli(ap, argv, device=True)
    for name in ("json", "video"):  # (checked before the evaluation: its result is never computed and then lost)
        out = getattr(args, name)
        if out is not None and (why := output_path_error(out, f"--{name}")):
            ap.error(why)
    for why in (seed_error("--seed", args.seed), seed_error("--eval-seed", args.eval_seed, EVAL_SEED_BITS)):
        if why:
            ap.error(why)
    if args.stochastic and args.checkpoint is None:
        ap.error("--stochastic samples a trained policy's actions: give --checkpoint")
    if args.cpu_matmul is not None and args.checkpoint is None:
        ap.error("--cpu-matmul chooses a SAC checkpoint's matmul library: give --checkpoint")
    payload = None
    try:
        import torch

        torch.set_num_threads(1)  # (before a --cpu-matmul auto choice: it is made for the threads that run)
        if args.checkpoint is not None:
            from vkgrl_newton.agents.checkpoint import load_checkpoint

            try:
                payload = load_checkpoint(args.checkpoint)
            except (FileNotFoundError, ValueError) as e:
                raise ConfigError(f"--checkpoint: {e}") from None
            words = argv if argv is not None else sys.argv[1:]
            given = {a.dest for a in ap._actions for o in a.option_strings
                     if any(w == o or w.startswith(o + "=") for w in words)}
            checkpoint_config(args, payload, given)
        result = evaluate_policy(args, payload)
    except ConfigError as e:
        ap.error(str(e))
    frames = result.pop("_frames")
    print(strict_json({k: v for k, v in result.items() if k != "per_episode"}, indent=2))
    print(f"{result['episodes']} episodes: {args.num_envs} worlds x {args.episodes} per world")
    if args.json is not None:
        atomic_write_text(args.json, strict_json(result, indent=2))  # FileExistsError rather than overwrite
    if frames:
        from vkgrl_newton.envs.evaluation import write_video

        write_video(args.video, frames)
        print(f"wrote {args.video} ({len(frames)} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "train/evaluate.py"))
