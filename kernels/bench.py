"""Kernel microbenchmarks: `python -m vkgrl_newton.kernels.bench [--json PATH]`.

Times every Warp kernel in this package against its torch implementation of the same
computation, for batch sizes (number of environments) 1, 128 and 4096 on every available
device (cpu, and cuda when present). Each timing is the median of --repeats runs after
--warmup runs, with the device synchronized around each run; inputs are allocated once,
outside the timed region. Prints a table and writes JSON.

On the CPU, Warp runs kernels on one thread, so torch is pinned to one thread too by default
(--torch-threads 1): a like-for-like comparison, and immune to the thread oversubscription
that makes multi-threaded torch timings on a busy 2-core machine swing by 50x.

A kernel joins the benchmark by adding a `Case` to `CASES`: a name and a setup function
(batch, device) -> (warp_fn, torch_fn), both zero-argument callables doing one batched call.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
import warp as wp

wp.config.quiet = True

from .kmp_horizon import kmp_horizon_pose, mat66f, vec6f


@dataclass(frozen=True)
class Case:
    name: str
    setup: Callable[[int, str], tuple[Callable[[], None], Callable[[], object]]]


def _torch_device(device: str) -> str:
    """torch's name of a warp device: 'cuda:N' is the same in both, warp's 'cpu' is torch's 'cpu'."""
    return device if device.startswith("cuda") else "cpu"


def setup_kmp_horizon(batch: int, device: str):
    """KMP horizon: 151-step tables (PegInsert grid), random actions, step indices and targets."""
    from ..kmp.tables import kmp_pose_torch

    tdev = _torch_device(device)
    g = torch.Generator().manual_seed(0)
    n_steps = 151
    mean = (torch.rand(n_steps, 6, generator=g) - 0.5) * 0.1
    gain = (torch.rand(n_steps, 6, 6, generator=g) - 0.5) * 1e-3
    zeta = (torch.rand(batch, 6, generator=g) - 0.5) * 300.0
    step_index = torch.randint(0, n_steps, (batch,), generator=g, dtype=torch.int32)
    target = torch.rand(batch, 3, generator=g)
    ref_quat = torch.nn.functional.normalize(torch.rand(batch, 4, generator=g) - 0.5, dim=1)
    mean, gain, zeta, step_index, target, ref_quat = (
        t.to(tdev).contiguous() for t in (mean, gain, zeta, step_index, target, ref_quat)
    )
    # warp views of the same torch memory (no copies), as the env will use them
    args = [
        wp.from_torch(step_index, dtype=wp.int32),
        wp.from_torch(zeta, dtype=vec6f),
        wp.from_torch(mean, dtype=vec6f),
        wp.from_torch(gain, dtype=mat66f),
        wp.from_torch(target, dtype=wp.vec3),
        wp.from_torch(ref_quat, dtype=wp.quat),
        wp.zeros(batch, dtype=vec6f, device=device),
        wp.zeros(batch, dtype=wp.vec3, device=device),
        wp.zeros(batch, dtype=wp.quat, device=device),
    ]

    def warp_fn():
        kmp_horizon_pose(*args)

    def torch_fn():
        return kmp_pose_torch(step_index, zeta, mean, gain, target, ref_quat)

    return warp_fn, torch_fn


CASES = [Case("kmp_horizon", setup_kmp_horizon)]


def _time(fn, device: str, warmup: int, repeats: int) -> float:
    sync = (lambda: wp.synchronize_device(device)) if device.startswith("cuda") else (lambda: None)
    tsync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    for _ in range(warmup):
        fn()
    sync()
    tsync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        tsync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass  # no /proc/cpuinfo (not Linux): keep platform's name
    info = dict(cpu=cpu, cores=os.cpu_count(), python=platform.python_version(), torch=torch.__version__,
                torch_threads=torch.get_num_threads(), warp=wp.config.version)
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, nargs="+", default=[1, 128, 4096], help="numbers of environments")
    p.add_argument("--devices", nargs="+", default=None, help="warp devices (default: cpu and cuda:0 if present)")
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--repeats", type=int, default=100)
    p.add_argument("--json", default="runs/bench/kernels.json", help="where to write the results")
    p.add_argument("--only", nargs="+", default=None, help=f"case names, from {[c.name for c in CASES]}")
    p.add_argument("--torch-threads", type=int, default=1, help="torch CPU threads (0: torch's default)")
    args = p.parse_args(argv)
    if args.torch_threads < 0:
        raise SystemExit(f"--torch-threads must be >= 0, got {args.torch_threads}")
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)

    wp.config.quiet = True
    wp.init()
    devices = args.devices or (["cpu"] + (["cuda:0"] if wp.is_cuda_available() else []))
    cases = [c for c in CASES if args.only is None or c.name in args.only]
    if args.only and len(cases) != len(args.only):
        raise SystemExit(f"--only: unknown case in {args.only}; cases are {[c.name for c in CASES]}")
    rows = []
    header = f"{'kernel':<14} {'device':<8} {'batch':>6} {'warp us':>10} {'torch us':>10} {'torch/warp':>10} {'Menv/s warp':>12}"
    print(header)
    print("-" * len(header))
    for case in cases:
        for device in devices:
            for batch in args.batch:
                with wp.ScopedDevice(device):
                    warp_fn, torch_fn = case.setup(batch, device)
                    t_warp = _time(warp_fn, device, args.warmup, args.repeats)
                    with torch.no_grad():
                        t_torch = _time(torch_fn, device, args.warmup, args.repeats)
                row = dict(kernel=case.name, device=device, batch=batch, warp_s=t_warp, torch_s=t_torch)
                rows.append(row)
                print(f"{case.name:<14} {device:<8} {batch:>6} {t_warp * 1e6:>10.1f} {t_torch * 1e6:>10.1f} "
                      f"{t_torch / t_warp:>10.2f} {batch / t_warp / 1e6:>12.3f}")
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = dict(machine=_machine(), warmup=args.warmup, repeats=args.repeats, rows=rows,
                  date=time.strftime("%Y-%m-%d %H:%M:%S"))
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(json.dumps(result, indent=2))
    os.replace(tmp, out)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
