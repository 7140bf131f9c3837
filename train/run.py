"""Train a policy for an assembly task and report the thesis metrics.

    python train/run.py --task PegInsert --method kgrl --env factory --action-dim 4 --seed 0

Methods (thesis ch. 4-5): `sac` acts through Factory's delta-pose mapping; `kgrl` is the same
SAC acting in the null space of the task's KMP prior (vkgrl_newton/envs/kgrl_action.py), the action
path of eq. 4.36. `vision_sac` and `vision_kgrl` add the 16-d mean of a frozen denoising-VAE
encoder of the hand camera's image to the policy observation (eq. 5.6; vkgrl_newton/vision/).
Baselines beyond the thesis: `ppo`, `kgrl_ppo` and `vision_ppo`, rsl-rl's PPO with Isaac Lab Factory's
settings on the same action paths and observations (vkgrl_newton/agents/ppo_config.py; `--ppo KEY=VALUE`
overrides). Each method is one row of vkgrl_newton/run/methods.py; this file is the command line of
the run library vkgrl_newton/run/ (RunConfig, the builder, the loops).

Everything a method needs is produced on first use and cached under `--cache-dir` (KGRL: scripted
demonstrations recorded in the simulator, and the KMP tables fitted to them; vision: the task
camera image set and the VAE trained on it, vkgrl_newton/prepare/vision.py, per task and preset:
64 px / 4,096 images / 10 epochs for `quick`, 256 px / 130,000 / 400 for `thesis`; `--vae`
uses your own). A run directory holds:

    config.json          the arguments and the SAC configuration
    curves.jsonl         the learning curves as a table, a row per episode (vkgrl_newton/results/curves.py)
    tb/                  tensorboard scalars (episode reward, success rate, mean contact force,
                         time to first success, losses, alpha, throughput)
    checkpoints/last.pt  written atomically when the run starts, every --checkpoint-every
                         transitions, on Ctrl-C and at the end; `--resume` continues from it
    metrics.json         deterministic evaluation of the final policy (train/evaluate.py's keys)
                         and a training summary

A run directory that already holds a run is never reused without `--resume`. Resuming restores
the agent, its optimizers, normalizer and replay buffer, the RNG states and the counters; the
simulator starts fresh episodes (physics state is not checkpointed).

Steps are env transitions summed over worlds: 16 worlds x 150 control steps = 2400 per episode.
Defaults: preset `thesis` (Table 5.3, 128 worlds) on CUDA, `quick` (16 worlds) on CPU. kgrl and
vision_kgrl take the defaults of a recipe (`--kgrl-recipe`): with the quick preset `residual` on
PegInsert Factory 4D (a learned residual on a fixed controller, issue 40: 0.62 / 0.92 at 30k) and
`reach_keep_prior` elsewhere (issue 28's deviations, which beat the prior on paired episodes);
`base` with the thesis's.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# Light imports only above the parser (no torch, Warp, Newton or rsl-rl): --help and every argument
# error answer in well under a second; the heavy modules load once the arguments are checked.
from vkgrl_newton.run.config import ConfigError, build_parser  # noqa: E402
from vkgrl_newton.run.resolve import Done, resolve  # noqa: E402
from vkgrl_newton.signals import exit_code, stop_line, stop_signals_as_interrupts  # noqa: E402


def main(argv=None, torch_threads: int | None = None) -> int:
    """The run of the command line `argv`: 0 when done, 2 for a refusal (one line), a signal's exit code
    when stopped (checkpointed). torch_threads: intra-op threads (1 as a program: the loop overlaps env
    and learner on two cores)."""
    ap = build_parser(__doc__)
    with stop_signals_as_interrupts():  # SIGTERM / SIGHUP: checkpoint and exit like Ctrl-C, at every phase
        try:
            resolved = resolve(ap, argv, torch_threads=torch_threads)
        except ConfigError as e:
            ap.error(str(e))
        except KeyboardInterrupt as e:  # (timing the CPU matmul libraries on a new cache: its file is written whole)
            print(stop_line("train/run.py", e, "nothing was written; run again to continue"), file=sys.stderr)
            return exit_code(e)
        if isinstance(resolved, Done):
            print(resolved.message, file=sys.stderr)
            return resolved.code
        from vkgrl_newton.run.train import train

        return train(resolved.config, resolved.payload, torch_threads=torch_threads)


if __name__ == "__main__":
    sys.exit(main(torch_threads=1))
