"""Vision cost per control step: render every world's task camera, then encode with the frozen VAE.

    python -m vkgrl_newton.tools.bench_vision --num-worlds 16 128 --resolution 64 256 --calls 3 --json runs/bench/vision.json
    python -m vkgrl_newton.tools.bench_vision --num-worlds 16 64 --preset quick thesis --task NutThread

For each world count and camera: a task env (Factory, 4D; PegInsert unless --task) after its
reset, the task camera (Newton's SensorCamera) and a VAE encoder of the thesis's shape (5 conv
layers, latent 16; untrained weights cost the same). The camera is either Table 5.6's at a
--resolution, or a vision preset's (--preset: its resolution, lens, mount angles and sampling).
Reported per call, i.e. per control step of all worlds: render ms, encode ms, their sum, per
world, and beside them the env's control step itself (8 physics steps, the captured graph) at
the same world count, so the ratio vision / physics is read off one run. Timed after one
warm-up call; the device is synchronized around each stage. One torch thread unless --threads
says otherwise. An existing JSON file is never overwritten.
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

from ..cli_types import add_device_option
from .._io import atomic_write_text
from ..runtime import parse_cli
from ..envs.camera_latent import CameraLatent
from ..prepare.vision import untrained_preset_latent
from ..vision.vae import DenoisingVAE, FrozenEncoder, VAEConfig


def measure(num_worlds: int, resolution: int | None, calls: int, device: str | None = None, preset: str | None = None,
            task: str = "PegInsert") -> dict:
    import dataclasses

    from ..envs.assembly_env import AssemblyEnv, EnvConfig

    env = AssemblyEnv(EnvConfig(task=task, num_envs=num_worlds, action_dim=4, family="factory", device=device))
    if preset is not None:
        latent = untrained_preset_latent(env, preset)
        resolution = latent.spec.width
    else:
        latent = CameraLatent(env, FrozenEncoder(DenoisingVAE(VAEConfig(resolution=resolution))))
    latent(env)  # warm-up: kernels, BVH build, allocator
    env.step(torch.zeros(num_worlds, 4, device=env.tdev))  # warm-up (graph capture)
    physics = 0.0
    for _ in range(calls):
        wp.synchronize_device(env.device)
        t0 = time.perf_counter()
        env.step(torch.zeros(num_worlds, 4, device=env.tdev))
        wp.synchronize_device(env.device)
        physics += time.perf_counter() - t0
    render = encode = 0.0
    for _ in range(calls):
        wp.synchronize_device(env.device)
        t0 = time.perf_counter()
        images = latent.camera.render_torch(env.state_0, *env.hand_pose())
        wp.synchronize_device(env.device)
        t1 = time.perf_counter()
        z = latent.encoder(images)
        if z.device.type == "cuda":
            torch.cuda.synchronize(z.device)
        t2 = time.perf_counter()
        render += t1 - t0
        encode += t2 - t1
    r_ms, e_ms = render / calls * 1e3, encode / calls * 1e3
    p_ms = physics / calls * 1e3
    return {"num_worlds": num_worlds, "resolution": resolution, "preset": preset, "task": task,
            "camera": dataclasses.asdict(latent.spec), "device": env.device, "calls": calls,
            "render_ms": r_ms, "encode_ms": e_ms, "total_ms": r_ms + e_ms,
            "ms_per_world": (r_ms + e_ms) / num_worlds, "env_step_ms": p_ms, "vision_over_step": (r_ms + e_ms) / p_ms}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--num-worlds", type=int, nargs="+", default=[16, 128])
    ap.add_argument("--resolution", type=int, nargs="+", default=None,
                    help="Table 5.6's camera at these resolutions (default 64 256 without --preset)")
    ap.add_argument("--preset", nargs="+", default=None, help="vision presets' cameras (prepare.vision.VISION_PRESETS)")
    ap.add_argument("--task", default="PegInsert")
    ap.add_argument("--calls", type=int, default=3)
    add_device_option(ap)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = parse_cli(ap, argv, device=True)
    if args.json is not None and args.json.exists():
        ap.error(f"--json {args.json} exists; results are never overwritten")
    if min(args.num_worlds) < 1 or args.calls < 1:
        ap.error("--num-worlds and --calls must be >= 1")
    from ..tasks import TASKS
    from ..prepare.vision import VISION_PRESETS

    if args.task not in TASKS:
        ap.error(f"--task {args.task!r}; allowed: {', '.join(TASKS)}")
    for p in args.preset or ():
        if p not in VISION_PRESETS:
            ap.error(f"--preset {p!r}; allowed: {', '.join(VISION_PRESETS)}")
    if args.resolution is None and args.preset is None:
        args.resolution = [64, 256]
    for r in args.resolution or ():
        try:
            VAEConfig(resolution=r)
        except ValueError as e:
            ap.error(f"--resolution: {e}")
    torch.set_num_threads(args.threads)
    cameras = [(r, None) for r in args.resolution or ()] + [(None, p) for p in args.preset or ()]
    rows = []
    for n in args.num_worlds:
        for r, p in cameras:
            row = measure(n, r, args.calls, args.device, preset=p, task=args.task)
            rows.append(row)
            name = f"preset {p}" if p else "Table 5.6"
            print(f"{n:5d} worlds {row['resolution']:4d} px ({name}): render {row['render_ms']:9.1f} ms  "
                  f"encode {row['encode_ms']:8.1f} ms  total {row['total_ms']:9.1f} ms  "
                  f"({row['ms_per_world']:.2f} ms/world)  env step {row['env_step_ms']:8.1f} ms  "
                  f"vision/step {row['vision_over_step']:.2f}", flush=True)
    if args.json is not None:
        out = {"machine": platform.processor() or platform.machine(), "torch": torch.__version__,
               "threads": args.threads, "rows": rows}
        atomic_write_text(args.json, json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
