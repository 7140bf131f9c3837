"""Where a training transition's wall time goes, and how close the update comes to the machine's peak.

    python -m vkgrl_newton.tools.bench_loop --methods sac kgrl vision_kgrl --json runs/bench/loop.json

For each method's quick recipe (run.py's own configuration: 16 worlds, the preset's networks and
16 gradient steps per batched env step), the real training loop (run.train) runs `--transitions`
transitions with the loop's overlap off, so that its parts add up, and every call of
  physics              the control step (PhysicsStepper.control_step: OSC, collision, solver, forces)
  camera and encoder   the task camera's render and the frozen VAE encoder (vision methods)
  gradient steps       SAC.update
is timed; "the rest" is the wall time less these (the policy's action, the KGRL action path,
observations, rewards, the replay buffer, logging). Only the steady state is counted: from the
first env step after the updates start (learning_starts) to the end. Then the same run with the
loop's overlap on (run.py's CPU default: the env steps in a worker thread while the update runs)
gives the transitions per second a user sees.

The update's achieved GFLOP/s counts the matrix products of a SAC gradient step (`sac_step_flops`,
checked against torch's FlopCounterMode: critic: forward and backward of the ensemble, the target
ensemble's and the actor's forward; the actor every policy_delay steps: its forward and backward
and the frozen critics' forward and input gradient)
and sets it beside the machine's measured matmul peak: the fastest of both libraries on one
product of the networks' widest shape (batch x 256 x 256 for the quick networks), timed here.

A vision method's VAE is an untrained one of the quick preset's shape and camera (the same cost as
a trained one; no image set or VAE training). A KGRL method takes its prior from --cache-dir (made
on first use: a few minutes). The JSON (never overwritten) names the CPU, cores, torch and the
matmul library of every row.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from .._io import output_path_error
from ..cli_types import add_cache_dir_option, positive_int
from ..runtime import parse_cli
from ..signals import run_cli

METHODS = ("sac", "kgrl", "vision_sac", "vision_kgrl")
PARTS = ("physics", "camera and encoder", "gradient steps")


def sac_step_flops(obs_dim: int, action_dim: int, hidden: tuple[int, ...], n_critics: int, batch: int,
                   policy_delay: int) -> float:
    """Floating-point operations of the matrix products of one SAC gradient step (2 per multiply-add),
    as torch's FlopCounterMode counts them on `SAC.update` (tests/test_bench_loop.py).

    A layer's forward is 2 B in out; its weight gradient as much, its input gradient as much again
    except in a first layer whose input needs none (the observations); the frozen critics in the
    actor's loss need only input gradients, down to the action."""
    def forward(dims):  # of the batch
        return 2 * batch * sum(i * o for i, o in zip(dims[:-1], dims[1:]))

    actor, actor_first = forward([obs_dim, *hidden, 2 * action_dim]), 2 * batch * obs_dim * hidden[0]
    critics = n_critics * forward([obs_dim + action_dim, *hidden, 1])
    critics_first = n_critics * 2 * batch * (obs_dim + action_dim) * hidden[0]
    # online critics: forward, weight and input gradients; the target critics' and the next action's forwards
    critic_update = 3 * critics - critics_first + critics + actor
    actor_update = 3 * actor - actor_first + 2 * critics  # the actor's fwd and grads; frozen critics' fwd and d/da
    return critic_update + actor_update / policy_delay


def matmul_peak(m: int, k: int, n: int, seconds: float = 0.5) -> dict:
    """GFLOP/s of one (m, k) @ (k, n) float32 product on each library: the fastest timed call."""
    import torch

    from ..agents.dense import linear, onednn_available

    g = torch.Generator().manual_seed(0)
    x, w, b = torch.randn(m, k, generator=g), torch.randn(n, k, generator=g), torch.zeros(n)
    out = {}
    for backend in ("torch", "onednn") if onednn_available() else ("torch",):
        for _ in range(5):
            linear(x, w, b, backend)
        best, t_end = float("inf"), time.perf_counter() + seconds
        while time.perf_counter() < t_end:
            t = time.perf_counter()
            for _ in range(10):
                linear(x, w, b, backend)
            best = min(best, (time.perf_counter() - t) / 10)
        out[backend] = 2 * m * k * n / best / 1e9
    return out


class _Timers:
    """Wraps the parts' callables at class level; counts from `start()` on."""

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(PARTS, 0.0)
        self.calls = dict.fromkeys(PARTS, 0)
        self.counting = False
        self.t0 = self.t_last = None

    def wrap(self, owner, name: str, part: str, stack: contextlib.ExitStack) -> None:
        real = getattr(owner, name)

        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return real(*args, **kwargs)
            finally:
                now = time.perf_counter()
                if self.counting:
                    self.seconds[part] += now - t
                    self.calls[part] += 1
                    self.t_last = now

        setattr(owner, name, timed)
        stack.callback(setattr, owner, name, real)

    def start(self) -> None:
        self.counting, self.t0 = True, time.perf_counter()


def _run_config(method: str, transitions: int, overlap: bool, run_dir: Path, cache_dir: Path, vae: Path | None,
                cpu_matmul: str | None):
    from ..run.config import build_parser
    from ..run.methods import METHODS as ROWS
    from ..run.resolve import resolve

    argv = ["--method", method, "--device", "cpu", "--total-steps", str(transitions), "--eval-episodes", "0",
            "--run-dir", str(run_dir), "--cache-dir", str(cache_dir), "--no-progress",
            "--overlap" if overlap else "--no-overlap", "--checkpoint-every", str(10 * transitions)]
    if vae is not None:
        argv += ["--vae", str(vae)]
    if ROWS[method].takes_recipe:  # the recipe of docs/results.md's figures (and a given --vae goes with it; the
        argv += ["--kgrl-recipe", "reach_keep_prior"]  # residual recipe, the quick default here, takes the cache's)
    if cpu_matmul is not None:
        argv += ["--cpu-matmul", cpu_matmul]
    return resolve(build_parser(), argv).config


def _untrained_vae(path: Path, task: str) -> Path:
    """A VAE file of the quick preset's shape and camera (untrained weights cost the same)."""
    from ..prepare.images import collect_camera_spec
    from ..prepare.vision import VISION_PRESETS
    from ..vision.vae import DenoisingVAE, save_vae

    p = VISION_PRESETS["quick"]
    camera = dataclasses.asdict(collect_camera_spec(p.collect_config(task)))
    cfg = p.vae_config()
    return save_vae(path, DenoisingVAE(cfg), cfg, meta={"task": task, "camera": camera})


def _timed_run(cfg) -> _Timers:
    """run.train on `cfg` with the parts timed from the first transition after learning_starts."""
    from ..agents.sac import SAC
    from ..envs.camera_latent import CameraLatent
    from ..run.train import train
    from ..sim.physics import PhysicsStepper

    timers = _Timers()
    starts_at = cfg.sac.learning_starts  # updates run from here: the steady state
    with contextlib.ExitStack() as stack:
        timers.wrap(PhysicsStepper, "control_step", "physics", stack)
        timers.wrap(CameraLatent, "__call__", "camera and encoder", stack)
        timers.wrap(SAC, "update", "gradient steps", stack)
        real_add = SAC.add

        def add(agent, *args, **kwargs):  # the first transition after learning_starts starts the clock
            real_add(agent, *args, **kwargs)
            if not timers.counting and agent.num_transitions >= starts_at:
                timers.start()

        SAC.add = add
        stack.callback(setattr, SAC, "add", real_add)
        if train(cfg, log=lambda m: None) != 0:
            raise RuntimeError(f"{cfg.method}: the timed run did not finish")
    return timers


def measure(method: str, transitions: int, cache_dir: Path, work: Path, cpu_matmul: str | None = None) -> dict:
    """One method's split (overlap off) and its overlapped rate, both over the steady state."""
    vae = _untrained_vae(work / f"{method}_vae.pt", "PegInsert") if method.startswith("vision") else None
    cfg = _run_config(method, transitions, False, work / f"{method}_split", cache_dir, vae, cpu_matmul)
    timers = _timed_run(cfg)
    metrics = json.loads((cfg.run_dir / "metrics.json").read_text())
    wall = timers.t_last - timers.t0
    counted = transitions - cfg.sac.learning_starts
    split = {k: v / counted * 1e3 for k, v in timers.seconds.items()}
    split["the rest"] = wall / counted * 1e3 - sum(split.values())
    s = cfg.sac
    flops = sac_step_flops(cfg.obs_dim, cfg.action_dim, s.hidden_dims, s.n_critics, s.batch_size, s.policy_delay)
    updates = timers.calls["gradient steps"] * s.gradient_steps  # (each call runs gradient_steps steps)
    over = _run_config(method, transitions, True, work / f"{method}_overlap", cache_dir, vae, cpu_matmul)
    timers_over = _timed_run(over)
    return {
        "method": method, "transitions": transitions, "cpu_matmul": metrics.get("cpu_matmul"),
        "num_envs": cfg.num_envs, "hidden": list(s.hidden_dims), "batch_size": s.batch_size,
        "gradient_steps_per_env_step": s.gradient_steps, "obs_dim": cfg.obs_dim, "counted_transitions": counted,
        "overlap_transitions_per_s": counted / (timers_over.t_last - timers_over.t0),
        "no_overlap_transitions_per_s": counted / wall, "ms_per_transition": split,
        "share": {k: v / (wall / counted * 1e3) for k, v in split.items()},
        "gflop_per_grad_step": flops / 1e9,
        "update_gflop_per_s": flops * updates / max(timers.seconds["gradient steps"], 1e-9) / 1e9,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--methods", nargs="+", default=["sac", "kgrl", "vision_kgrl"], choices=METHODS)
    ap.add_argument("--transitions", type=positive_int, default=3_200,
                    help="per run (the first learning_starts, 1 024 on the quick preset, are not counted)")
    ap.add_argument("--cpu-matmul", default=None, choices=("auto", "onednn", "torch"),
                    help="the runs' SAC matmul library (default: run.py's, auto)")
    add_cache_dir_option(ap)
    ap.add_argument("--json", type=Path, default=None, help="output file (never overwritten)")
    args = parse_cli(ap, argv)
    if args.transitions <= 1_024 + 16:
        ap.error("--transitions must be > 1040: the first 1 024 (learning_starts) are not counted")
    if args.json is not None and (why := output_path_error(args.json, "--json")):
        ap.error(why)
    import torch

    from .._io import atomic_write_text
    from ..runtime import cpu_model

    torch.set_num_threads(1)  # as run.py trains: its loop overlaps the env and the learner on two cores

    report = {"cpu": cpu_model(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
              "torch_threads": torch.get_num_threads(), "rows": []}
    with tempfile.TemporaryDirectory(prefix="bench_loop_") as work:
        for method in args.methods:
            row = measure(method, args.transitions, args.cache_dir, Path(work), args.cpu_matmul)
            widest = max(row["hidden"])
            row["matmul_peak_gflop_per_s"] = matmul_peak(row["batch_size"], widest, widest)
            row["update_fraction_of_peak"] = row["update_gflop_per_s"] / max(row["matmul_peak_gflop_per_s"].values())
            report["rows"].append(row)
            ms = row["ms_per_transition"]
            print(f"{method:12s} [{row['cpu_matmul']}] overlap on {row['overlap_transitions_per_s']:6.1f} transitions/s; "
                  f"off {row['no_overlap_transitions_per_s']:6.1f}/s = "
                  + ", ".join(f"{k} {v:.2f} ms" for k, v in ms.items())
                  + f" per transition; update {row['update_gflop_per_s']:.0f} GFLOP/s = "
                    f"{row['update_fraction_of_peak']:.0%} of the measured matmul peak "
                    f"({max(row['matmul_peak_gflop_per_s'].values()):.0f})", flush=True)
    print(f"[bench_loop] {report['cpu']}, {report['cpu_count']} cores, torch {report['torch']}")
    if args.json is not None:
        atomic_write_text(args.json, json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main, "bench_loop", "nothing was written"))
