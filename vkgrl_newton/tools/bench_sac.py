"""SAC update throughput: gradient steps per second of our agent vs stable-baselines3's SAC.

    python -m vkgrl_newton.tools.bench_sac --device cpu --steps 50 --json runs/bench/sac.json

Both learn on the thesis network ([512, 256, 128] ELU, 2 critics, AdamW weight decay 1e-4) and
batch (256), from a replay buffer pre-filled with random transitions, on the same device and in
the same process. Three variants, timed interleaved and repeated (the median is reported, since
a shared CPU drifts):
  ours_thesis  Table 5.3 as configured (policy_delay 4: the actor and alpha every 4th step)
  ours_delay1  policy_delay 1: the same work per step as SB3, whose SAC has no policy delay
  ours_delay1_<other>  the same on the other CPU matmul library (onednn or torch: MKL), CPU only
  sb3          stable_baselines3.SAC.train(gradient_steps, batch_size), if stable-baselines3 is
               installed (an optional extra; skipped with a message otherwise)
`--cpu-matmul` (default auto, as run.py's) picks the library of ours_thesis and ours_delay1; "auto" is
this machine's faster one (agents/matmul_backend.py, kept in --cache-dir), and the JSON's `cpu_matmul`
is the one that ran, with each variant's beside its figures. `ratio_to_sb3` is ours_delay1 / sb3.
Not identical work: ours also normalizes observations (rsl-rl EmpiricalNormalization); SB3 here
has no VecNormalize. Default dims: the Factory 4D policy observation is 1 + 3 + 4 = 8 (thesis
eq. 5.5-5.6: 8, 11, 24 or 27) and the action is 4D.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .._io import atomic_write_text, output_path_error
from ..agents.dense import onednn_available
from ..agents.matmul_backend import CHOICE_FILE, choose_cpu_matmul
from ..agents.sac import SAC, make_sac_config
from ..cli_types import add_cache_dir_option, add_device_option, nonnegative_int, positive_int
from ..run.config import add_cpu_matmul_option
from ..runtime import cpu_model, device_error, parse_cli
from ..signals import run_cli


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _random_transitions(n: int, obs_dim: int, action_dim: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "obs": rng.normal(size=(n, obs_dim)).astype(np.float32),
        "action": rng.uniform(-1, 1, size=(n, action_dim)).astype(np.float32),
        "reward": rng.normal(size=n).astype(np.float32),
        "next_obs": rng.normal(size=(n, obs_dim)).astype(np.float32),
        "terminated": (rng.uniform(size=n) < 0.01).astype(np.float32),
    }


def bench_config(args: argparse.Namespace, policy_delay: int, cpu_matmul: str):
    return make_sac_config("thesis", buffer_size=args.fill, learning_starts=0, batch_size=args.batch_size,
                           hidden_dims=tuple(args.hidden), policy_delay=policy_delay, cpu_matmul=cpu_matmul)


def make_ours(args: argparse.Namespace, data: dict[str, np.ndarray], policy_delay: int,
              cpu_matmul: str) -> tuple[Callable[[int], None], str]:
    """(n gradient steps, the matmul library that runs them)."""
    agent = SAC(args.obs_dim, args.action_dim, bench_config(args, policy_delay, cpu_matmul), args.device, seed=0)
    agent.add(*(torch.from_numpy(data[k]) for k in ("obs", "action", "reward", "next_obs", "terminated")))
    return (lambda steps: agent.update(steps)), agent.cpu_matmul


def make_sb3(args: argparse.Namespace, data: dict[str, np.ndarray]) -> Callable[[int], None]:
    import gymnasium as gym
    from stable_baselines3 import SAC as SB3SAC
    from stable_baselines3.common.logger import Logger

    class _Spaces(gym.Env):  # SB3 reads the spaces from an env; it is never stepped here
        observation_space = gym.spaces.Box(-np.inf, np.inf, (args.obs_dim,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (args.action_dim,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(args.obs_dim, np.float32), {}

        def step(self, action):
            return np.zeros(args.obs_dim, np.float32), 0.0, False, False, {}

    model = SB3SAC(
        "MlpPolicy", _Spaces(), learning_rate=4e-4, buffer_size=args.fill, learning_starts=0,
        batch_size=args.batch_size, tau=0.005, gamma=0.99, device=args.device, seed=0,
        policy_kwargs=dict(net_arch=list(args.hidden), activation_fn=torch.nn.ELU, n_critics=2,
                           optimizer_class=torch.optim.AdamW, optimizer_kwargs=dict(weight_decay=1e-4)),
    )
    model.set_logger(Logger(folder=None, output_formats=[]))
    rb = model.replay_buffer  # arrays (buffer_size, n_envs=1, ...); fill them directly
    rb.observations[:, 0] = data["obs"]
    rb.next_observations[:, 0] = data["next_obs"]
    rb.actions[:, 0] = data["action"]
    rb.rewards[:, 0] = data["reward"]
    rb.dones[:, 0] = data["terminated"]
    rb.pos, rb.full = 0, True
    return lambda steps: model.train(gradient_steps=steps, batch_size=args.batch_size)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_device_option(p, default="cpu")
    p.add_argument("--steps", type=positive_int, default=50, help="gradient steps per timed call")
    p.add_argument("--repeats", type=positive_int, default=5)
    p.add_argument("--obs-dim", type=positive_int, default=8)
    p.add_argument("--action-dim", type=positive_int, default=4)
    p.add_argument("--batch-size", type=positive_int, default=256)
    p.add_argument("--hidden", type=positive_int, nargs="+", default=[512, 256, 128])
    p.add_argument("--fill", type=positive_int, default=20_000, help="random transitions in the replay buffer")
    p.add_argument("--threads", type=nonnegative_int, default=None,
                   help="torch intra-op threads (default: torch's). On a shared 2-core CPU, 1 avoids OpenMP "
                        "barriers stalling whenever another process holds a core")
    add_cpu_matmul_option(p, "ours_thesis's and ours_delay1's CPU matmul library (default auto: this machine's "
                             "faster one, timed once and kept in --cache-dir, as run.py chooses it)")
    add_cache_dir_option(p)
    p.add_argument("--json", type=Path, default=None)
    args = parse_cli(p, argv)
    if args.json is not None and (why := output_path_error(args.json, "--json")):
        p.error(why)
    if args.batch_size > args.fill:  # a batch is drawn from the filled buffer
        p.error(f"--batch-size {args.batch_size}: must be <= --fill {args.fill} (the replay buffer's transitions)")
    if (why := device_error(args.device)) is not None:
        p.error(why)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    data = _random_transitions(args.fill, args.obs_dim, args.action_dim, seed=0)

    chosen = choose_cpu_matmul(bench_config(args, 1, args.cpu_matmul or "auto"), args.obs_dim, args.action_dim,
                               device, args.cache_dir / CHOICE_FILE, log=lambda m: print(f"[bench_sac] {m}"))
    if chosen == "onednn" and device.type == "cpu" and not onednn_available():
        p.error(f"--cpu-matmul onednn: this torch ({torch.__version__}) does not provide oneDNN's linear; give auto "
                "or torch")
    runners: dict[str, Callable[[int], None]] = {}
    backends: dict[str, str] = {}
    variants = [("ours_thesis", 4, chosen), ("ours_delay1", 1, chosen)]
    if device.type == "cpu" and onednn_available():  # the same agent on the other library
        other = "torch" if chosen == "onednn" else "onednn"
        variants.append((f"ours_delay1_{other}", 1, other))
    for name, delay, backend in variants:
        runners[name], backends[name] = make_ours(args, data, policy_delay=delay, cpu_matmul=backend)
    sb3_note = None
    try:
        runners["sb3"] = make_sb3(args, data)
    except ImportError as e:
        sb3_note = f"skipped: stable-baselines3 not importable ({e}); pip install stable-baselines3 --no-deps"
        print(f"[bench_sac] SB3 {sb3_note}")

    times: dict[str, list[float]] = {k: [] for k in runners}
    for run in runners.values():  # warm-up: allocator, optimizer state, lazy init
        run(max(1, min(8, args.steps)))
    for _ in range(args.repeats):
        for name, run in runners.items():  # interleaved so drift hits all variants alike
            _sync(device)
            t = time.perf_counter()
            run(args.steps)
            _sync(device)
            times[name].append(time.perf_counter() - t)

    results = {}
    for name, ts in times.items():
        results[name] = {"grad_steps_per_s_median": args.steps / statistics.median(ts),
                         "grad_steps_per_s_best": args.steps / min(ts), "seconds": ts}
        if name in backends:
            results[name]["cpu_matmul"] = backends[name]
    if sb3_note:
        results["sb3"] = {"note": sb3_note}
    report = {
        "device": str(device), "cpu": cpu_model(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "obs_dim": args.obs_dim, "action_dim": args.action_dim, "batch_size": args.batch_size,
        "hidden": args.hidden, "activation": "elu", "n_critics": 2, "cpu_matmul": backends["ours_delay1"],
        "cpu_matmul_requested": args.cpu_matmul or "auto", "steps_per_call": args.steps,
        "repeats": args.repeats, "results": results,
    }
    if "grad_steps_per_s_median" in results.get("sb3", {}):  # like for like: no policy delay on either side
        report["ratio_to_sb3"] = (results["ours_delay1"]["grad_steps_per_s_median"]
                                  / results["sb3"]["grad_steps_per_s_median"])
    print(f"[bench_sac] {report['cpu']}, {report['cpu_count']} cores, torch {report['torch']}")
    for name, r in results.items():
        line = r.get("note") or (f"{r['grad_steps_per_s_median']:8.1f} grad steps/s "
                                 f"(best {r['grad_steps_per_s_best']:.1f})"
                                 + (f"  [{r['cpu_matmul']}]" if "cpu_matmul" in r else ""))
        print(f"{name:18s} {line}")
    if "ratio_to_sb3" in report:
        print(f"ours_delay1 / sb3: {report['ratio_to_sb3']:.2f}x")
    if args.json:
        atomic_write_text(args.json, json.dumps(report, indent=2))  # never overwrites
    return report


if __name__ == "__main__":
    def _cli() -> int:  # main() returns the report (for callers); the command's status is 0
        main()
        return 0

    raise SystemExit(run_cli(_cli, "bench_sac", "nothing was written"))
