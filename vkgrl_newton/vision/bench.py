"""Vision cost per control step: render every world's task camera, then encode with the frozen VAE.

    python -m vkgrl_newton.vision.bench --num-worlds 16 128 --resolution 64 256 --calls 3 --json runs/bench/vision.json

For each world count and resolution: a PegInsert env (Factory, 4D) after its reset, the task
camera of thesis Table 5.6 at that resolution (Newton's SensorCamera), and a VAE encoder of the
thesis's shape (5 conv layers, latent 16; untrained weights cost the same). Reported per call,
i.e. per control step of all worlds: render ms, encode ms, their sum, and per world. Timed
after one warm-up call; the device is synchronized around each stage. One torch thread unless
--threads says otherwise. An existing JSON file is never overwritten.
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

from .._io import atomic_write_text
from ..runtime import parse_cli
from .latent import CameraLatent
from .vae import DenoisingVAE, FrozenEncoder, VAEConfig


def measure(num_worlds: int, resolution: int, calls: int, device: str | None = None) -> dict:
    from ..envs.assembly_env import AssemblyEnv, EnvConfig

    env = AssemblyEnv(EnvConfig(num_envs=num_worlds, action_dim=4, family="factory", device=device))
    latent = CameraLatent(env, FrozenEncoder(DenoisingVAE(VAEConfig(resolution=resolution))))
    latent(env)  # warm-up: kernels, BVH build, allocator
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
    return {"num_worlds": num_worlds, "resolution": resolution, "device": env.device, "calls": calls,
            "render_ms": r_ms, "encode_ms": e_ms, "total_ms": r_ms + e_ms,
            "ms_per_world": (r_ms + e_ms) / num_worlds}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--num-worlds", type=int, nargs="+", default=[16, 128])
    ap.add_argument("--resolution", type=int, nargs="+", default=[64, 256])
    ap.add_argument("--calls", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = parse_cli(ap, argv, device=True)
    if args.json is not None and args.json.exists():
        ap.error(f"--json {args.json} exists; results are never overwritten")
    if min(args.num_worlds) < 1 or args.calls < 1:
        ap.error("--num-worlds and --calls must be >= 1")
    for r in args.resolution:
        try:
            VAEConfig(resolution=r)
        except ValueError as e:
            ap.error(f"--resolution: {e}")
    torch.set_num_threads(args.threads)
    rows = []
    for n in args.num_worlds:
        for r in args.resolution:
            row = measure(n, r, args.calls, args.device)
            rows.append(row)
            print(f"{n:5d} worlds {r:4d} px: render {row['render_ms']:9.1f} ms  encode {row['encode_ms']:8.1f} ms  "
                  f"total {row['total_ms']:9.1f} ms  ({row['ms_per_world']:.2f} ms/world)", flush=True)
    if args.json is not None:
        out = {"machine": platform.processor() or platform.machine(), "torch": torch.__version__,
               "threads": args.threads, "rows": rows}
        atomic_write_text(args.json, json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
