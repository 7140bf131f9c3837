"""Env throughput: env steps per second at several world counts, and where the time goes.

    python -m vkgrl_newton.tools.throughput --num-worlds 1 16 64 --steps 10 --json runs/bench/env.json
    python -m vkgrl_newton.tools.throughput --task NutThread --policy scripted --warmup 75 --num-worlds 16
    python -m vkgrl_newton.tools.throughput --graph both --num-worlds 16 64 --json runs/bench/graph.json
    python -m vkgrl_newton.tools.throughput --vision quick --num-worlds 16 64     # with the task camera + encoder

Each env step is 8 physics steps (1/120 s) x `substeps` solver substeps, with the OSC kernel every
substep, plus the contact-force reduction and the Python/torch work of the step (action mapping,
observations, rewards, blow-up checks). The policy is zero actions through the SAC path (`step`),
factory family, 4-D actions (NutThread: a zero action turns the gripper clockwise at half speed,
see assembly_env); or, with `--policy scripted`, the scripted demonstrator through
`step_pose`, timed after `--warmup` steps (e.g. 75 for NutThread: the nut is on the thread and
contacts are at their peak). `--graph` picks the physics mode: `on` (the control step replayed as
one captured Warp graph, EnvConfig.graph), `off` (eager launches) or `both` (the default: each
world count in both modes, in one process, eager first). Timed runs per world count and mode:
1. plain: wall time of `--steps` env steps (no synchronization beyond what the env does itself);
2. eager only, profiled: the same number of steps with the device synchronized around each stage,
   giving the split kinematics+OSC (Newton's eval_jacobian/eval_mass_matrix and our OSC kernel),
   collision (Newton's pipeline), solver (MuJoCo-Warp), contact forces (our reduction kernels);
   "python" is the profiled total minus those stages. (A graph has no stages to time.)
With `--vision PRESET` the observation gains the vision latent of that preset's camera and an
encoder of the thesis's shape (untrained weights cost the same; envs.camera_latent.CameraLatent), so
every env step also renders and encodes, and the eager split has a "vision" stage.
Resets are excluded (the env is reset before timing). The JSON has `results`, one entry per
(task, num_worlds, mode) with `task`, `num_worlds`, `mode` ("eager" | "graph"), `env_steps_per_s`,
`ms_per_env_step`, and `speedup` (graph entries: eager ms / graph ms when both ran). An existing
JSON file is never overwritten.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import torch
import warp as wp

from .._io import atomic_write_text, output_path_error
from ..cli_types import add_device_option, device_name
from ..runtime import parse_cli
from ..signals import run_cli
from ..tasks import TASKS, get_task
from ..sim.physics import PROFILE_STAGES
from ..sim.scene import SimConfig
from ..envs.assembly_env import AssemblyEnv, EnvConfig

STAGES = PROFILE_STAGES + ("vision",)  # vision: the camera render and the encoder (with --vision)


MODES = {"on": ("graph",), "off": ("eager",), "both": ("eager", "graph")}


def measure(num_worlds: int, steps: int, device: str | None = None, warmup: int = 2, task: str = "PegInsert",
            policy: str = "zero", mode: str = "graph", sim: SimConfig | None = None, vision: str | None = None) -> dict:
    if mode not in ("eager", "graph"):
        raise ValueError(f"mode must be 'eager' or 'graph', got {mode!r}")
    env = AssemblyEnv(EnvConfig(task=task, num_envs=num_worlds, action_dim=4, family="factory", device=device,
                                graph=mode == "graph", sim=sim or SimConfig(), vision_latent_dim=16 if vision else 0))
    if vision is not None:
        from ..prepare.vision import untrained_preset_latent

        env.attach_vision(untrained_preset_latent(env, vision))
    if policy == "scripted":
        from ..envs.scripted import ScriptedInserter

        inserter = ScriptedInserter(seed=0)
        inserter.reset(env)
        step = lambda: env.step_pose(*inserter.act(env))  # noqa: E731
    else:
        zero = torch.zeros(num_worlds, 4, device=env.tdev)
        step = lambda: env.step(zero)  # noqa: E731
    for _ in range(warmup):
        step()
    wp.synchronize_device(env.device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    wp.synchronize_device(env.device)
    plain = time.perf_counter() - t0

    row = {
        "task": task,
        "policy": policy,
        "vision": vision,
        "num_worlds": num_worlds,
        "mode": mode,
        "device": str(env.device),
        "steps": steps,
        "ms_per_env_step": plain / steps * 1e3,
        "env_steps_per_s": num_worlds * steps / plain,
        "realtime_factor": num_worlds * steps * (1.0 / 15.0) / plain,
        # world-substeps of the timed stretch: the unit of native MuJoCo's cost (docs/log/benchmarks.md)
        "us_per_world_substep": plain / (steps * num_worlds * 8 * env.substeps) * 1e6,
        "contact_overflows": env.contact_overflows_total,
    }
    if mode == "eager":
        env.profile = {}
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        wp.synchronize_device(env.device)
        profiled = time.perf_counter() - t0
        split = {k: env.profile.get(k, 0.0) / steps * 1e3 for k in STAGES}
        split["python"] = profiled / steps * 1e3 - sum(split.values())
        env.profile = None
        row["profiled_ms_per_env_step"] = profiled / steps * 1e3
        row["split_ms_per_env_step"] = split
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--num-worlds", type=int, nargs="+", default=[1, 16, 64])
    ap.add_argument("--steps", type=int, default=10, help="timed env steps per run")
    add_device_option(ap)
    ap.add_argument("--json", type=Path, default=None, help="output file (never overwritten)")
    ap.add_argument("--task", default="PegInsert", choices=sorted(TASKS))
    ap.add_argument("--policy", default="zero", choices=("zero", "scripted"))
    ap.add_argument("--warmup", type=int, default=2, help="untimed env steps first")
    ap.add_argument("--collide-once-per-step", action="store_true",
                    help="SimConfig(collide_every_substep=False): collision once per physics step")
    ap.add_argument("--vision", default=None, metavar="PRESET",
                    help="render and encode the task camera of this vision preset every step (quick, thesis)")
    ap.add_argument("--graph", default="both", choices=sorted(MODES),
                    help="physics as one captured graph (on), eager launches (off), or both (default)")
    args = parse_cli(ap, argv, device=True)
    if min(args.num_worlds) < 1 or args.steps < 1 or args.warmup < 0:
        ap.error("--num-worlds and --steps must be >= 1, --warmup >= 0")
    episode = get_task(args.task).episode_steps
    if args.warmup + 2 * args.steps >= episode:
        ap.error(f"--warmup + 2 x --steps = {args.warmup + 2 * args.steps} must stay inside one {args.task} episode "
                 f"({episode} steps): a time-out reset would be timed")
    if args.warmup < 2 and "graph" in MODES[args.graph]:
        ap.error("--warmup must be >= 2 with a graph: the first step runs eagerly, the second records the graph "
                 "(neither is to be timed)")
    if args.json is not None and (why := output_path_error(args.json, "--json")):
        ap.error(why)
    from ..prepare.vision import VISION_PRESETS

    if args.vision is not None and args.vision not in VISION_PRESETS:
        ap.error(f"--vision {args.vision!r}; allowed: {', '.join(VISION_PRESETS)}")
    rows = []
    print(f"{'worlds':>6} {'mode':>6} {'ms/step':>9} {'env steps/s':>12} {'x realtime':>10} {'us/world-substep':>16} "
          f"{'speedup':>8}   eager split ms/step: " + " ".join(f"{k:>14}" for k in (*STAGES, "python")))
    for n in args.num_worlds:
        eager_ms = None
        for mode in MODES[args.graph]:
            r = measure(n, args.steps, args.device, warmup=args.warmup, task=args.task, policy=args.policy, mode=mode,
                        sim=SimConfig(collide_every_substep=not args.collide_once_per_step), vision=args.vision)
            r["collide_every_substep"] = not args.collide_once_per_step
            if mode == "eager":
                eager_ms = r["ms_per_env_step"]
            elif eager_ms is not None:
                r["speedup"] = eager_ms / r["ms_per_env_step"]
            rows.append(r)
            sp = r.get("split_ms_per_env_step")
            print(f"{n:>6} {mode:>6} {r['ms_per_env_step']:>9.1f} {r['env_steps_per_s']:>12.1f} "
                  f"{r['realtime_factor']:>10.2f} {r['us_per_world_substep']:>16.1f} "
                  f"{r['speedup'] if 'speedup' in r else float('nan'):>8.2f}   "
                  + (" ".join(f"{sp[k]:>14.1f}" for k in (*STAGES, "python")) if sp else ""), flush=True)
    if args.json is not None:
        meta = {"machine": platform.processor() or platform.machine(), "python": platform.python_version(),
                "warp": wp.__version__, "torch": torch.__version__}
        atomic_write_text(args.json, json.dumps({"meta": meta, "results": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "throughput", "nothing was written"))
